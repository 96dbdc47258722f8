"""Colour, written once: the tone map between linear HDR and the model's [-1, 1], the sRGB transfer,
and uint8 pictures for people.

Every function takes numpy arrays or torch tensors (``to_uint8`` and ``tonemap01``: tensors) and
keeps the input's dtype. torch is never imported here, so the render stage (bpy) and the
shard stage load this module without it.

* ``hdr_to_model`` / ``model_to_hdr``: the schema's map for HDR keys (pilight.data.schema.to_model).
  ``eps`` > 0 gives the physics terms' variant (pilight.relight.encoding.tonemap): the 1/2.2 power
  has an infinite slope at 0, so gradients through black pixels need the offset.
* ``tonemap01``: the same map onto [0, 1] display values, the space evaluation compares images in.
* ``linear_to_srgb`` / ``srgb_to_linear``: the sRGB curve (IEC 61966-2-1). sRGB appears only at the
  edges: photos in (pilight.photo), PNG previews out (``srgb_preview``, ``to_uint8``), and the
  sRGB albedo target of stage 1 (``intrinsics.albedo_space: srgb``).
"""

from __future__ import annotations

import numpy as np

HDR_MAX = 65504.0  # float16 max: the largest value a shard can hold (pilight.data.schema)

# --- linear HDR <-> model space -----------------------------------------------------------
# Fixed exposure, then Reinhard u / (1 + u), then a 1/2.2 power. Reinhard maps [0, inf) onto
# [0, 1) with no clipping and a closed-form inverse; the power spreads the codes like a display
# gamma so mid-gray 0.18 lands near 0 (-0.15) instead of crowding at -1. Exposure is fixed, not
# per image, so brightness differences between lights survive (relighting must learn them).
EXPOSURE = 1.0
GAMMA = 2.2
Y_MAX = 2.0 * (HDR_MAX / (1.0 + HDR_MAX)) ** (1.0 / GAMMA) - 1.0  # image of HDR_MAX


def hdr_to_model(x, exposure: float = EXPOSURE, eps: float = 0.0):
    """Linear HDR (ndarray or tensor, float32/64, >= 0) -> [-1, 1). 0 -> -1, 1 -> 0.46, 4 -> 0.81.
    ``eps``: added to the exposed value (0: the schema's map; the physics terms add a small one)."""
    u = x.clip(0.0, None) * exposure  # negatives are invalid input; clipping avoids NaN
    if eps:  # only when asked: the schema's map stays the very same operations
        u = u + eps
    return 2.0 * (u / (1.0 + u)) ** (1.0 / GAMMA) - 1.0


def model_to_hdr(y, exposure: float = EXPOSURE):
    """Exact inverse of `hdr_to_model` (to float precision). Out-of-range model outputs are
    clamped to [-1, hdr_to_model(HDR_MAX)] so the result is finite and storable as float16."""
    r = ((y.clip(-1.0, Y_MAX) + 1.0) / 2.0) ** GAMMA
    return r / (1.0 - r) / exposure


def tonemap01(x):
    """Linear HDR tensor -> [0, 1) display values (hdr_to_model + 1) / 2, in float32 at least
    (float16 EXR reads are promoted first)."""
    return (hdr_to_model(x.float()) + 1) / 2


REC709_LUMINANCE = (0.2126, 0.7152, 0.0722)  # linear RGB -> luminance (Rec. 709 / sRGB primaries)


# --- sRGB ---------------------------------------------------------------------------------
SRGB_KNEE = 0.0031308  # linear value where the curve turns from the line to the power law
SRGB_KNEE_ENCODED = 0.04045


def _where(cond, a, b):
    # torch.Tensor has the method (a.where(cond, b) = torch.where(cond, a, b)); numpy arrays do not.
    return a.where(cond, b) if hasattr(a, "where") else np.where(cond, a, b)


def linear_to_srgb(x):
    """Linear -> sRGB-encoded values (the curve only; callers clip). The power law reads x clamped at
    the knee, so gradients stay finite below it, where the line is taken anyway."""
    return _where(x <= SRGB_KNEE, 12.92 * x, 1.055 * x.clip(SRGB_KNEE, None) ** (1 / 2.4) - 0.055)


def srgb_to_linear(y):
    """sRGB-encoded -> linear values (the curve only; callers clip)."""
    return _where(y <= SRGB_KNEE_ENCODED, y / 12.92, ((y + 0.055) / 1.055) ** 2.4)


__all__ = [
    "HDR_MAX",
    "EXPOSURE",
    "GAMMA",
    "Y_MAX",
    "hdr_to_model",
    "model_to_hdr",
    "tonemap01",
    "REC709_LUMINANCE",
    "linear_to_srgb",
    "srgb_to_linear",
]
