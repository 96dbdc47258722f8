"""Stage-2 evaluation on a held-out split: relighting in three tiers beside baselines and oracles.

The tiers, methods and figures are pilight.eval.relight_tiers': ``absolute`` (the target ball as
rendered, the paper's setting), ``relative`` (the model told r = level(ball_b) / level(ball_a), the
product's setting, beside the exposure-matched copy I_a x r) and ``scale_invariant`` (each absolute
image x its least-squares scale against the target on the mask, linear HDR). Per method: PSNR, SSIM
(and LPIPS with local weights, `evaluate.lpips_backbone`; nothing is downloaded) of whole tone-mapped
images in [0, 1] (u = (schema.to_model(x) + 1) / 2; PSNR capped at 100 dB so identical images stay
valid JSON), change_r2 (pilight.eval.light_following) on the full image and on the mask, and the
level sd (linear HDR, mask), over the cross-light pairs (relight) and the identity pairs
(reconstruction) where the method's split holds them.

What the relight stage writes to the relit folder (pilight.eval.relit_pairs), per `<split>` of its
index's sampling: `<split>` and `<split>_gt` (the model, relative intensity, stage-1 / ground-truth
conditions), `<split>_abs` and `<split>_gt_abs` (absolute), `<split>_anchor`, `<split>_gt_anchor`,
`<split>_anchor_abs`, `<split>_gt_anchor_abs` (the zero-gain physics anchor, same four settings) and
`probes`. `<split>` and `<split>_abs` are required (a folder without `<split>_abs` predates relative
intensity: rerun the relight stage); the others are scored where present (the anchor exists with
relight.form physics_first, the `_gt` splits when the model's conditions are stage-1 predictions). Each
split present must hold every cross-light pair, and either every identity pair or none.

Checks on the model's ABSOLUTE split (where its D and S are in the truth's units): the decomposition
residual mean |I_relit - A D_pred - S_pred| (linear HDR, ground-truth A) of the model and of the
ground truth (float16 shards: ~1e-3), PSNR of D_pred and S_pred, and with physics_first the identity
``identity_residual_relative`` = sum |I_relit - A_x D - S| / sum |I_relit| on the mask, A_x being the
albedo the model formed I_relit with (float16 EXRs: ~1e-3 at most). The paper's appendix check on the
analytic shading: flipping the x channel of N should flip which side of the image is brighter. The
probes' direction and linearity come from the relit folder's `probes` split (``light_following``).
The evaluate stage calls ``relight_report``: the split the relight stage wrote, or nothing.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from pilight.data.colour import tonemap01
from pilight.data.predictions import read_predictions
from pilight.data.schema import DataError
from pilight.data.shard_reader import eval_dataset, make_loader
from pilight.eval.grids import labelled_grid
from pilight.eval.light_following import (
    PROBE_AZIMUTH_DEG,
    PROBE_ELEVATION_DEG,
    PROBE_SPLIT,
    lr_asymmetry,
    probe_key,
    probe_scores,
    select_probes,
)
from pilight.eval.metrics import PSNR_CAP, psnr_per_image
from pilight.eval.relight_tiers import (
    SPACES,
    TIER_METHODS,
    TIERS,
    MethodScores,
    Pairs,
    exposure_matched_copy,
    strongest_baseline,
    tier_image,
)
from pilight.physics import compose
from pilight.physics.calculated import diffuse_calculated
from pilight.pictures import to_uint8

PROBE_COUNT_MAX = 64  # probes are re-selected in shard order; those the relight stage relit are scored
ABSOLUTE, RELATIVE = "_abs", ""  # the model's split suffixes; the checks and the grid use ABSOLUTE
FULL_MAPS = ("relit", "diffuse", "specular", "albedo")  # read from the model's absolute split; "relit" elsewhere


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


def _read_relit(relit_dir: Path, split: str, maps: tuple[str, ...]) -> dict[str, dict[str, np.ndarray]]:
    """key -> {map: H x W x C} of one relit split, keeping only ``maps`` (eight splits stay small)."""
    return {k: {m: v[m] for m in maps if m in v} for k, v in read_predictions(relit_dir, split).items()}


def _stack(preds: dict, keys: list[str], name: str = "relit") -> torch.Tensor:
    return torch.stack([torch.from_numpy(preds[k][name]).permute(2, 0, 1) for k in keys])


def baseline_image(method, b: dict) -> torch.Tensor:
    """The linear HDR images of a method formed from the pairs of batch ``b`` themselves (no relit split)."""
    if method.name == "copy_input":
        return b["image_a"]
    if method.name == "exposure_matched_copy":
        return exposure_matched_copy(b["image_a"], b["ball_a"], b["ball_b"])
    if method.name == "analytic_ad":  # no specular, no shadows, black background
        return b["albedo"] * diffuse_calculated(b["ball_b"], b["normal"], b["mask"], b["metallic"])
    raise ValueError(f"no image for method {method.name!r}")


def evaluate_relight(shard_dir: Path, relit_dir: Path, split: str = "test", lpips=None, grid_pairs: int = 0) -> dict:
    """Metrics (see the module docstring), numbers only; with ``grid_pairs`` > 0 also "grid": that many
    cross-light pairs of the model's absolute split as a labelled uint8 image, columns as in GRID_COLUMNS."""
    relit_dir = Path(relit_dir)
    written = set(json.loads((relit_dir / "index.json").read_text())["splits"])
    for need in (split + RELATIVE, split + ABSOLUTE):
        if need not in written:
            raise DataError(
                f"{relit_dir}: no `{need}` split (it has {sorted(written)}); a folder without `{split}{ABSOLUTE}` "
                "predates relative intensity: rerun the relight stage"
            )
    suffixes = sorted({m.split_suffix for ms in TIER_METHODS.values() for m in ms if m.split_suffix is not None})
    relit = {
        sfx: _read_relit(relit_dir, split + sfx, FULL_MAPS if sfx == ABSOLUTE else ("relit",))
        for sfx in suffixes
        if split + sfx in written
    }
    scores: dict[str, dict[str, MethodScores]] = {t: {} for t in TIERS}
    instances: dict[tuple, MethodScores] = {}
    identity_held = {sfx: 0 for sfx in relit}
    rows: dict[str, list[torch.Tensor]] = {k: [] for k in ("diffuse", "specular", "model", "ground_truth")}
    flip_a, flip_b = [], []
    grid_rows: list[list[np.ndarray]] = []
    identity = {"abs": 0.0, "ref": 0.0}
    n = n_cross = 0
    for b in make_loader(eval_dataset(shard_dir, split, "relight"), 8):
        keys = b["key"]
        cross = torch.tensor(
            [json.loads(a)["light"] != json.loads(c)["light"] for a, c in zip(b["meta_a"], b["meta_b"])]
        )
        held = {}
        for sfx, preds in relit.items():
            held[sfx] = torch.tensor([k in preds for k in keys])
            lacking = [k for k, c, h in zip(keys, cross, held[sfx]) if c and not h]
            if lacking:
                raise DataError(
                    f"{relit_dir}: no `{split}{sfx}` prediction for cross-light pair(s) {lacking[:3]}; rerun the "
                    "relight stage on the current shards"
                )
            identity_held[sfx] += int((held[sfx] & ~cross).sum())
        pairs = Pairs.of(b["image_a"], b["image_b"], b["mask"], cross)
        graded: set[tuple] = set()
        for tier, methods in TIER_METHODS.items():
            for m in methods:
                if m.split_suffix is None:
                    sel = torch.ones(len(keys), dtype=torch.bool)
                elif m.split_suffix in relit:
                    sel = held[m.split_suffix]
                else:
                    continue  # not written this run (module docstring)
                # the same images graded the same way (the copy in the absolute and relative tiers) share
                # one MethodScores, updated once: SSIM is most of this stage's time
                same = (m.split_suffix if m.split_suffix is not None else m.name, tier == "scale_invariant")
                shared = scores[tier][m.name] = instances.setdefault(same, MethodScores())
                if same in graded:
                    continue
                graded.add(same)
                img = (
                    baseline_image(m, b)
                    if m.split_suffix is None
                    else _stack(relit[m.split_suffix], [k for k, h in zip(keys, sel) if h])
                )
                view = pairs.select(sel)
                shared.update(tier_image(tier, img, view.target, view.mask), view, lpips)
        own = relit[ABSOLUTE]
        pred = {k: _stack(own, keys, k) for k in FULL_MAPS if k in own[keys[0]]}
        d_calc = diffuse_calculated(b["ball_b"], b["normal"], b["mask"], b["metallic"])
        for i in torch.nonzero(cross).flatten().tolist()[: max(0, grid_pairs - len(grid_rows))]:
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
        if "diffuse" in pred:
            for k, g in (("diffuse", b["diffuse_b"]), ("specular", b["specular_b"])):
                rows[k].append(psnr_per_image(tonemap01(pred[k]), tonemap01(g)))
            res = (pred["relit"] - compose(b["albedo"], pred["diffuse"], pred["specular"])).abs()
            rows["model"].append(res.flatten(1).mean(1))
            if "albedo" in pred:  # physics_first: the identity with the albedo the model formed I_relit with
                m = b["mask"].expand_as(pred["relit"]) > 0.5
                formed = (pred["relit"] - compose(pred["albedo"], pred["diffuse"], pred["specular"])).abs()
                identity["abs"] += float(formed[m].sum())
                identity["ref"] += float(pred["relit"].abs()[m].sum())
        rows["ground_truth"].append(
            (b["image_b"] - compose(b["albedo"], b["diffuse_b"], b["specular_b"])).abs().flatten(1).mean(1)
        )
        flipped = b["normal"].clone()
        flipped[:, 0] *= -1
        flip_a.append(lr_asymmetry(d_calc, b["normal"], b["mask"]))
        flip_b.append(
            lr_asymmetry(diffuse_calculated(b["ball_b"], flipped, b["mask"], b["metallic"]), b["normal"], b["mask"])
        )
        n += len(keys)
        n_cross += int(cross.sum())
    if n == 0:
        raise DataError(f"{shard_dir}: the {split} split has no relighting pairs")
    for sfx, count in identity_held.items():
        if 0 < count < n - n_cross:
            raise DataError(
                f"{relit_dir}: `{split}{sfx}` holds {count} of the {n - n_cross} identity pairs (all or none); "
                "rerun the relight stage"
            )
    mean = lambda xs: float(torch.cat(xs).float().mean())
    out: dict = {"pairs": n, "cross_light_pairs": n_cross, "identity_pairs": n - n_cross}
    out |= {tier: {name: s.compute() for name, s in methods.items()} for tier, methods in scores.items()}
    if identity["ref"] > 0:
        out["identity_residual_relative"] = identity["abs"] / identity["ref"]
    if following := light_following(shard_dir, relit_dir, split):
        out["light_following"] = following
    out["components_psnr"] = {k: mean(rows[k]) for k in ("diffuse", "specular") if rows[k]}
    out["residual_abs_mean"] = {k: mean(rows[k]) for k in ("model", "ground_truth") if rows[k]}
    a, c = torch.cat(flip_a), torch.cat(flip_b)
    lit = a.abs() > 0.01  # pairs with a visible left/right difference
    out["flip_check_d_calc"] = {
        "mean_abs_asymmetry_with_n": float(a.abs().mean()),
        "mean_abs_asymmetry_flipped": float(c.abs().mean()),
        "pairs_considered": int(lit.sum()),
    }
    if lit.any():
        out["flip_check_d_calc"]["sign_flipped_fraction"] = float(((a * c) < 0)[lit].float().mean())
    if grid_rows:
        out["grid"] = labelled_grid(grid_rows, list(GRID_COLUMNS[: len(grid_rows[0])]))
    return out


