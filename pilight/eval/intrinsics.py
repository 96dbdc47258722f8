"""Stage-1 evaluation on a held-out split: the model beside trivial baselines.

The paper's Table 1 layout: PSNR, SSIM and LPIPS for each intrinsic and their average, on
display values in [0, 1] (albedo as is, normal (n + 1) / 2, roughness and metallic as gray),
background and non-Principled pixels set to 0 in both prediction and ground truth (SSIM and
LPIPS need whole images; PSNR is over the masked pixels).  LPIPS only with local weights
(`evaluate.lpips_backbone`), else null with the reason.

Baselines (what a model must clearly beat):
- albedo: "the input image is the albedo" (linear image clipped to [0, 1]);
- normal: "every normal faces the camera" (0, 0, 1);
- roughness, metallic: "the training-set mean" over masked training pixels.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torchmetrics.functional.image import structural_similarity_index_measure

from pilight.data.predictions import read_predictions
from pilight.data.schema import DataError
from pilight.data.shards import intrinsics_dataset, make_loader
from pilight.eval.metrics import angular_errors, masked_mae, masked_psnr, normal_metrics

SCALARS = ("roughness", "metallic")
DOMAINS = ("albedo", "normal", "roughness", "metallic")


def display01(domain: str, x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """(B, C, H, W) map -> (B, 3, H, W) display values in [0, 1], zero off the mask."""
    y = (x + 1) / 2 if domain == "normal" else x
    y = y.expand(-1, 3, -1, -1) if y.shape[1] == 1 else y
    return y.clamp(0, 1) * (mask > 0.5)


def table1(pred: dict[str, torch.Tensor], gt: dict[str, torch.Tensor], mask: torch.Tensor, lpips=None) -> dict:
    """{domain: {psnr, ssim, lpips}} plus "average" over the predicted domains (the paper's Table 1)."""
    out: dict[str, dict] = {}
    for d in DOMAINS:
        if d not in pred:
            continue
        p, g = display01(d, pred[d], mask), display01(d, gt[d], mask)
        out[d] = {
            "psnr": masked_psnr(p, g, mask),
            "ssim": float(structural_similarity_index_measure(p, g, data_range=1.0)),
            "lpips": float(lpips(p, g).mean()) if lpips is not None else None,
        }
    if out:
        avg = lambda k: None if any(v[k] is None for v in out.values()) else sum(v[k] for v in out.values()) / len(out)
        out["average"] = {k: avg(k) for k in ("psnr", "ssim", "lpips")}
    return out


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
    lacking: dict[str, list[str]] = {k: [] for k in pr}
    for b in make_loader(intrinsics_dataset(shard_dir, split, shuffle=False), 8):
        for i, key in enumerate(b["key"]):
            for k in keys:
                gt[k].append(b[k][i])
            for d in pr:
                if d in preds.get(key, {}):
                    pr[d].append(torch.from_numpy(preds[key][d]).permute(2, 0, 1))
                else:
                    lacking[d].append(key)
    # A domain predicted for some images but not all is damage, not a subset (infer_intrinsics.domains):
    # scoring it on what is there, or not at all, would pass with a metric missing.
    for d, keys_without in lacking.items():
        if pr[d] and keys_without:
            raise DataError(
                f"{split} image(s) {keys_without[:3]} have no predicted {d} while {len(pr[d])} others "
                "do; rerun infer_intrinsics"
            )
    if not any(pr.values()):
        raise DataError(f"no stage-1 predictions for the {split} split; rerun infer_intrinsics")
    out = {f"gt_{k}": torch.stack(v) for k, v in gt.items()}
    out.update({f"pred_{k}": torch.stack(v) for k, v in pr.items() if len(v) == len(gt["image"])})
    return out


def evaluate_intrinsics(
    shard_dir: Path, pred_dir: Path, split: str = "test", lpips=None, grid_images: int = 0
) -> dict[str, dict]:
    """{method: {metric: value}} for the model and each baseline (None where not applicable);
    with ``grid_images`` > 0 also "grid": an input | ground truth | prediction uint8 image."""
    preds = read_predictions(pred_dir, split)
    d = _collect(Path(shard_dir), split, preds)
    mask = d["gt_mask"]
    means = train_means(Path(shard_dir))
    facing = torch.zeros_like(d["gt_normal"])
    facing[:, 2] = 1.0
    baseline = {
        "albedo_psnr": masked_psnr(d["gt_image"].clamp(0, 1), d["gt_albedo"], mask),
        **{f"normal_{k}": v for k, v in normal_metrics(angular_errors(facing, d["gt_normal"], mask)).items()},
        **{f"{k}_mae": masked_mae(torch.full_like(d[f"gt_{k}"], means[k]), d[f"gt_{k}"], mask) for k in SCALARS},
    }
    model: dict[str, float | None] = {}
    if "pred_albedo" in d:
        model["albedo_psnr"] = masked_psnr(d["pred_albedo"], d["gt_albedo"], mask)
    if "pred_normal" in d:
        model.update(
            {
                f"normal_{k}": v
                for k, v in normal_metrics(angular_errors(d["pred_normal"], d["gt_normal"], mask)).items()
            }
        )
    for k in SCALARS:
        if f"pred_{k}" in d:
            model[f"{k}_mae"] = masked_mae(d[f"pred_{k}"], d[f"gt_{k}"], mask)
    gt = {k: d[f"gt_{k}"] for k in DOMAINS}
    pred = {k: d[f"pred_{k}"] for k in DOMAINS if f"pred_{k}" in d}
    base_maps = {
        "albedo": d["gt_image"].clamp(0, 1),
        "normal": facing,
        **{k: torch.full_like(d[f"gt_{k}"], means[k]) for k in SCALARS},
    }
    out = {
        "model": model,
        "baseline": baseline,
        "train_means": means,
        "samples": int(mask.shape[0]),
        "table1": {"model": table1(pred, gt, mask, lpips), "baseline": table1(base_maps, gt, mask, lpips)},
    }
    if grid_images > 0 and pred:
        out["grid"] = grid(d["gt_image"][:grid_images], gt, pred, mask, grid_images)
    return out


def intrinsics_report(
    shard_dir: Path, pred_dir: Path, split: str = "test", lpips=None, lpips_note: str = "", grid_images: int = 0
) -> tuple[dict, str, np.ndarray | None]:
    """(metrics, markdown table, grid or None) of ``evaluate_intrinsics``, as the evaluate stage writes
    them; the metrics say why LPIPS is what it is (``lpips_note``)."""
    result = evaluate_intrinsics(shard_dir, pred_dir, split, lpips=lpips, grid_images=grid_images)
    result["lpips_note"] = lpips_note
    grid_image = result.pop("grid", None)
    return result, markdown_table(result, split), grid_image


def grid(image: torch.Tensor, gt: dict, pred: dict, mask: torch.Tensor, n: int) -> np.ndarray:
    """One row per image: input | (ground truth, prediction) for each predicted intrinsic, labelled."""
    from pilight.data.colour import to_uint8
    from pilight.eval.grids import labelled_grid

    domains = [d for d in DOMAINS if d in pred]
    rows = []
    for i in range(min(n, image.shape[0])):
        tiles = [to_uint8(image[i], hdr=True)]
        for d in domains:
            m = mask[i : i + 1]
            tiles += [to_uint8(display01(d, x[d][i : i + 1], m)[0], hdr=False) for x in (gt, pred)]
        rows.append(tiles)
    labels = ["input"] + [f"{d} {who}" for d in domains for who in ("truth", "model")]
    return labelled_grid(rows, labels)


def markdown_table(result: dict, split: str) -> str:
    rows = [
        ("albedo PSNR (dB) ↑", "albedo_psnr", "input image"),
        ("normal mean error (°) ↓", "normal_mean_deg", "facing camera"),
        ("normal median error (°) ↓", "normal_median_deg", "facing camera"),
        ("normal within 11.25° ↑", "normal_within_11.25", "facing camera"),
        ("normal within 22.5° ↑", "normal_within_22.5", "facing camera"),
        ("normal within 30° ↑", "normal_within_30.0", "facing camera"),
        ("roughness MAE ↓", "roughness_mae", "train mean"),
        ("metallic MAE ↓", "metallic_mae", "train mean"),
    ]
    fmt = lambda v: "n/a" if v is None else f"{v:.3f}"
    lines = [
        f"Stage 1 on the `{split}` split ({result['samples']} images, masked pixels)",
        "",
        "| metric | model | baseline | baseline is |",
        "|---|---|---|---|",
    ]
    lines += [
        f"| {name} | {fmt(result['model'].get(key))} | {fmt(result['baseline'].get(key))} | {what} |"
        for name, key, what in rows
    ]
    t1 = result.get("table1", {})
    if t1.get("model"):
        f2 = lambda v: "n/a" if v is None else f"{v:.3f}"
        lines += [
            "",
            "The paper's Table 1 layout (display values in [0, 1], background zeroed; LPIPS: "
            f"{result.get('lpips_note', 'n/a')})",
            "",
            "| intrinsic | PSNR ↑ | SSIM ↑ | LPIPS ↓ | baseline PSNR | baseline SSIM | baseline LPIPS |",
            "|---|---|---|---|---|---|---|",
        ]
        for d, m in t1["model"].items():
            b = t1["baseline"].get(d, {})
            lines.append(
                f"| {d} | {f2(m['psnr'])} | {f2(m['ssim'])} | {f2(m['lpips'])} | {f2(b.get('psnr'))} | "
                f"{f2(b.get('ssim'))} | {f2(b.get('lpips'))} |"
            )
    return "\n".join(lines) + "\n"
