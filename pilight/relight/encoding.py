"""How the relit branch's change is encoded, and the tone map the physics terms compare in.

`relight.form` target gain (ours; the physics-first form's relit branch too): the relit branch denoises the log ratio of display values,
G = log((u_b + GAIN_EPS) / (u_a + GAIN_EPS)) / GAIN_SCALE with u = (y + 1) / 2 of the schema's tone
map, and decodes to u_relit = (u_a + GAIN_EPS) exp(GAIN_SCALE G) - GAIN_EPS. "Copy the input" is the
zero prediction, and the input's texture enters multiplicatively: where only shading changes, G is
the shading ratio, free of texture. GAIN_EPS keeps black pixels finite: |G| <= GAIN_MAX.

``tonemap`` / ``to_linear``: the physics terms form A*D + S in linear HDR and compare after the
schema's tone map (pilight.relight.physics_terms). Decoded outputs are clamped to model values of at
most hdr_to_model(PHYS_HDR_MAX) before the inverse tone map, and the tone map adds TONEMAP_EPS (its
1/2.2 power has an infinite slope at 0), so gradients stay finite.
"""

from __future__ import annotations

import numpy as np
import torch

from pilight.data.colour import hdr_to_model, model_to_hdr

PHYS_HDR_MAX = 64.0
Y_PHYS = float(hdr_to_model(np.float64(PHYS_HDR_MAX)))
TONEMAP_EPS = 1e-6
GAIN_EPS = 0.05  # display-value floor of the gain target (u in [0, 1]; mid-gray 0.18 linear is u ~ 0.42)
GAIN_SCALE = 2.0  # G = log ratio / GAIN_SCALE: |G| <= log(1.05 / 0.05) / 2 = 1.52, the range of the other targets
GAIN_MAX = float(np.log((1.0 + GAIN_EPS) / GAIN_EPS) / GAIN_SCALE)


def gain_encode(y_b: torch.Tensor, y_a: torch.Tensor) -> torch.Tensor:
    """The gain target: model-space target y_b and input y_a ([-1, 1)) -> G (module docstring)."""
    u_b, u_a = (y_b.float() + 1) / 2, (y_a.float() + 1) / 2
    return torch.log((u_b.clamp_min(0) + GAIN_EPS) / (u_a.clamp_min(0) + GAIN_EPS)) / GAIN_SCALE


def gain_decode(g: torch.Tensor, y_a: torch.Tensor) -> torch.Tensor:
    """Inverse of gain_encode: G and the input y_a -> the relit image in model space [-1, 1)."""
    u_a = ((y_a.float() + 1) / 2).clamp_min(0)
    u = (u_a + GAIN_EPS) * torch.exp(GAIN_SCALE * g.float().clamp(-GAIN_MAX, GAIN_MAX)) - GAIN_EPS
    return 2 * u.clamp(0.0, 1.0 - 1e-6) - 1


def tonemap(x: torch.Tensor) -> torch.Tensor:
    """Linear HDR -> [-1, 1): the schema's hdr_to_model plus TONEMAP_EPS, a finite slope at 0 (for gradients)."""
    return hdr_to_model(x, eps=TONEMAP_EPS)


def to_linear(y: torch.Tensor) -> torch.Tensor:
    """Decoded model-space output -> linear HDR, clamped to [0, PHYS_HDR_MAX] (gradients stay finite)."""
    return model_to_hdr(y.clamp(-1.0, Y_PHYS))