def relight_report(
    shard_dir: Path, relit_dir: Path, lpips=None, lpips_note: str = "", grid_pairs: int = 0
) -> tuple[dict, str | None, np.ndarray | None]:
    """(metrics, markdown tables, grid) of what the relight stage wrote to ``relit_dir``, on the split its
    index records (``evaluate_relight``). Without ``relit_dir``/index.json (the relight stage has not run)
    the metrics are {} and there is no table or grid, so evaluate still reports stage 1."""
    index = Path(relit_dir) / "index.json"
    if not index.is_file():
        return {}, None, None
    info = json.loads(index.read_text())
    split = info.get("sampling", {}).get("split", "test")
    result = evaluate_relight(shard_dir, relit_dir, split, lpips=lpips, grid_pairs=grid_pairs)
    grid = result.pop("grid", None)
    return result, markdown_table(result, split, info, lpips_note), grid


def light_following(shard_dir: Path, relit_dir: Path, split: str) -> dict:
    """The probes' direction and linearity (pilight.eval.light_following), numbers only, where the relight
    stage wrote its `probes` split; {} otherwise. (change_r2 with ground-truth conditions is the tiers'
    ``model_gt``.)"""
    index = json.loads((Path(relit_dir) / "index.json").read_text())
    if PROBE_SPLIT not in index["splits"]:
        return {}
    probes = select_probes(make_loader(eval_dataset(shard_dir, split, "relight"), 8), PROBE_COUNT_MAX)
    relit = read_predictions(Path(relit_dir), PROBE_SPLIT)
    probes = [p for p in probes if probe_key(p, "target") in relit]
    return {k: v for k, v in probe_scores(relit, probes).items() if isinstance(v, int | float)}


