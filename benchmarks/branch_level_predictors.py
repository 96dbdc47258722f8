"""Can anything we have predict stage 2's gain levels per image? Candidates scored against the oracle.

    python benchmarks/branch_level_predictors.py --model weights/pilight-base/relight --shards <shards>
        [--pred <stage-1 predictions>] [--fit-shards <shards> --fit-split train [--fit-pred <predictions>]]
        [--folds 6]
        [--light-level estimated|rendered] [--source-shading estimated|rendered] [--json FILE]

Stage 2's D and S branches are gains g_D, g_S on their physics anchors (pilight.relight.physics_first).
Moving the model's g_D to the true gains' mean on the mask of each image (one number per image) lifts the
relative tier's change_r2 on the mask by +0.13 to +0.15 (benchmarks/stage2_branch_errors.py, "model +
level"); g_S's level is worth as much again. This asks whether those numbers can be predicted from what
inference has. Per cross-light pair (relative intensity, single step) it gathers each branch's true level
l = mean_mask(g target), the model's own level, inference-time
physics features (the anchors' brightness per unit light, the two source-light fits, the backdrop, the
albedo, the balls' first-order directions) and pooled UNet features (mean and spread of the mid block and
the last down block, per branch item: what a level head on the network would read). Predictors:

* model: its own level; calibrated: a + b x its level; train mean: a constant;
* physics features / UNet features: ridge regressions on them (standardised, weight ``--ridge``);
* truth: the oracle.

Each is fitted per branch on ``--fit-shards`` (its ``--fit-split``, conditioned on ``--fit-pred``'s stage-1
maps when given, else ground truth) when given, otherwise by scene-grouped
``--folds``-fold cross-validation on the scored shards (no scene in both the fit and its scoring). Printed
per predictor: each level's R^2, and the pooled change_r2 on the mask with the model's D gains, its S
gains, or both moved to the predicted levels (the other branch: the model's).

``--light-level rendered`` gives the model the target ball at its rendered level instead of the relative
ball scaled to the input's estimated light (pilight.relight.intensity), ``--source-shading rendered`` the
rendered ball of light a for the effective albedo instead of its estimate (pilight.physics.source_light):
both together split the level into what the source light's estimate gets wrong and what the scene adds.
Neither is available for a photo. The scored pairs are held in memory (about 1.5 MB each at 128 px).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

from stage2_branch_errors import level_per_image, load, masked_mean, pair_gains  # noqa: E402

BRANCHES = {"D": 1, "S": 2}  # the physics-first gains' items in the stage-2 stack (relit, D, S)

PROBED = ("mid_block", "down_blocks.-1")  # the UNet blocks a level head would read
LOG_FEATURES = ("fb", "fa", "level9_over_level1", "backdrop", "input_over_fit", "albedo", "albedo_eff")


def moved_to_level(g: torch.Tensor, mask: torch.Tensor, level: torch.Tensor) -> torch.Tensor:
    """Gains (B, C, H, W) shifted so that their mean on the mask is ``level`` (B,): the shape kept."""
    return g - level_per_image(g, mask) + level.to(g.dtype).view(-1, 1, 1, 1)


def first_order_direction(ball: torch.Tensor) -> torch.Tensor:
    """(B, 3): the ball's luminance-weighted mean normal over its disk (where its light comes from)."""
    from pilight.physics.envmap import ball_normals

    n, disk = ball_normals(*ball.shape[-2:], device=ball.device)
    w = ball.float().mean(1) * disk[0, 0]
    return (n[0][None] * w[:, None]).sum((-1, -2)) / w.sum((-1, -2)).clamp_min(1e-9)[:, None]


