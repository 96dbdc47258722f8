"""Prediction folders made from the shards' own ground truth with the real writer (write_predictions), so an
evaluation test knows, by construction, what every figure must be."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import torch

from pilight.data.predictions import write_predictions
from pilight.data.shards import eval_dataset, intrinsics_dataset, make_loader

RELIT_SPLITS = ("", "_gt", "_abs", "_gt_abs", "_anchor", "_gt_anchor", "_anchor_abs", "_gt_anchor_abs")


def _hwc(t: torch.Tensor):
    return t.permute(1, 2, 0).contiguous().numpy()


def write_intrinsics_predictions(
    shards: Path, out: Path, albedo: Callable[[dict, int], torch.Tensor] | None = None
) -> Path:
    """data/intrinsics_pred for the test split: the ground truth, the albedo replaced by
    ``albedo(batch, i)`` when given."""
    items = []
    for b in make_loader(intrinsics_dataset(shards, "test", shuffle=False), 8):
        for i, key in enumerate(b["key"]):
            maps = {d: b[d][i] for d in ("albedo", "normal", "roughness", "metallic")}
            if albedo is not None:
                maps["albedo"] = albedo(b, i)
            items.append((key, {d: _hwc(v) for d, v in maps.items()}, b["meta"][i]))
    write_predictions(out, {"test": items}, {})
    return out


def write_relit(
    shards: Path,
    out: Path,
    relit: Callable[[str, dict, int], torch.Tensor],
    splits: tuple[str, ...] = RELIT_SPLITS,
    cross_only: tuple[str, ...] = ("_gt", "_gt_abs", "_gt_anchor", "_gt_anchor_abs"),
) -> Path:
    """data/relit holding test<suffix> for each of ``splits``: ``relit(suffix, batch, i)`` for each pair
    (only the cross-light pairs in ``cross_only`` splits, as the relight stage writes the `_gt` ones); the
    model's absolute split also carries the ground truth's D, S and albedo."""
    jobs: dict[str, list] = {f"test{s}": [] for s in splits}
    for b in make_loader(eval_dataset(shards, "test", "relight"), 8):
        for i, key in enumerate(b["key"]):
            identity = json.loads(b["meta_a"][i])["light"] == json.loads(b["meta_b"][i])["light"]
            for s in splits:
                if identity and s in cross_only:
                    continue
                maps = {"relit": _hwc(relit(s, b, i))}
                if s == "_abs":
                    maps |= {k: _hwc(b[f"{k}_b"][i]) for k in ("diffuse", "specular")} | {
                        "albedo": _hwc(b["albedo"][i])
                    }
                jobs[f"test{s}"].append((key, maps, "{}"))
    write_predictions(out, jobs, {"sampling": {"split": "test", "mode": "single_step"}, "conditions": "pred"})
    return out