COLUMNS = (  # (figure, column heading); LPIPS columns join when a figure has them
    ("psnr", "PSNR ↑"),
    ("ssim", "SSIM ↑"),
    ("change_r2_full", "change_r2 full ↑"),
    ("change_r2_mask", "change_r2 mask ↑"),
    ("change_r2_mask_pair_median", "change_r2 mask, pair median ↑"),
    ("level_sd", "level sd ↓"),
    ("reconstruction_psnr", "reconstr. PSNR ↑"),
    ("reconstruction_ssim", "reconstr. SSIM ↑"),
)
LPIPS_COLUMNS = (("lpips", "LPIPS ↓"), ("reconstruction_lpips", "reconstr. LPIPS ↓"))
TIER_TITLES = {
    "absolute": "Absolute: the target ball as rendered (the paper's setting)",
    "relative": "Relative: the model told r = level(ball_b) / level(ball_a) (the product's setting)",
    "scale_invariant": "Scale-invariant: each absolute-mode image x its least-squares scale s* (structure only)",
}


def tier_table(tier: str, figures: dict[str, dict]) -> list[str]:
    """One tier's markdown table, methods as rows (those the relit folder had), then its strongest baselines."""
    fmt = lambda v: "n/a" if v is None else f"{v:.3f}"
    columns = COLUMNS + tuple(c for c in LPIPS_COLUMNS if any(c[0] in f for f in figures.values()))
    lines = [
        f"### {TIER_TITLES[tier]}",
        "",
        f"Space: {SPACES[tier]}; PSNR, SSIM and change_r2 on tone-mapped u = (to_model(x) + 1) / 2 in [0, 1] "
        "(fixed exposure, Reinhard, 1/2.2 power), PSNR/SSIM of whole images, change_r2 pooled over pixels of the "
        "full image or the mask; level sd in linear HDR on the mask.",
        "",
        "| method | kind | " + " | ".join(h for _, h in columns) + " |",
        "|---|---|" + "---|" * len(columns),
    ]
    for m in TIER_METHODS[tier]:
        if m.name in figures:
            f = figures[m.name]
            lines.append(f"| {m.label} | {m.kind} | " + " | ".join(fmt(f.get(k)) for k, _ in columns) + " |")
    labels = {m.name: m.label for m in TIER_METHODS[tier]}
    best = [
        f"{heading.split(' ↑')[0]}: {labels[found[0]]} ({fmt(found[1])})"
        for figure, heading in (("psnr", "PSNR ↑"), ("change_r2_mask", "change_r2 mask ↑"))
        if (found := strongest_baseline(figures, tier, figure)) is not None
    ]
    if best:
        lines += ["", "Strongest baseline: " + "; ".join(best) + "."]
    return lines


