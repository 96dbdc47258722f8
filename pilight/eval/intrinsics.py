"""Stage-1 evaluation on a held-out split: the model beside trivial baselines, graded as the field does.

The paper's Table 1 layout: PSNR, SSIM and LPIPS for each intrinsic and their average, on
display values in [0, 1] (albedo as is, normal (n + 1) / 2, roughness and metallic as gray),
background and non-Principled pixels set to 0 in both prediction and ground truth (SSIM and
LPIPS need whole images; PSNR is over the masked pixels).  LPIPS only with local weights
(`evaluate.lpips_backbone`), else absent, with the reason in the report.

Albedo, in linear [0, 1] on the mask, in the three ways the intrinsic-image field grades it
(pilight.eval.scale_invariant, Grosse et al. 2009):
- raw PSNR (pooled over the masked pixels of every image, maps clamped to [0, 1]);
- si-PSNR: each image first multiplied by its least-squares scale alpha* = <gt, est> / <est, est>
  on its mask (one scale per image, all channels), then as raw;
- LMSE: Grosse's local scale-invariant error (16 px windows, stride 8 at 128^2), per image, averaged;
- light-invariance (pilight.eval.light_invariance): PSNR and si-PSNR between the albedos predicted
  from two lightings of one view, averaged over every such pair of the split.

Baselines (what a model must clearly beat):
- albedo: "the input image is the albedo" (the linear image clipped to [0, 1]), in every albedo metric
  above;
- normal: "every normal faces the camera" (0, 0, 1);
- roughness, metallic: "the training-set mean" and "the training-set median" over masked training
  pixels (the median of a mostly non-metal set is 0: "nothing is metal").
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from pilight.data.layout import VIEW_MAPS
from pilight.data.predictions import read_predictions
from pilight.data.schema import DataError
from pilight.data.shard_reader import intrinsics_dataset, make_loader
from pilight.eval.light_invariance import light_invariance
from pilight.eval.metrics import (
    PSNR_CAP,
    angular_errors,
    masked_mae,
    masked_psnr,
    masked_ssim,
    mean_over_masked,
    normal_metrics,
)
from pilight.eval.scale_invariant import LMSE_STRIDE, LMSE_WINDOW, lmse, scaled_to
from pilight.params import DOMAINS

SCALARS = ("roughness", "metallic")


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
            "ssim": masked_ssim(p, g, mask),  # None, not 1.0, when every mask is empty (#36)
            "lpips": mean_over_masked(lpips(p, g).flatten(), mask) if lpips is not None else None,
        }
    if out:
        avg = lambda k: None if any(v[k] is None for v in out.values()) else sum(v[k] for v in out.values()) / len(out)
        out["average"] = {k: avg(k) for k in ("psnr", "ssim", "lpips")}
    return out


MEDIAN_BINS = 2**16 + 1  # the training median is read from a count over [0, 1] in steps of 2^-16


def median_from_counts(counts: torch.Tensor) -> float:
    """The median of values counted in MEDIAN_BINS bins over [0, 1] (bin k holds the value k / (bins - 1),
    so 0, 1/2, 1 are exact); for an even count the mean of the two middle values, as numpy's median."""
    n = int(counts.sum())
    cum = counts.cumsum(0)
    at = lambda rank: int(torch.searchsorted(cum, torch.tensor(rank, dtype=cum.dtype)))  # 1-based rank's bin
    lo, hi = at((n + 1) // 2), at(n // 2 + 1)
    return (lo + hi) / 2 / (len(counts) - 1)


def train_constants(shard_dir: Path) -> dict[str, dict[str, float]]:
    """{"mean": {roughness, metallic}, "median": {...}} over the masked pixels of the training split.
    The median comes from a MEDIAN_BINS count (to 2^-17; the shards are float16), so the pass holds no
    pixel list; 0.5 for both when the split has no masked pixel."""
    sums = {k: 0.0 for k in SCALARS}
    counts = {k: torch.zeros(MEDIAN_BINS, dtype=torch.int64) for k in SCALARS}
    n = 0
    for b in make_loader(intrinsics_dataset(shard_dir, "train", shuffle=False), 8):
        m = b["mask"] > 0.5
        n += int(m.sum())
        for k in SCALARS:
            v = b[k][m].double()
            sums[k] += float(v.sum())
            bins = (v.clamp(0, 1) * (MEDIAN_BINS - 1)).round().long()
            counts[k] += torch.bincount(bins, minlength=MEDIAN_BINS)
    if n == 0:
        return {"mean": dict.fromkeys(SCALARS, 0.5), "median": dict.fromkeys(SCALARS, 0.5)}
    return {
        "mean": {k: sums[k] / n for k in SCALARS},
        "median": {k: median_from_counts(counts[k]) for k in SCALARS},
    }


def _collect(shard_dir: Path, split: str, preds: dict) -> dict:
    keys = ("image", *VIEW_MAPS)
    gt = {k: [] for k in keys}
    metas: list[dict] = []
    pr = {k: [] for k in DOMAINS}
    lacking: dict[str, list[str]] = {k: [] for k in pr}
    for b in make_loader(intrinsics_dataset(shard_dir, split, shuffle=False), 8):
        for i, key in enumerate(b["key"]):
            for k in keys:
                gt[k].append(b[k][i])
            metas.append(json.loads(b["meta"][i]))
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
    out: dict = {f"gt_{k}": torch.stack(v) for k, v in gt.items()}
    out.update({f"pred_{k}": torch.stack(v) for k, v in pr.items() if len(v) == len(gt["image"])})
    out["metas"] = metas
    return out


def albedo_scores(est: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor, metas: list[dict]) -> dict:
    """raw PSNR, si-PSNR, LMSE against the truth and light-invariance across lightings (module docstring).
    An albedo lies in [0, 1]: every figure sees ``est`` clamped there (raw PSNR always did), so the scale
    is fitted to what is graded and si-PSNR >= raw PSNR."""
    est = est.clamp(0, 1)
    li = light_invariance(est, mask, metas)
    errors = lmse(est, gt, mask)
    return {
        "albedo_psnr": masked_psnr(est, gt, mask),
        "albedo_si_psnr": masked_psnr(scaled_to(est, gt, mask), gt, mask),
        "albedo_lmse": float(errors[errors.isfinite()].mean()) if errors.isfinite().any() else None,
        "albedo_light_invariance_psnr": li["psnr"],
        "albedo_light_invariance_si_psnr": li["si_psnr"],
    }


def evaluate_intrinsics(
    shard_dir: Path, pred_dir: Path, split: str = "test", lpips=None, grid_images: int = 0
) -> dict[str, dict]:
    """{"model": {metric: value}, "baselines": {baseline: {metric: value}}, ...} (None where not
    applicable); with ``grid_images`` > 0 also "grid": an input | ground truth | prediction uint8 image."""
    preds = read_predictions(pred_dir, split)
    d = _collect(Path(shard_dir), split, preds)
    mask, metas = d["gt_mask"], d["metas"]
    constants = train_constants(Path(shard_dir))
    facing = torch.zeros_like(d["gt_normal"])
    facing[:, 2] = 1.0
    constant_maps = {kind: {k: torch.full_like(d[f"gt_{k}"], v[k]) for k in SCALARS} for kind, v in constants.items()}
    baselines = {
        "input_image": albedo_scores(d["gt_image"].clamp(0, 1), d["gt_albedo"], mask, metas),
        "facing_camera": {
            f"normal_{k}": v for k, v in normal_metrics(angular_errors(facing, d["gt_normal"], mask)).items()
        },
        **{
            f"train_{kind}": {f"{k}_mae": masked_mae(maps[k], d[f"gt_{k}"], mask) for k in SCALARS}
            for kind, maps in constant_maps.items()
        },
    }
    model: dict[str, float | None] = {}
    if "pred_albedo" in d:
        model.update(albedo_scores(d["pred_albedo"], d["gt_albedo"], mask, metas))
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
    base_maps = {"albedo": d["gt_image"].clamp(0, 1), "normal": facing, **constant_maps["mean"]}
    out = {
        "model": model,
        "baselines": baselines,
        "train_constants": constants,
        "samples": int(mask.shape[0]),
        "light_invariance_pairs": light_invariance(d["gt_albedo"], mask, metas)["pairs"],
        "table1": {"model": table1(pred, gt, mask, lpips), "baseline": table1(base_maps, gt, mask, lpips)},
    }
    if grid_images > 0 and pred:
        out["grid"] = grid(d["gt_image"][:grid_images], gt, pred, mask, grid_images)
    return out


def intrinsics_report(
    shard_dir: Path, pred_dir: Path, split: str = "test", lpips=None, lpips_note: str = "", grid_images: int = 0
) -> tuple[dict, str, np.ndarray | None]:
    """(metrics, markdown table, grid or None) of ``evaluate_intrinsics``, as the evaluate stage writes
    them; the table says why LPIPS is what it is (``lpips_note``)."""
    result = evaluate_intrinsics(shard_dir, pred_dir, split, lpips=lpips, grid_images=grid_images)
    grid_image = result.pop("grid", None)
    return result, markdown_table(result, split, lpips_note), grid_image


def grid(image: torch.Tensor, gt: dict, pred: dict, mask: torch.Tensor, n: int) -> np.ndarray:
    """One row per image: input | (ground truth, prediction) for each predicted intrinsic, labelled."""
    from pilight.eval.grids import labelled_grid
    from pilight.pictures import to_uint8

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


# (row label, metric key, baseline key in result["baselines"], what the baseline is)
TABLE_ROWS = (
    ("albedo PSNR (dB) ↑", "albedo_psnr", "input_image", "input image"),
    ("albedo si-PSNR (dB) ↑", "albedo_si_psnr", "input_image", "input image"),
    ("albedo LMSE ↓", "albedo_lmse", "input_image", "input image"),
    ("albedo light-invariance PSNR (dB) ↑", "albedo_light_invariance_psnr", "input_image", "input image"),
    ("albedo light-invariance si-PSNR (dB) ↑", "albedo_light_invariance_si_psnr", "input_image", "input image"),
    ("normal mean error (°) ↓", "normal_mean_deg", "facing_camera", "facing camera"),
    ("normal median error (°) ↓", "normal_median_deg", "facing_camera", "facing camera"),
    ("normal within 11.25° ↑", "normal_within_11.25", "facing_camera", "facing camera"),
    ("normal within 22.5° ↑", "normal_within_22.5", "facing_camera", "facing camera"),
    ("normal within 30° ↑", "normal_within_30.0", "facing_camera", "facing camera"),
    ("roughness MAE ↓", "roughness_mae", "train_mean", "train mean"),
    ("roughness MAE ↓", "roughness_mae", "train_median", "train median"),
    ("metallic MAE ↓", "metallic_mae", "train_mean", "train mean"),
    ("metallic MAE ↓", "metallic_mae", "train_median", "train median"),
)


def markdown_table(result: dict, split: str, lpips_note: str = "") -> str:
    fmt = lambda v: "n/a" if v is None else f"{v:.3f}"
    const = result["train_constants"]
    lines = [
        f"Stage 1 on the `{split}` split ({result['samples']} images, masked pixels). Albedo in linear [0, 1]: "
        f"raw PSNR; si-PSNR after one least-squares scale per image on the mask; LMSE (Grosse et al. 2009) over "
        f"{LMSE_WINDOW} px windows with stride {LMSE_STRIDE}; light-invariance between the albedos predicted from "
        f"two lightings of one view ({result['light_invariance_pairs']} pairs; the truth scores the {PSNR_CAP:g} dB "
        "cap). Normals in camera space, degrees. Roughness and metallic in [0, 1]; train mean "
        f"{fmt(const['mean']['roughness'])} / {fmt(const['mean']['metallic'])}, train median "
        f"{fmt(const['median']['roughness'])} / {fmt(const['median']['metallic'])} (roughness / metallic).",
        "",
        "| metric | model | baseline | baseline is |",
        "|---|---|---|---|",
    ]
    lines += [
        f"| {name} | {fmt(result['model'].get(key))} | {fmt(result['baselines'][base].get(key))} | {what} |"
        for name, key, base, what in TABLE_ROWS
    ]
    t1 = result.get("table1", {})
    if t1.get("model"):
        lines += [
            "",
            f"The paper's Table 1 layout (display values in [0, 1], background zeroed; LPIPS: {lpips_note or 'n/a'})",
            "",
            "| intrinsic | PSNR ↑ | SSIM ↑ | LPIPS ↓ | baseline PSNR | baseline SSIM | baseline LPIPS |",
            "|---|---|---|---|---|---|---|",
        ]
        for d, m in t1["model"].items():
            b = t1["baseline"].get(d, {})
            lines.append(
                f"| {d} | {fmt(m['psnr'])} | {fmt(m['ssim'])} | {fmt(m['lpips'])} | {fmt(b.get('psnr'))} | "
                f"{fmt(b.get('ssim'))} | {fmt(b.get('lpips'))} |"
            )
    return "\n".join(lines) + "\n"