def physics_features(batch: dict, intr: dict, anc, ball_b: torch.Tensor) -> dict[str, torch.Tensor]:
    """{name: (B,)} what inference knows of a pair without the network (module docstring)."""
    from pilight.physics.calculated import diffuse_calculated
    from pilight.physics.envmap import light_level
    from pilight.relight import physics_first as pf

    img, mask = batch["image_a"].float(), batch["mask"].float()
    m = (mask[:, :1] > 0.5).float()
    size = ball_b.shape[-1]
    ball9, _ = pf.source_balls(img, intr, mask, size)
    ball1, _ = pf.source_balls(img, intr, mask, size, level=True)
    level9, level1 = light_level(ball9).flatten(), light_level(ball1).flatten()
    d_a = diffuse_calculated(ball9, intr["normal"].float(), mask, intr["metallic"].float())
    lum = lambda x: x.mean(1, keepdim=True)
    f = {
        "fb": masked_mean(lum(anc.d_calc), m) / anc.level.flatten(),  # how much of light b the camera sees lit
        "fa": masked_mean(lum(d_a), m) / level9,
        "level9_over_level1": level9 / level1,
        "backdrop": masked_mean(lum(img), 1 - m) / level1,
        "input_over_fit": masked_mean(lum(img), m) / masked_mean(lum(intr["albedo"].float() * d_a), m).clamp_min(1e-9),
        "albedo": masked_mean(lum(intr["albedo"].float()), m),
        "albedo_eff": masked_mean(lum(anc.albedo), m),
        "mask_share": m.flatten(1).mean(1),
        "metal_share": masked_mean((intr["metallic"][:, :1].float() > 0.5).float(), m),
    }
    for name, ball in (("a", ball1), ("b", ball_b)):
        d = first_order_direction(ball)
        f |= {f"{name}_{c}": d[:, i] for i, c in enumerate("xyz")}
    return {k: torch.log(v.clamp_min(1e-4)) if k in LOG_FEATURES else v for k, v in f.items()}


class UNetProbe:
    """Forward hooks on PROBED blocks of a diffusers UNet: ``pooled(B, V)`` -> (B, F), each block's output
    averaged and spread over space, per branch item, concatenated."""

    def __init__(self, unet: torch.nn.Module):
        self.out: dict[str, torch.Tensor] = {}
        self.handles = []
        for name in PROBED:
            block = unet.mid_block if name == "mid_block" else unet.down_blocks[int(name.split(".")[1])]
            hook = lambda mod, inp, out, name=name: self.out.__setitem__(
                name, out[0] if isinstance(out, tuple) else out
            )
            self.handles.append(block.register_forward_hook(hook))

    def pooled(self, B: int, V: int) -> torch.Tensor:
        missing = [n for n in PROBED if n not in self.out]
        if missing:
            raise RuntimeError(f"UNetProbe: no output captured from {missing}: run the UNet first")
        parts = []
        for name in PROBED:
            h = self.out[name].float().unflatten(0, (B, V))
            parts += [h.mean((-1, -2)).flatten(1), h.std((-1, -2)).flatten(1)]
        return torch.cat(parts, 1)

    def remove(self):
        for h in self.handles:
            h.remove()


@torch.no_grad()
def collect(model, shards: Path, split: str, pred: Path | None, light_level: str, batches: int | None, keep: bool):
    """Per cross-light pair: features, probe, true and model levels, scene; with ``keep`` the tensors that
    score a predicted level (anchors, the model's D and S gains, both images, the mask)."""
    from pilight.data.shard_reader import eval_dataset, make_loader
    from pilight.eval.light_following import cross_light
    from pilight.relight.conditions import optional_predictions, oracle_conditions
    from pilight.relight.intensity import relative_pair

    preds = optional_predictions(shards, pred, split, "branch_level_predictors") if pred else None
    probe = UNetProbe(model.stack.model.unet)
    rows: dict[str, list] = {"features": [], "probe": [], "scene": [], "kept": []}
    rows |= {f"{kind} {b}": [] for kind in ("true", "model") for b in BRANCHES}
    for n, batch in enumerate(make_loader(eval_dataset(shards, split, "relight"), 8)):
        if batches is not None and n >= batches:
            break
        batch = cross_light(batch)
        if batch is None:
            continue
        intensity = "relative" if light_level == "estimated" else "absolute"  # absolute: the rendered ball b
        if intensity == "relative":
            batch = relative_pair(batch)
        intr = oracle_conditions(batch, preds)
        _, anc, balls, true_g, model_g = pair_gains(model, batch, intr, intensity)
        rows["probe"].append(probe.pooled(batch["image_a"].shape[0], model.V))
        g = {b: model_g[:, i] for b, i in BRANCHES.items()}
        mask = batch["mask"].float()
        f = physics_features(batch, intr, anc, balls["ball_b"])
        rows["features"].append(torch.stack(list(f.values()), 1))
        for b, i in BRANCHES.items():
            rows[f"true {b}"].append(level_per_image(true_g[:, i], mask)[:, 0, 0, 0])
            rows[f"model {b}"].append(level_per_image(g[b], mask)[:, 0, 0, 0])
        rows["scene"] += [json.loads(m)["scene"] for m in batch["meta_a"]]
        if keep:
            rows["kept"].append(
                {"anchors": anc, "g_d": g["D"], "g_s": g["S"], "mask": mask}
                | {k: batch[k].float() for k in ("image_a", "image_b")}
            )
    probe.remove()
    if not rows["scene"]:
        raise SystemExit(f"{shards} ({split}): no cross-light pairs")
    out = {k: torch.cat(v).double().numpy() for k, v in rows.items() if k not in ("scene", "kept")}
    return out | {"names": list(f), "scene": rows["scene"], "kept": rows["kept"]}


