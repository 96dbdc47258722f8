"""The evaluate stage's metrics files: numbers only, and a headline small enough for a terminal.

``metrics/evaluate.json`` holds every figure, and nothing but numbers: notes (why LPIPS is absent,
the conditions, colour spaces) go to reports/*.md, and a figure that does not exist this run is left
out, not written as null. ``metrics/headline.json`` holds the few figures a person compares two runs
on, flat, short keys, 3 decimals, so `dvc exp show` of two runs fits 120 columns one group
at a time (the README's calls):

    stage 1   albedo_db albedo_si albedo_inv normal_deg normal_med rough_mae metal_mae
    stage 2   <tier>_db <tier>_base_db <tier>_r2 <tier>_base_r2, tier = abs | rel | si

albedo: raw PSNR, si-PSNR and light-invariance PSNR (all dB); normals: mean and median angular error
(degrees); roughness and metallic: MAE; per relighting tier (pilight.eval.relight_tiers): the model's PSNR and
change_r2 on the mask, and the strongest baseline's (the best "baseline" method on that figure).
"""

from __future__ import annotations

import math
from typing import Any

from pilight.eval.relight_tiers import strongest_baseline

HEADLINE_DECIMALS = 3  # narrow columns (-0.047, not -0.04729); every figure has its full value in evaluate.json
STAGE1 = {  # headline key -> key of intrinsics.model
    "albedo_db": "albedo_psnr",
    "albedo_si": "albedo_si_psnr",
    "albedo_inv": "albedo_light_invariance_psnr",
    "normal_deg": "normal_mean_deg",
    "normal_med": "normal_median_deg",
    "rough_mae": "roughness_mae",
    "metal_mae": "metallic_mae",
}
TIER_KEYS = {"abs": "absolute", "rel": "relative", "si": "scale_invariant"}
STAGE2 = {"db": "psnr", "r2": "change_r2_mask"}  # headline suffix -> figure of a tier's method


def numbers_only(tree: Any, where: str = "metrics") -> Any:
    """``tree`` without its None leaves (and the dicts they empty); a ValueError naming the key for any
    leaf that is not a finite int or float (a string, a list, NaN: notes belong in the reports)."""
    if isinstance(tree, dict):
        out = {k: numbers_only(v, f"{where}.{k}") for k, v in tree.items() if v is not None}
        return {k: v for k, v in out.items() if v != {}}
    if isinstance(tree, bool) or not isinstance(tree, int | float):
        raise ValueError(f"{where}: {type(tree).__name__} {str(tree)[:60]!r} is not a number (notes go to reports)")
    if not math.isfinite(tree):
        raise ValueError(f"{where}: {tree} is not finite")
    return tree


def _round(x: float) -> float:
    return round(float(x), HEADLINE_DECIMALS)


def headline(intrinsics: dict, relight: dict) -> dict[str, float]:
    """The headline figures (module docstring) of the evaluate stage's two results; a figure absent
    from them (a domain not predicted, relighting skipped, a tier without a baseline) is left out."""
    out: dict[str, float | None] = {k: intrinsics.get("model", {}).get(v) for k, v in STAGE1.items()}
    for short, tier in TIER_KEYS.items():
        figures = relight.get(tier, {})
        for suffix, figure in STAGE2.items():
            out[f"{short}_{suffix}"] = figures.get("model", {}).get(figure)
            best = strongest_baseline(figures, tier, figure)
            out[f"{short}_base_{suffix}"] = best[1] if best else None
    return {k: _round(v) for k, v in out.items() if v is not None}
