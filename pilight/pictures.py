"""Linear HDR values as 8-bit pictures for people, written once: PNG previews, report tiles, the CLI's
outputs and contact sheets. Never a model input (those are pilight.data.colour's tone map and the sRGB
curve). sRGB-encoded values clip at 1."""

from __future__ import annotations

import numpy as np

from pilight.data.colour import linear_to_srgb


def srgb_preview(x: np.ndarray) -> np.ndarray:
    """Linear values -> sRGB uint8 for PNG previews only (clips at 1; never a model input)."""
    x = np.clip(np.asarray(x, dtype=np.float32), 0.0, 1.0)
    return np.round(linear_to_srgb(x) * 255.0).astype(np.uint8)


def to_uint8(x, hdr: bool) -> np.ndarray:
    """C x H x W tensor -> H x W x 3 uint8 preview (``hdr``: srgb_preview, clipped at 1; else the
    [0, 1] values as they are, e.g. ``tonemap01`` of an HDR image). For report tiles and training
    previews only."""
    a = x.detach().float().cpu().numpy().transpose(1, 2, 0)
    if a.shape[2] == 1:
        a = np.repeat(a, 3, axis=2)
    return srgb_preview(a) if hdr else (np.clip(a, 0, 1) * 255 + 0.5).astype(np.uint8)


def linear_to_srgb8(x: np.ndarray, alpha: np.ndarray | None = None) -> np.ndarray:
    """Linear values (clipped at 1) -> sRGB uint8 (H, W, 3), or (H, W, 4) with ``alpha`` (H, W) in [0, 1]."""
    x = np.asarray(x, dtype=np.float32)
    if x.ndim == 2:
        x = x[..., None]
    if x.shape[2] == 1:
        x = np.repeat(x, 3, axis=2)
    out = srgb_preview(x)
    if alpha is not None:
        out = np.concatenate([out, np.round(np.clip(alpha, 0, 1) * 255)[..., None].astype(np.uint8)], axis=2)
    return out


def normal_preview(n: np.ndarray, alpha: np.ndarray | None = None) -> np.ndarray:
    """Unit normals (H, W, 3) -> the usual RGB picture (n + 1) / 2, stored as is (not sRGB-encoded)."""
    u8 = np.round(np.clip((np.asarray(n, np.float32) + 1) / 2, 0, 1) * 255).astype(np.uint8)
    if alpha is not None:
        u8 = np.concatenate([u8, np.round(np.clip(alpha, 0, 1) * 255)[..., None].astype(np.uint8)], axis=2)
    return u8


def _srgb8_truncated(x: np.ndarray) -> np.ndarray:
    # +0.5 and truncation, not srgb_preview's round-half-even: the bytes of every preview.png so far.
    return (linear_to_srgb(np.clip(x, 0.0, 1.0)) * 255.0 + 0.5).astype(np.uint8)


# A 16-bit lookup table: 4x faster than the power law per preview, within one code value of it.
_SRGB_LUT = _srgb8_truncated(np.linspace(0.0, 1.0, 65536))


def srgb8_preview_lut(x: np.ndarray) -> np.ndarray:
    """Linear values -> sRGB uint8 through the table (the render stage's previews)."""
    return _SRGB_LUT[(np.clip(x, 0.0, 1.0) * 65535.0 + 0.5).astype(np.uint16)]