def markdown_table(result: dict, split: str, info: dict | None = None, lpips_note: str = "") -> str:
    """reports/relight.md: the three tiers as tables, then light-following and the model's checks."""
    fmt = lambda v: "n/a" if v is None else f"{v:.3f}"
    info = info or {}
    sampling = info.get("sampling", {})
    how = ", ".join(f"{k} {sampling[k]}" for k in ("mode", "steps", "cfg_scale", "ensemble") if k in sampling)
    lines = [
        f"Stage 2 on the `{split}` split: {result['pairs']} pairs ({result['cross_light_pairs']} cross-light: "
        f"relight; {result['identity_pairs']} identity: reconstruction). The model's conditions: "
        f"{info.get('conditions', 'n/a')} (pred = stage-1 predictions); sampling: {how or 'n/a'}. "
        f"PSNR is capped at {PSNR_CAP:g} dB (identical images). Kinds: baseline = needs nothing the model is not "
        "given; oracle = uses ground truth at test time.",
        "",
    ]
    for tier in TIERS:
        if result.get(tier):
            lines += tier_table(tier, result[tier]) + [""]
    lf = result.get("light_following", {})
    comp = result.get("components_psnr", {})
    res = result.get("residual_abs_mean", {})
    fl = result["flip_check_d_calc"]
    lines += [
        "### Light-following of the model, and its checks",
        "",
        f"- Probes: direction {fmt(lf.get('direction'))} over {lf.get('probes', 0)} probe images: the share whose "
        "relit left/right asymmetry (ground-truth normals, mask) is larger under an analytic light from "
        f"camera-right than from camera-left (azimuth ±{PROBE_AZIMUTH_DEG:g}°, elevation {PROBE_ELEVATION_DEG:g}°; "
        f"chance 0.5); linearity {fmt(lf.get('linearity'))}: the median relit radiance ratio under the target "
        "ball x 2 and x 1 (mask; truth 2).",
        f"- Identity |I - A_x D - S| / |I| on the mask (absolute split): {fmt(result.get('identity_residual_relative'))}.",
        f"- LPIPS: {lpips_note or 'n/a'}.",
        f"- D_pred PSNR {fmt(comp.get('diffuse'))}, S_pred PSNR {fmt(comp.get('specular'))} (tone-mapped, "
        "absolute split).",
        f"- Residual mean |I - A D - S| (linear, ground-truth A, absolute split): model {fmt(res.get('model'))}, "
        f"ground truth {fmt(res.get('ground_truth'))}.",
        "- Flipped-normal check (analytic D_calc): (R - L) / (R + L) of masked D_calc over right-/left-facing "
        "pixels (n_x > 0.2 / < -0.2 of the unflipped N); mean |asymmetry| "
        f"{fmt(fl['mean_abs_asymmetry_with_n'])} with N, {fmt(fl['mean_abs_asymmetry_flipped'])} with N_x "
        f"flipped; sign flipped in {fmt(fl.get('sign_flipped_fraction'))} of {fl['pairs_considered']} pairs with "
        "|asymmetry| > 0.01. The model's D_pred version is in metrics/relight.json (flip_check_d_pred).",
    ]
    return "\n".join(lines) + "\n"
