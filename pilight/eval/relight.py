"""Stage-2 evaluation on a held-out split: relighting quality beside trivial baselines.

Images are compared TONE-MAPPED: y = schema.to_model(x) (fixed exposure, Reinhard, 1/2.2 power),
then (y + 1) / 2 in [0, 1]; PSNR (data range 1) and SSIM (torchmetrics.functional, Gaussian 11x11)
per image over the full frame (relighting is full-image, no mask; PSNR capped at 100 dB so identical
images stay valid JSON), averaged over pairs. Two settings:
relight (light a != light b) and reconstruction (a == b, the identity pairs).

Baselines:
- copy input: I_relit = image a (what a model ignoring the target light scores);
- analytic A * D_calc: ground-truth albedo times the Lambertian lookup of the TARGET ball with the
  ground-truth normals, times (1 - metallic) as in training (no specular, no shadows, black background).
Light-following (pilight.eval.light_following): change_r2 of every method on the full image and on
the mask, over the cross-light pairs (copying scores 0, the ground truth 1).
Light-following of the model with ground-truth conditions, and the probes' direction and
linearity, come from the relit folder's `<split>_gt` and `probes` splits (``light_following``).
The evaluate stage calls ``relight_report``: the split the relight stage wrote, or a skipped note.
With physics_first, ``identity_residual_relative`` is sum |I_relit - A_x D - S| / sum |I_relit| on the
mask, A_x being the albedo the model formed I_relit with (float16 EXRs: ~1e-3 at most).
Also: the decomposition residual mean |I_relit - A D_pred - S_pred| (linear HDR, ground-truth A)
of the model and of the ground truth (float16 shards: ~1e-3), PSNR of D_pred and S_pred, and the
paper's appendix check on the analytic shading: flipping the x channel of N should flip which
side of the image is brighter.
LPIPS (tone-mapped, full image) only with local weights (`evaluate.lpips_backbone`), else null
with the reason; nothing is downloaded.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from pilight.data.colour import to_uint8, tonemap01
from pilight.data.predictions import read_predictions
from pilight.data.schema import DataError
from pilight.data.shards import eval_dataset, make_loader
from pilight.eval.grids import labelled_grid
from pilight.eval.light_following import (
    PROBE_SPLIT,
    ChangeR2,
    cross_light,
    lr_asymmetry,
    probe_key,
    probe_scores,
    select_probes,
)
from pilight.eval.metrics import psnr_per_image, ssim_per_image
from pilight.physics import compose
from pilight.physics.calculated import diffuse_calculated

METHODS = ("model", "copy_input", "analytic_ad")
PROBE_COUNT_MAX = 64  # probes are re-selected in shard order; those the relight stage relit are scored


def grid_row(
    ball: torch.Tensor,
    image_a: torch.Tensor,
    image_b: torch.Tensor,
    pred: dict[str, torch.Tensor],
    gt_d: torch.Tensor,
    gt_s: torch.Tensor,
) -> list[np.ndarray]:
    """One cross-light pair as uint8 tiles, in GRID_COLUMNS order (D and S when the model has them)."""
    h = image_a.shape[-1]
    ball = torch.nn.functional.interpolate(ball[None].float(), size=(h, h), mode="nearest")[0]
    tiles = [ball, image_a, image_b, pred["relit"]]
    if "diffuse" in pred:
        tiles += [gt_d, pred["diffuse"], gt_s, pred["specular"]]
    return [to_uint8(tonemap01(t), hdr=False) for t in tiles]


GRID_COLUMNS = ("target ball", "input", "target", "model relit", "D truth", "D model", "S truth", "S model")


def evaluate_relight(
    shard_dir: Path, relit_dir: Path, split: str = "test", lpips=None, lpips_note: str = "", grid_pairs: int = 0
) -> dict:
    """Metrics (see the module docstring); with ``grid_pairs`` > 0 also "grid": that many cross-light
    pairs as a labelled uint8 image, columns as in GRID_COLUMNS."""
    relit = read_predictions(Path(relit_dir), split)
    info = json.loads((Path(relit_dir) / "index.json").read_text())
    rows: dict[str, dict[str, list[torch.Tensor]]] = {s: {} for s in ("relight", "reconstruction")}
    resid = {"model": [], "ground_truth": []}
    flip_a, flip_b = [], []
    grid_rows: list[list[np.ndarray]] = []
    change: dict[str, ChangeR2] = {}
    identity = {"abs": 0.0, "ref": 0.0}
    n = 0
    for b in make_loader(eval_dataset(shard_dir, split, "relight"), 8):
        keys = b["key"]
        missing = [k for k in keys if k not in relit]
        if missing:
            raise DataError(
                f"{relit_dir}: no relit prediction for pair(s) {missing[:3]}; rerun the relight stage "
                "on the current shards"
            )
        pred = {
            k: torch.stack([torch.from_numpy(relit[key][k]).permute(2, 0, 1) for key in keys])
            for k in ("relit", "diffuse", "specular", "albedo")
            if k in relit[keys[0]]
        }
        same = torch.tensor(
            [json.loads(a)["light"] == json.loads(c)["light"] for a, c in zip(b["meta_a"], b["meta_b"])]
        )
        d_calc = diffuse_calculated(b["ball_b"], b["normal"], b["mask"], b["metallic"])
        for i in torch.nonzero(~same).flatten().tolist()[: max(0, grid_pairs - len(grid_rows))]:
            grid_rows.append(
                grid_row(
                    b["ball_b"][i],
                    b["image_a"][i],
                    b["image_b"][i],
                    {k: v[i] for k, v in pred.items()},
                    b["diffuse_b"][i],
                    b["specular_b"][i],
                )
            )
        gt, u_in = tonemap01(b["image_b"]), tonemap01(b["image_a"])
        cands = {"model": pred["relit"], "copy_input": b["image_a"], "analytic_ad": b["albedo"] * d_calc}
        for name, img in cands.items():
            p = tonemap01(img)
            if (~same).any():
                change.setdefault(name, ChangeR2()).update(p[~same], gt[~same], u_in[~same], b["mask"][~same])
            for setting, sel in (("relight", ~same), ("reconstruction", same)):
                if sel.any():
                    r = rows[setting].setdefault(name, {"psnr": [], "ssim": [], "lpips": []})
                    r["psnr"].append(psnr_per_image(p[sel], gt[sel]))
                    r["ssim"].append(ssim_per_image(p[sel], gt[sel]))
                    if lpips is not None:
                        r["lpips"].append(lpips(p[sel], gt[sel]))
        if "diffuse" in pred:
            for k, g in (("diffuse", b["diffuse_b"]), ("specular", b["specular_b"])):
                r = rows.setdefault("components", {}).setdefault(k, {"psnr": []})
                r["psnr"].append(psnr_per_image(tonemap01(pred[k]), tonemap01(g)))
            res = (pred["relit"] - compose(b["albedo"], pred["diffuse"], pred["specular"])).abs()
            resid["model"].append(res.flatten(1).mean(1))
            if "albedo" in pred:  # physics_first: the identity with the albedo the model formed I_relit with
                m = b["mask"].expand_as(pred["relit"]) > 0.5
                own = (pred["relit"] - compose(pred["albedo"], pred["diffuse"], pred["specular"])).abs()
                identity["abs"] += float(own[m].sum())
                identity["ref"] += float(pred["relit"].abs()[m].sum())
        resid["ground_truth"].append(
            (b["image_b"] - compose(b["albedo"], b["diffuse_b"], b["specular_b"])).abs().flatten(1).mean(1)
        )
        flipped = b["normal"].clone()
        flipped[:, 0] *= -1
        flip_a.append(lr_asymmetry(d_calc, b["normal"], b["mask"]))
        flip_b.append(
            lr_asymmetry(diffuse_calculated(b["ball_b"], flipped, b["mask"], b["metallic"]), b["normal"], b["mask"])
        )
        n += len(keys)
    if n == 0:
        raise DataError(f"{shard_dir}: the {split} split has no relighting pairs")
    mean = lambda xs: float(torch.cat(xs).float().mean()) if xs else None
    out: dict = {
        "pairs": n,
        "conditions": info.get("conditions"),
        "sampling": info.get("sampling"),
        "space": "tone-mapped: (schema.to_model(x) + 1) / 2, full image",
        "lpips_note": lpips_note,
    }
    for setting in ("relight", "reconstruction"):
        out[setting] = {
            name: {m: mean(v) for m, v in r.items()} | {"pairs": len(torch.cat(r["psnr"]))}
            for name, r in rows[setting].items()
        }
    out["change_r2"] = {name: c.compute() for name, c in change.items()}
    out["identity_residual_relative"] = identity["abs"] / identity["ref"] if identity["ref"] > 0 else None
    out["light_following"] = light_following(shard_dir, relit_dir, split)
    out["components_psnr"] = {k: mean(r["psnr"]) for k, r in rows.get("components", {}).items()}
    out["residual_abs_mean"] = {k: mean(v) for k, v in resid.items()}
    a, c = torch.cat(flip_a), torch.cat(flip_b)
    lit = a.abs() > 0.01  # pairs with a visible left/right difference
    out["flip_check_d_calc"] = {
        "mean_abs_asymmetry_with_n": float(a.abs().mean()),
        "mean_abs_asymmetry_flipped": float(c.abs().mean()),
        "sign_flipped_fraction": float(((a * c) < 0)[lit].float().mean()) if lit.any() else None,
        "pairs_considered": int(lit.sum()),
        "what": "(R - L) / (R + L) of masked D_calc over right-/left-facing pixels (n_x > 0.2 / < -0.2 of the "
        "unflipped N); flipping N_x should flip the sign",
    }
    if grid_rows:
        out["grid"] = labelled_grid(grid_rows, list(GRID_COLUMNS[: len(grid_rows[0])]))
    return out


def relight_report(
    shard_dir: Path, relit_dir: Path, lpips=None, lpips_note: str = "", grid_pairs: int = 0
) -> tuple[dict, str | None, np.ndarray | None]:
    """(metrics, markdown table, grid) of what the relight stage wrote to ``relit_dir``, on the split its
    index records (``evaluate_relight``). Without ``relit_dir``/index.json (the relight stage has not run)
    the metrics are {"skipped": why} and there is no table or grid, so evaluate still reports stage 1."""
    index = Path(relit_dir) / "index.json"
    if not index.is_file():
        return {"skipped": f"{relit_dir}/index.json not found (run the relight stage)"}, None, None
    split = json.loads(index.read_text()).get("sampling", {}).get("split", "test")
    result = evaluate_relight(shard_dir, relit_dir, split, lpips=lpips, lpips_note=lpips_note, grid_pairs=grid_pairs)
    grid = result.pop("grid", None)
    return result, markdown_table(result, split), grid


def light_following(shard_dir: Path, relit_dir: Path, split: str) -> dict:
    """change_r2 of the model with ground-truth conditions (the relit folder's `<split>_gt`), and the
    probes' direction and linearity (its `probes`), where the relight stage wrote them."""
    index = json.loads((Path(relit_dir) / "index.json").read_text())
    out: dict = {}
    if f"{split}_gt" in index["splits"]:
        relit = read_predictions(Path(relit_dir), f"{split}_gt")
        r2 = ChangeR2()
        for b in make_loader(eval_dataset(shard_dir, split, "relight"), 8):
            b = cross_light(b)
            if b is None:
                continue
            missing = [k for k in b["key"] if k not in relit]
            if missing:
                raise DataError(
                    f"{relit_dir}: no {split}_gt prediction for pair(s) {missing[:3]}; rerun the relight stage"
                )
            pred = torch.stack([torch.from_numpy(relit[k]["relit"]).permute(2, 0, 1) for k in b["key"]])
            r2.update(tonemap01(pred), tonemap01(b["image_b"]), tonemap01(b["image_a"]), b["mask"])
        out["change_r2_gt_conditions"] = r2.compute()
    if PROBE_SPLIT in index["splits"]:
        probes = select_probes(make_loader(eval_dataset(shard_dir, split, "relight"), 8), PROBE_COUNT_MAX)
        relit = read_predictions(Path(relit_dir), PROBE_SPLIT)
        probes = [p for p in probes if probe_key(p, "target") in relit]
        out |= probe_scores(relit, probes)
    return out


def markdown_table(result: dict, split: str) -> str:
    fmt = lambda v: "n/a" if v is None else f"{v:.3f}"
    names = {
        "model": "model",
        "copy_input": "copy the input (baseline)",
        "analytic_ad": "A * D_calc, analytic (baseline)",
    }
    lines = [
        f"Stage 2 on the `{split}` split ({result['pairs']} pairs; conditions: {result['conditions']}); "
        f"PSNR/SSIM on tone-mapped [0, 1] images ({result['space']})",
        "",
        "| method | relight PSNR ↑ | relight SSIM ↑ | reconstruction PSNR ↑ | reconstruction SSIM ↑ | relight LPIPS ↓ |",
        "|---|---|---|---|---|---|",
    ]
    for key, name in names.items():
        r, c = result["relight"].get(key, {}), result["reconstruction"].get(key, {})
        lines.append(
            f"| {name} | {fmt(r.get('psnr'))} | {fmt(r.get('ssim'))} | {fmt(c.get('psnr'))} | {fmt(c.get('ssim'))} | "
            f"{fmt(r.get('lpips'))} |"
        )
    comp = result["components_psnr"]
    res = result["residual_abs_mean"]
    fl = result["flip_check_d_calc"]
    r2 = result.get("change_r2", {})
    lines += [
        "",
        "change_r2 (1 - sum (dp - dt)^2 / sum dt^2 of the change from the input; copy 0, truth 1): "
        + "; ".join(f"{names[k]} {fmt(v['full'])} full, {fmt(v['mask'])} mask" for k, v in r2.items() if k in names),
    ]
    lf = result.get("light_following", {})
    if lf:
        gt_r2 = lf.get("change_r2_gt_conditions") or {}
        lines += [
            "",
            f"Light-following of the model: change_r2 with ground-truth conditions {fmt(gt_r2.get('full'))} full, "
            f"{fmt(gt_r2.get('mask'))} mask; direction {fmt(lf.get('direction'))} over {lf.get('probes', 0)} probe "
            f"images (chance 0.5); linearity {fmt(lf.get('linearity'))} (truth 2); identity "
            f"|I - A_x D - S| / |I| on the mask {fmt(result.get('identity_residual_relative'))}.",
        ]
    lines += [
        "",
        f"- LPIPS: {result['lpips_note']}.",
        f"- D_pred PSNR {fmt(comp.get('diffuse'))}, S_pred PSNR {fmt(comp.get('specular'))} (tone-mapped).",
        f"- Residual mean |I - A D - S| (linear, ground-truth A): model {fmt(res.get('model'))}, "
        f"ground truth {fmt(res.get('ground_truth'))}.",
        f"- Flipped-normal check (analytic D_calc): mean |asymmetry| {fmt(fl['mean_abs_asymmetry_with_n'])} with N, "
        f"{fmt(fl['mean_abs_asymmetry_flipped'])} with N_x flipped; sign flipped in "
        f"{fmt(fl['sign_flipped_fraction'])} of {fl['pairs_considered']} pairs with |asymmetry| > 0.01. "
        "The model's D_pred version is in metrics/relight.json (flip_check_d_pred).",
    ]
    return "\n".join(lines) + "\n"
