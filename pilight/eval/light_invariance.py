"""Albedo light-invariance: does stage 1 give one view the same albedo whatever light it is seen under?

The test split renders each view under several lights; the true albedo of a view is the same under
all of them, so an albedo predicted from each lighting should be too. For every two lightings i < j of
one view (scene, view), on the mask both share:

    PSNR(A_j, A_i)                      the raw agreement (a level that follows the light counts)
    PSNR(alpha* A_j, A_i),  alpha* = <A_i, A_j>_mask / <A_j, A_j>_mask      (one scale per pair)

each capped at PSNR_CAP, averaged over the pairs. The ground truth scores the cap in both. This is the
consistency across a collection of images that PI-Light's abstract claims for its cross-batch attention.
"""

from __future__ import annotations

import itertools
from collections import defaultdict

import torch

from pilight.eval.metrics import masked_psnr_per_image
from pilight.eval.scale_invariant import scaled_to


def same_view_pairs(metas: list[dict]) -> list[tuple[int, int]]:
    """(i, j) index pairs of samples that show one (scene, view) under two different lights, i's light
    before j's; each unordered pair of lightings once."""
    views: dict[tuple, list[int]] = defaultdict(list)
    for idx, m in enumerate(metas):
        views[(m["scene"], m["view"])].append(idx)
    pairs = []
    for members in views.values():
        members = sorted(members, key=lambda i: metas[i]["light"])
        pairs += [(i, j) for i, j in itertools.combinations(members, 2) if metas[i]["light"] != metas[j]["light"]]
    return pairs


def light_invariance(albedo: torch.Tensor, mask: torch.Tensor, metas: list[dict]) -> dict[str, float | int | None]:
    """{"psnr", "si_psnr", "pairs"} of (B, 3, H, W) albedos (any map in [0, 1]) whose i-th sample is
    described by ``metas[i]`` (scene, view, light); None without a view seen under two lights."""
    pairs = same_view_pairs(metas)
    if not pairs:
        return {"psnr": None, "si_psnr": None, "pairs": 0}
    i, j = (torch.tensor(x) for x in zip(*pairs))
    ref, other = albedo[i], albedo[j]
    both = (mask[i] > 0.5) & (mask[j] > 0.5)
    mean = lambda x: float(x[torch.isfinite(x)].mean()) if torch.isfinite(x).any() else None
    return {
        "psnr": mean(masked_psnr_per_image(other, ref, both)),
        "si_psnr": mean(masked_psnr_per_image(scaled_to(other, ref, both), ref, both)),
        "pairs": len(pairs),
    }
