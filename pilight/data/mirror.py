"""The left-right mirror of a map: what the mirrored scene's truth is, so a render's mirror is an exact
training sample (intrinsics.augment.flip) and an exact test-time symmetry (benchmarks/flip_average.py).
Every map flips along x; a normal map (camera space, x to the right) also has its x component negated."""

from __future__ import annotations

import torch

NORMAL_SIGN = (-1.0, 1.0, 1.0)  # x, y, z of a camera-space normal under the mirror


def mirrored(key: str, x: torch.Tensor) -> torch.Tensor:
    """Map ``x`` (..., C, H, W) named ``key`` mirrored left-right; ``key == "normal"`` also negates x."""
    y = x.flip(-1)
    if key == "normal":
        y = y * torch.tensor(NORMAL_SIGN, dtype=x.dtype, device=x.device).view(3, 1, 1)
    return y
