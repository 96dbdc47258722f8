"""Which of stage 2's branches costs the relit image most? Predicted and true gains, mixed.

    python benchmarks/stage2_branch_errors.py --model weights/pilight-base/relight --shards base/data/shards
        [--split train --batches 24] [--pred <stage-1 predictions>] [--json FILE]

The physics-first form relights as I = A_x D + S on the mask, with D and S gains g_D, g_S on their
physics anchors (pilight.relight.physics_first). For each cross-light pair (relative intensity, single
step), the model's gains are set beside the true ones (the training targets, cell means) and the relit
image is formed from every mix of D and S in {model, truth, anchor (zero gain)}, D also from the true
gains' level per image alone and from the model's gains moved to that level. Printed: the mean
tone-mapped squared error on the mask of each mix (what the image loss sees), and per branch the share
of its target's variance the model explains (cell gains; on the mask for D and S, off it for the relit
branch's gain on the input). Conditions: ground-truth maps, or stage-1 predictions with --pred.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from pilight.params import SamplingParams  # noqa: E402

SINGLE_STEP = SamplingParams(mode="single_step", cfg_scale=1.0)
SOURCES = ("model", "truth", "anchor")
# the diffuse branch also takes the true gains' level per image (their mean on the mask) alone, and the
# model's gains moved to that level: does the network miss the level or the shape? (docs: stage 2)
D_SOURCES = (*SOURCES, "level", "model + level")
BRANCHES = ("relit", "diffuse", "specular")


def masked_mean(x: torch.Tensor, m: torch.Tensor) -> torch.Tensor:
    """(B, C, H, W) and a (B, 1, H, W) 0/1 weight -> (B,) mean over the weight and the channels."""
    m = m.expand_as(x)
    return (x * m).flatten(1).sum(1) / m.flatten(1).sum(1).clamp_min(1)


def level_per_image(g: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """(B, C, H, W) gains -> their mean over the mask and the channels of each image, broadcast to g's shape."""
    return masked_mean(g, (mask[:, :1] > 0.5).float()).view(-1, 1, 1, 1).expand_as(g)


def mixed_errors(
    anc,
    true_g: torch.Tensor,
    model_g: torch.Tensor,
    image_b: torch.Tensor,
    mask: torch.Tensor,
    image_a: torch.Tensor | None = None,
    change: dict | None = None,
) -> dict:
    """{"D <source>, S <source>": (sum of squared tone-mapped errors on the mask, pixel count)} for every
    mix (D from D_SOURCES, S from SOURCES); true_g, model_g: (B, 3, 3, H, W) cell-smoothed gains of the
    relit, D and S branches. With
    ``image_a`` and ``change`` ({mix: ChangeR2}, filled here), each mix's change_r2 is accumulated too
    (off the mask the target stands in: only the mask is read)."""
    from pilight.data.colour import tonemap01
    from pilight.eval.light_following import ChangeR2
    from pilight.relight import physics_first as pf
    from pilight.relight.encoding import tonemap

    s_gains = {"model": model_g[:, 2], "truth": true_g[:, 2], "anchor": torch.zeros_like(true_g[:, 2])}
    true_level = level_per_image(true_g[:, 1], mask)
    d_gains = {"model": model_g[:, 1], "truth": true_g[:, 1], "anchor": torch.zeros_like(true_g[:, 1])}
    d_gains |= {"level": true_level, "model + level": model_g[:, 1] - level_per_image(model_g[:, 1], mask) + true_level}
    target = tonemap(image_b.float())
    m = (mask[:, :1] > 0.5).float().expand_as(target)
    if change is not None:  # the mixes differ only in the relit image: tone-map the pair once
        u_target, u_input = tonemap01(image_b.float()), tonemap01(image_a.float())
    out = {}
    for d in D_SOURCES:
        for s in SOURCES:
            linear = pf.compose_relit(anc, d_gains[d], s_gains[s])["relit"]
            relit = tonemap(linear)
            out[f"D {d}, S {s}"] = (float((m * (relit - target) ** 2).sum()), float(m.sum()))
            if change is not None:
                shown = torch.where(mask > 0.5, linear, image_b.float())
                change.setdefault(f"D {d}, S {s}", ChangeR2()).update(tonemap01(shown), u_target, u_input, mask)
    return out


def explained(
    true_g: torch.Tensor, model_g: torch.Tensor, mask: torch.Tensor, metallic: torch.Tensor | None = None
) -> dict:
    """{branch: (sum sq error, sum target, sum target^2, weight)} for the explained-variance share; with
    ``metallic``, also "specular, metal" and "specular, dielectric" (metallic > 0.5 or not)."""
    m = (mask[:, :1] > 0.5).float()
    weights = {name: (1 - m) if name == "relit" else m for name in BRANCHES}
    if metallic is not None:
        metal = (metallic[:, :1] > 0.5).float()
        weights |= {"specular, metal": m * metal, "specular, dielectric": m * (1 - metal)}
    out = {}
    for name, w in weights.items():
        i = BRANCHES.index(name.split(",")[0])
        t, o = true_g[:, i], model_g[:, i]
        w = w.expand_as(t)
        out[name] = (float((w * (t - o) ** 2).sum()), float((w * t).sum()), float((w * t * t).sum()), float(w.sum()))
    return out