def scene_folds(scenes: list[str], k: int) -> np.ndarray:
    """Fold index per pair, whole scenes per fold (round-robin over sorted scene ids)."""
    order = {s: i % k for i, s in enumerate(sorted(set(scenes)))}
    if len(order) < k:
        raise SystemExit(f"--folds {k}: only {len(order)} scenes to split")
    return np.array([order[s] for s in scenes])


def ridge(X: np.ndarray, y: np.ndarray, weight: float):
    """Standardised ridge regression with a free intercept -> predict(X)."""
    mu, sd = X.mean(0), X.std(0) + 1e-9
    Z = np.concatenate([np.ones((len(X), 1)), (X - mu) / sd], 1)
    reg = weight * len(X) * np.eye(Z.shape[1])
    reg[0, 0] = 0.0
    w = np.linalg.solve(Z.T @ Z + reg, Z.T @ y)
    return lambda Xn: np.concatenate([np.ones((len(Xn), 1)), (Xn - mu) / sd], 1) @ w


PREDICTORS = {  # name -> the inputs of its regression for a branch (None: not fitted)
    "model": None,
    "train mean": lambda d, b: np.zeros((len(d[f"true {b}"]), 0)),
    "calibrated": lambda d, b: d[f"model {b}"][:, None],
    "physics features": lambda d, b: d["features"],
    "UNet features": lambda d, b: d["probe"],
    "truth": None,
}


def predict_levels(scored: dict, fit: dict | None, folds: int, weight: float, branch: str) -> dict[str, np.ndarray]:
    """{predictor: (N,) predicted levels of ``branch`` (D or S) for the scored pairs}: fitted on ``fit``,
    or cross-validated over whole scenes."""
    y = scored[f"true {branch}"]
    out = {"model": scored[f"model {branch}"], "truth": y}
    for name, inputs in PREDICTORS.items():
        if inputs is None:
            continue
        X = inputs(scored, branch)
        if fit is not None:
            out[name] = ridge(inputs(fit, branch), fit[f"true {branch}"], weight)(X)
            continue
        fold, p = scene_folds(scored["scene"], folds), np.zeros(len(X))
        for i in range(folds):
            p[fold == i] = ridge(X[fold != i], y[fold != i], weight)(X[fold == i])
        out[name] = p
    return {name: out[name] for name in PREDICTORS}


def change_r2_at(kept: list[dict], level_d: np.ndarray | None, level_s: np.ndarray | None = None) -> float:
    """Pooled change_r2 on the mask with each pair's D gains moved to ``level_d`` and its S gains to
    ``level_s`` (None: the model's gains as they are)."""
    from pilight.data.colour import tonemap01
    from pilight.eval.light_following import ChangeR2
    from pilight.relight import physics_first as pf

    change, start = ChangeR2(), 0
    for k in kept:
        B = k["mask"].shape[0]
        gains = []
        for g, levels in ((k["g_d"], level_d), (k["g_s"], level_s)):
            level = None if levels is None else torch.as_tensor(levels[start : start + B], dtype=torch.float32)
            gains.append(g if level is None else moved_to_level(g, k["mask"], level))
        start += B
        linear = pf.compose_relit(k["anchors"], *gains)["relit"]
        shown = torch.where(k["mask"] > 0.5, linear, k["image_b"])
        change.update(tonemap01(shown), tonemap01(k["image_b"]), tonemap01(k["image_a"]), k["mask"])
    return change.compute()["mask"]


