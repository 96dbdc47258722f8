"""Stage-1 evaluation on a held-out split: the model beside trivial baselines.

Baselines (what a model must clearly beat):
- albedo: "the input image is the albedo" (linear image clipped to [0, 1]);
- normal: "every normal faces the camera" (0, 0, 1);
- roughness, metallic: "the training-set mean" over masked training pixels.
"""

from __future__ import annotations

from pathlib import Path

import torch

from pilight.data.predictions import read_predictions
from pilight.data.shards import intrinsics_dataset, make_loader
from pilight.eval.metrics import albedo_psnr, angular_errors, masked_mae, normal_metrics

SCALARS = ("roughness", "metallic")


def train_means(shard_dir: Path) -> dict[str, float]:
    sums = {k: 0.0 for k in SCALARS}
    count = 0.0
    for b in make_loader(intrinsics_dataset(shard_dir, "train", shuffle=False), 8):
        m = b["mask"] > 0.5
        count += float(m.sum())
        for k in SCALARS:
            sums[k] += float(b[k][m].sum())
    return {k: sums[k] / count if count else 0.5 for k in SCALARS}


def _collect(shard_dir: Path, split: str, preds: dict) -> dict[str, torch.Tensor]:
    keys = ("image", "albedo", "normal", "roughness", "metallic", "mask")
    gt = {k: [] for k in keys}
    pr = {k: [] for k in ("albedo", "normal", "roughness", "metallic")}
    for b in make_loader(intrinsics_dataset(shard_dir, split, shuffle=False), 8):
        for i, key in enumerate(b["key"]):
            for k in keys:
                gt[k].append(b[k][i])
            for d in pr:
                if d in preds.get(key, {}):
                    pr[d].append(torch.from_numpy(preds[key][d]).permute(2, 0, 1))
    out = {f"gt_{k}": torch.stack(v) for k, v in gt.items()}
    out.update({f"pred_{k}": torch.stack(v) for k, v in pr.items() if len(v) == len(gt["image"])})
    return out


def evaluate_intrinsics(shard_dir: Path, pred_dir: Path, split: str = "test") -> dict[str, dict]:
    """{method: {metric: value}} for the model and each baseline (None where not applicable)."""
    preds = read_predictions(pred_dir, split)
    d = _collect(Path(shard_dir), split, preds)
    mask = d["gt_mask"]
    means = train_means(Path(shard_dir))
    facing = torch.zeros_like(d["gt_normal"])
    facing[:, 2] = 1.0
    baseline = {
        "albedo_psnr": albedo_psnr(d["gt_image"].clamp(0, 1), d["gt_albedo"], mask),
        **{f"normal_{k}": v for k, v in normal_metrics(angular_errors(facing, d["gt_normal"], mask)).items()},
        **{f"{k}_mae": masked_mae(torch.full_like(d[f"gt_{k}"], means[k]), d[f"gt_{k}"], mask) for k in SCALARS},
    }
    model: dict[str, float | None] = {}
    if "pred_albedo" in d:
        model["albedo_psnr"] = albedo_psnr(d["pred_albedo"], d["gt_albedo"], mask)
    if "pred_normal" in d:
        model.update({f"normal_{k}": v for k, v in normal_metrics(angular_errors(d["pred_normal"], d["gt_normal"], mask)).items()})
    for k in SCALARS:
        if f"pred_{k}" in d:
            model[f"{k}_mae"] = masked_mae(d[f"pred_{k}"], d[f"gt_{k}"], mask)
    return {"model": model, "baseline": baseline, "train_means": means, "samples": int(mask.shape[0])}


def markdown_table(result: dict, split: str) -> str:
    rows = [("albedo PSNR (dB) ↑", "albedo_psnr", "input image"), ("normal mean error (°) ↓", "normal_mean_deg", "facing camera"),
            ("normal median error (°) ↓", "normal_median_deg", "facing camera"),
            ("normal within 11.25° ↑", "normal_within_11.25", "facing camera"), ("normal within 22.5° ↑", "normal_within_22.5", "facing camera"),
            ("normal within 30° ↑", "normal_within_30.0", "facing camera"),
            ("roughness MAE ↓", "roughness_mae", "train mean"), ("metallic MAE ↓", "metallic_mae", "train mean")]
    fmt = lambda v: "n/a" if v is None else f"{v:.3f}"
    lines = [f"Stage 1 on the `{split}` split ({result['samples']} images, masked pixels)", "",
             "| metric | model | baseline | baseline is |", "|---|---|---|---|"]
    lines += [f"| {name} | {fmt(result['model'].get(key))} | {fmt(result['baseline'].get(key))} | {what} |" for name, key, what in rows]
    return "\n".join(lines) + "\n"