def pair_gains(model, batch: dict, intr: dict, intensity: str):
    """(maps, anchors, balls, true gains, model gains) of a pairs batch: the gains (B, 3, 3, H, W) of the
    relit, D and S branches, the true ones the training targets as the stage-2 task forms them (cell means),
    the model's from one single-step pass; both cell-smoothed as inference reads them
    (RelightModel._physics_first_outputs)."""
    from pilight.diffusion.codec import cell_smooth
    from pilight.relight.branches import encode_conditions
    from pilight.train.relight import RelightTask

    maps, anc, balls = model._conditions(batch, intr, "cpu", intensity=intensity)
    true_g = RelightTask._physics_first_targets(model, batch, anc, maps["image"], "cpu")
    B, z_cond = batch["image_a"].shape[0], encode_conditions(model.stack.codec, maps, model.layout, model.width)
    z0 = model.stack.sample(z_cond, torch.arange(model.V).repeat(B), maps["image"], model.V, SINGLE_STEP, None)
    model_g = model.stack.codec.decode(z0).float().unflatten(0, (B, model.V))
    smooth = lambda g: torch.stack([cell_smooth(g[:, i], model._cell) for i in range(g.shape[1])], 1)
    return maps, anc, balls, smooth(true_g), smooth(model_g)


def load(folder: Path):
    from pilight.models.folder import load_model
    from pilight.models.relight import RelightModel
    from pilight.params import RelightParams

    raw = json.loads((folder / "config.json").read_text())["params"]
    raw |= {"conditions": "gt", "rec_features": "pooled-rgb", "dinov2_path": None}  # training-only keys
    model = RelightModel(RelightParams.model_validate(raw))
    load_model(model.stack, folder)
    model.stack.model.eval()
    return model


@torch.no_grad()
def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", type=Path, required=True, help="a stage-2 folder (config.json + weights)")
    ap.add_argument("--shards", type=Path, required=True)
    ap.add_argument("--split", default="test")
    ap.add_argument("--batches", type=int, default=None, help="only the first N batches of 8")
    ap.add_argument("--pred", type=Path, default=None, help="stage-1 predictions as conditions (default: truth)")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    from pilight.data.shard_reader import eval_dataset, make_loader
    from pilight.eval.light_following import cross_light
    from pilight.relight.conditions import optional_predictions, oracle_conditions
    from pilight.relight.intensity import relative_pair

    model = load(args.model)
    if model.form.kind != "physics_first":
        raise SystemExit(f"{args.model}: form {model.form.kind!r}; this benchmark reads physics-first gains")
    preds = optional_predictions(args.shards, args.pred, args.split, "stage2_branch_errors") if args.pred else None
    errors: dict = {}
    change: dict = {}
    variance: dict = {}
    pairs = 0
    for n, batch in enumerate(make_loader(eval_dataset(args.shards, args.split, "relight"), 8)):
        if args.batches is not None and n >= args.batches:
            break
        batch = cross_light(batch)
        if batch is None:
            continue
        pairs += batch["image_a"].shape[0]
        batch = relative_pair(batch)
        intr = oracle_conditions(batch, preds)
        # the batch's balls are relative (relative_pair above), whatever the model's default intensity
        _, anc, _, true_g, model_g = pair_gains(model, batch, intr, "relative")
        mixed = mixed_errors(anc, true_g, model_g, batch["image_b"], batch["mask"], batch["image_a"], change)
        for k, (sq, cnt) in mixed.items():
            e = errors.setdefault(k, [0.0, 0.0])
            e[0], e[1] = e[0] + sq, e[1] + cnt
        for k, vals in explained(true_g, model_g, batch["mask"], intr["metallic"]).items():
            v = variance.setdefault(k, [0.0] * 4)
            variance[k] = [a + b for a, b in zip(v, vals)]
    table = {"pairs": pairs, "split": args.split, "conditions": "stage-1" if args.pred else "ground truth"}
    table["mse_on_mask"] = {k: sq / max(cnt, 1) for k, (sq, cnt) in errors.items()}
    table["change_r2_mask"] = {k: c.compute()["mask"] for k, c in change.items()}
    table["change_r2_mask_pair_median"] = {k: c.compute()["mask_pair_median"] for k, c in change.items()}
    table["explained"] = {}
    for k, (err, s1, s2, w) in variance.items():
        var = s2 - s1 * s1 / max(w, 1)
        table["explained"][k] = 1 - err / var if var > 0 else float("nan")
    print(f"{args.model} on {args.split} ({pairs} cross-light pairs, {table['conditions']} maps, relative)")
    print("I = A_x D + S on the mask: tone-mapped squared error, change_r2 pooled, change_r2 of the median pair")
    for k, v in table["mse_on_mask"].items():
        r2, med = table["change_r2_mask"][k], table["change_r2_mask_pair_median"][k]
        print(f"  {k:28s} {v:.5f}  {r2:+.3f}  {med:+.3f}" if med is not None else f"  {k:28s} {v:.5f}  {r2:+.3f}")
    print("share of each branch's target variance the model explains:")
    for k, v in table["explained"].items():
        print(f"  {k:22s} {v:+.3f}")
    if args.json:
        args.json.write_text(json.dumps(table, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