def r2(pred: np.ndarray, y: np.ndarray) -> float:
    return float(1 - ((pred - y) ** 2).sum() / ((y - y.mean()) ** 2).sum())


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", type=Path, required=True, help="a physics-first stage-2 folder")
    ap.add_argument("--shards", type=Path, required=True)
    ap.add_argument("--split", default="test")
    ap.add_argument("--pred", type=Path, default=None, help="stage-1 predictions as conditions (default: truth)")
    ap.add_argument("--fit-shards", type=Path, default=None, help="fit the predictors here (default: CV)")
    ap.add_argument("--fit-split", default="train")
    ap.add_argument("--fit-pred", type=Path, default=None, help="stage-1 predictions of the fit split")
    ap.add_argument("--fit-batches", type=int, default=None)
    ap.add_argument("--batches", type=int, default=None, help="only the first N batches of 8")
    ap.add_argument("--folds", type=int, default=6)
    ap.add_argument("--ridge", type=float, default=1.0, help="ridge weight on standardised inputs")
    ap.add_argument("--light-level", choices=("estimated", "rendered"), default="estimated")
    ap.add_argument("--source-shading", choices=("estimated", "rendered"), default="estimated")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    model = load(args.model)
    if model.form.kind != "physics_first":
        raise SystemExit(f"{args.model}: form {model.form.kind!r}; this benchmark reads physics-first gains")
    if args.source_shading == "rendered":
        if args.light_level != "rendered":  # RelightModel._conditions scales to the rendered ball then
            raise SystemExit(
                "--source-shading rendered takes the rendered ball's level too: add --light-level rendered"
            )
        model.form = model.form.model_copy(update={"source_light": "rendered"})
    scored = collect(model, args.shards, args.split, args.pred, args.light_level, args.batches, keep=True)
    fit = None
    if args.fit_shards is not None:
        fit = collect(
            model, args.fit_shards, args.fit_split, args.fit_pred, args.light_level, args.fit_batches, keep=False
        )
    levels = {b: predict_levels(scored, fit, args.folds, args.ridge, b) for b in BRANCHES}
    table = {
        "pairs": len(scored["scene"]),
        "conditions": "stage-1" if args.pred else "ground truth",
        "light_level": args.light_level,
        "source_shading": args.source_shading,
        "fitted_on": f"{args.fit_shards} ({args.fit_split}, {'stage-1' if args.fit_pred else 'ground-truth'} maps)"
        if fit
        else f"{args.folds}-fold scene-grouped CV",
        "level_sd": {b: float(scored[f"true {b}"].std()) for b in BRANCHES},
        "level_corr_D_S": float(np.corrcoef(scored["true D"], scored["true S"])[0, 1]),
        "anchor_D_change_r2": change_r2_at(
            [k | {"g_d": torch.zeros_like(k["g_d"])} for k in scored["kept"]], np.zeros(len(scored["scene"]))
        ),
        "predictors": {},
    }
    for name in PREDICTORS:
        d, s = levels["D"][name], levels["S"][name]
        table["predictors"][name] = {
            "D_level_r2": r2(d, scored["true D"]),
            "S_level_r2": r2(s, scored["true S"]),
            "change_r2_mask": {
                "D moved": change_r2_at(scored["kept"], d),
                "S moved": change_r2_at(scored["kept"], None, s),
                "both moved": change_r2_at(scored["kept"], d, s),
            },
        }
    sd = table["level_sd"]
    print(
        f"{args.model} on {args.shards} ({table['pairs']} cross-light pairs, {table['conditions']} maps, light level "
        f"{args.light_level}, source shading {args.source_shading}); fitted on {table['fitted_on']}"
    )
    print(
        f"true levels (gain units): sd D {sd['D']:.3f}, S {sd['S']:.3f}, their correlation "
        f"{table['level_corr_D_S']:+.3f}; D anchor with the model's S: change_r2 {table['anchor_D_change_r2']:+.3f}"
    )
    print(f"  {'levels from':18s} {'R2 of D':>8s} {'R2 of S':>8s} {'D moved':>8s} {'S moved':>8s} {'both':>8s}")
    for n, v in table["predictors"].items():
        c = v["change_r2_mask"]
        print(
            f"  {n:18s} {v['D_level_r2']:+8.3f} {v['S_level_r2']:+8.3f} {c['D moved']:+8.3f} {c['S moved']:+8.3f} "
            f"{c['both moved']:+8.3f}"
        )
    if args.json:
        args.json.write_text(json.dumps(table, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
