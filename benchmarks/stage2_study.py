"""Stage 2 alone, trained and scored in one process: does the network add to its physics anchor?

    python benchmarks/stage2_study.py --shards data/shards -S relight.conditions=gt --seeds 42 43 44 --json /tmp/a.json
    python benchmarks/stage1_study.py --compare /tmp/a.json /tmp/b.json      # the same comparison table

Each seed trains the params' `relight` section with the -S overrides through the stage's training loop,
then relights the test split's cross-light pairs with GROUND-TRUTH conditions (the question is the
network's, not stage 1's) and, with --score-pred, again with stage-1 predictions as conditions (the
figures prefixed ``s1_``: what a pipeline with that stage 1 would see). It prints, for the model and for
the zero-gain anchor, in relative and absolute intensity: change_r2 on the mask (pooled, and the median
pair's) and on the full image, and tone-mapped PSNR, beside the wall-clock seconds of training and the
machine. ``gain_r2`` is how much of the variance of the true
diffuse gains g_D (on the mask, relative intensity) the predicted gains explain: 0 = the anchor, 1 =
perfect gains (the oracle's 0.96-0.97 change_r2).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.stage1_study import apply_overrides  # noqa: E402
from pilight.params import RelightParams, SamplingParams, read_params  # noqa: E402

SINGLE_STEP = SamplingParams(mode="single_step", cfg_scale=1.0)


@torch.no_grad()
def score(
    task, shards: Path, split: str = "test", max_batches: int | None = None, preds: dict | None = None
) -> dict[str, float]:
    """The figures above on ``split``'s cross-light pairs (its first ``max_batches`` batches of 8 when set:
    the train split, scored to measure the generalisation gap, is large), conditioned on ground truth, or
    on ``preds`` (stage-1 predictions of the split, pilight.relight.conditions) when given."""
    from pilight.data.colour import tonemap01
    from pilight.data.shard_reader import eval_dataset, make_loader
    from pilight.eval.light_following import ChangeR2, cross_light
    from pilight.eval.metrics import psnr_per_image
    from pilight.relight import physics_first as pf
    from pilight.relight.conditions import oracle_conditions
    from pilight.relight.intensity import relative_pair

    r2 = {f"{m}_{i}": ChangeR2() for m in ("model", "anchor") for i in ("rel", "abs")}
    psnr = {k: [] for k in r2}
    gain_err, gain_var, gain_n = 0.0, 0.0, 0
    for n, batch in enumerate(make_loader(eval_dataset(shards, split, "relight"), 8)):
        if max_batches is not None and n >= max_batches:
            break
        batch = cross_light(batch)
        if batch is None:
            continue
        intr = oracle_conditions(batch, preds)  # ground truth when preds is None
        target, inp, mask = tonemap01(batch["image_b"]), tonemap01(batch["image_a"]), batch["mask"]
        for i, intensity in (("rel", "relative"), ("abs", "absolute")):
            given = relative_pair(batch) if intensity == "relative" else batch
            for m in ("model", "anchor"):
                out = task.predict(given, SINGLE_STEP, None, intr, intensity=intensity, zero_gains=m == "anchor")
                pred = tonemap01(out["relit"])
                r2[f"{m}_{i}"].update(pred, target, inp, mask)
                psnr[f"{m}_{i}"] += psnr_per_image(pred, target).tolist()
                if m == "model" and i == "rel":
                    maps, anc, _ = task._conditions(given, intr, "cpu", "relative")
                    g_true = pf.gain_of(
                        pf.diffuse_target(batch["image_b"], batch["specular_b"], anc.albedo), anc.d_calc, anc.eps
                    )
                    g_pred = pf.gain_of(out["diffuse"], anc.d_calc, anc.eps)
                    sel = (mask > 0.5).expand_as(g_true)
                    gain_err += float(((g_pred - g_true)[sel] ** 2).sum())
                    gain_var += float((g_true[sel] ** 2).sum())
                    gain_n += int(sel.sum())
    out = {}
    for k, v in r2.items():
        c = v.compute()
        out[f"{k}_change_r2_mask"], out[f"{k}_change_r2_full"] = c["mask"], c["full"]
        out[f"{k}_change_r2_pair_median"] = c["mask_pair_median"]
        out[f"{k}_psnr"] = sum(psnr[k]) / len(psnr[k])
    out["gain_r2"] = 1 - gain_err / max(gain_var, 1e-12)
    return out


def run_seed(
    raw: dict, shards: Path, pred: Path, seed: int, train_batches: int = 0, score_preds: dict | None = None
) -> dict:
    from pilight.train.loop import train
    from pilight.train.relight import RelightTask

    p = RelightParams.model_validate(raw)
    torch.manual_seed(seed)
    task = RelightTask(p, shards, seed=seed, pred_dir=pred)
    if p.unet.init == "base":
        from pilight.base_model import init_from_base

        init_from_base(task.stack, p, "relight")
    with tempfile.TemporaryDirectory() as ckpt:
        stats = train(task, p.train, Path(ckpt), None, seed=seed)
    task.stack.model.eval()
    out = {"seed": seed, "train_seconds": stats["seconds"], "steps": stats["steps"], **score(task, shards)}
    if score_preds is not None:  # the same pairs, conditioned as a pipeline with that stage 1 would be
        out |= {f"s1_{k}": v for k, v in score(task, shards, preds=score_preds).items()}
    if train_batches:  # the same figures on pairs it trained on: underfitting or a generalisation gap?
        out["train_split"] = score(task, shards, "train", train_batches)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--params", type=Path, default=Path("params.yaml"))
    ap.add_argument("--shards", type=Path, default=Path("data/shards"))
    ap.add_argument("--pred", type=Path, default=Path("data/intrinsics_pred"))
    ap.add_argument("-S", dest="overrides", action="append", default=[], metavar="relight.KEY=VALUE")
    ap.add_argument("--seeds", type=int, nargs="+", default=[42])
    ap.add_argument(
        "--score-pred", type=Path, default=None, help="also score with these stage-1 predictions of the test split"
    )
    ap.add_argument("--name", default=None)
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument(
        "--train-batches", type=int, default=0, help="also score the first N batches of 8 of the train split"
    )
    args = ap.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    raw = apply_overrides(read_params(args.params)["relight"], args.overrides, root="relight")
    RelightParams.model_validate(raw)
    from pilight import machine
    from pilight.relight.conditions import load_condition_predictions

    score_preds = None
    if args.score_pred is not None:  # read once, before any training: a missing split fails here, not after it
        score_preds = load_condition_predictions(args.shards, args.score_pred, "test", "stage2_study --score-pred")

    result = {"name": args.name or " ".join(args.overrides) or "params", "overrides": args.overrides}
    result |= {"machine": machine.one_line(), "seeds": []}
    for seed in args.seeds:
        r = run_seed(raw, args.shards, args.pred, seed, args.train_batches, score_preds)
        result["seeds"].append(r)
        print(json.dumps(r), flush=True)
        if args.json:
            args.json.write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
