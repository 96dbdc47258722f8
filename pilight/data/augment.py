"""Mirror augmentation: a left-right mirrored render is an exact render of the mirrored scene.

Mirroring the scene across the camera's vertical plane (x -> -x in camera space; see schema: x
right, y up, z to the camera) maps every image the schema holds to its left-right mirror: the
photo, albedo, roughness, metallic, mask, diffuse and specular shading, and the light ball, which
is rendered with the scene camera's orientation. Normals are vectors, so they also change sign in
x: (n_x, n_y, n_z) -> (-n_x, n_y, n_z). The mirrored sample then obeys every identity of the
original (A * D + S = I, the ball's Lambertian lookup D_calc), so it is free, physically exact data
for a model that sees only a few dozen scenes. Unlike a rotation it keeps "up" up, so the prior
that light comes from above survives.
"""

from __future__ import annotations

import torch

NORMAL_KEYS = ("normal",)  # vector maps: mirrored AND x negated


def hflip(maps: dict, flip: torch.Tensor) -> dict:
    """Mirror the samples where ``flip`` (B,) is true in every (B, C, H, W) tensor of ``maps``.

    Other entries (keys, metadata) pass through. Returns a new dict; the input is not modified."""
    flip = flip.bool()
    if flip.ndim != 1:
        raise ValueError(f"flip must be one bool per sample, got shape {tuple(flip.shape)}")
    out = dict(maps)
    if not bool(flip.any()):
        return out
    for key, x in maps.items():
        if not (isinstance(x, torch.Tensor) and x.ndim == 4):
            continue
        if x.shape[0] != flip.shape[0]:
            raise ValueError(f"{key!r} holds {x.shape[0]} samples but flip has {flip.shape[0]}")
        mirrored = x.flip(-1)
        if key in NORMAL_KEYS:
            mirrored = torch.cat([-mirrored[:, :1], mirrored[:, 1:]], dim=1)
        out[key] = torch.where(flip.to(x.device)[:, None, None, None], mirrored, x)
    return out
