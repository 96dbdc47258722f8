"""DVC stage `relight`: relight the test pairs with the trained stage-2 model and write them in the
prediction shard format (pilight/eval/relit_pairs.py: the splits, keys and conditions).

    python stages/relight.py

A stage of its own so that changing relight_infer (cfg_scale, steps) reruns sampling only, never
training. Conditions: stage-1 predictions of the input image when data/intrinsics_pred holds the
split, else ground truth; the output index records which. The mask and the target light ball always
come from the shards. Also the paper's appendix check (pilight/eval/flip_check.py) on the first
batches of pairs: with the x channel of N flipped, the left/right asymmetry of D_pred should change sign.

Reads params `base`, `relight` (the model) and `relight_infer`; models/relight + data/shards
(+ data/intrinsics_pred) -> data/relit; timings, the identity residual and the flip check ->
metrics/relight.json (never into data/relit, which is byte-deterministic).
"""

from __future__ import annotations

import sys
from pathlib import Path

from pilight import atomic
from pilight.stage_cli import fails_on, run_stage


def options(ap) -> None:
    ap.add_argument("--shards", type=Path, default=Path("data/shards"))
    ap.add_argument("--pred", type=Path, default=Path("data/intrinsics_pred"))
    ap.add_argument("--model", type=Path, default=Path("models/relight"))
    ap.add_argument("--out", type=Path, default=Path("data/relit"))
    ap.add_argument("--metrics", type=Path, default=Path("metrics/relight.json"))
    ap.add_argument("--no-flip-check", action="store_true", help="skip the flipped-normal check (one extra batch)")


def body(args, base, p, ip) -> int:
    from pilight.data.predictions import write_predictions
    from pilight.data.schema import DataError
    from pilight.data.shards import read_index
    from pilight.eval.flip_check import FLIP_CHECK_BATCHES, flip_check
    from pilight.eval.light_following import PROBE_SPLIT
    from pilight.eval.relit_pairs import RunStats, index_info, relit_pairs, relit_probes
    from pilight.relight.conditions import optional_predictions
    from pilight.train.build import ModelError, check_image_size, load_model
    from pilight.train.relight import RelightTask

    split = ip.split
    with fails_on(ModelError, FileNotFoundError, ValueError):
        index = read_index(args.shards)
        if not index["splits"].get(split, {}).get("shards"):
            raise DataError(f"{args.shards}: the {split} split has no shards")
        # Conditions for the model are chosen below, not by relight.conditions (a training setting).
        task = RelightTask(p.model_copy(update={"conditions": "gt"}), args.shards, seed=base.seed)
        check_image_size(tuple(index["sizes"]["image"][:2]), task.stack.codec.factor, f"{args.shards}/index.json")
        load_model(task.stack, args.model)
        preds = optional_predictions(args.shards, args.pred, split, "relight")
    source = "pred" if preds is not None else "gt"
    task.stack.model.eval()
    stats = RunStats(FLIP_CHECK_BATCHES)
    run = lambda conditions, **kw: relit_pairs(task, args.shards, split, ip, base.seed, conditions, preds, **kw)
    jobs = {split: run(source, stats=stats)}
    if source == "pred":
        jobs[f"{split}_gt"] = run("gt", cross_only=True)
    jobs[PROBE_SPLIT] = relit_probes(task, args.shards, split, ip, base.seed, preds)
    out_index = write_predictions(args.out, jobs, index_info(task, ip, split, source))
    flip = {"pairs": 0, "note": "needs the diffuse branch (relight.decomposition: true)"}
    if not args.no_flip_check and stats.first and "diffuse" in task.branches:
        flip = flip_check(task, stats.first, ip, base.seed)
    per_pair = stats.seconds / max(stats.pairs, 1)
    atomic.write_json(
        args.metrics,
        {
            "seconds_per_pair": per_pair,
            "pairs": stats.pairs,
            "conditions": source,
            "identity_residual_relative": stats.identity_residual(),
            "samples": out_index["splits"][split]["samples"],
            "flip_check_d_pred": flip,
        },
        sort_keys=True,
    )
    print(
        f"relight: {stats.pairs} pairs, {per_pair:.3f} s/pair ({ip.mode}, {ip.steps} steps, cfg {ip.cfg_scale}, "
        f"ensemble {ip.ensemble}, conditions {source}) -> {args.out}"
    )
    return 0


def main(argv: list[str] | None = None) -> int:
    return run_stage("relight", __doc__, argv, ["base", "relight", "relight_infer"], options, body)


if __name__ == "__main__":
    sys.exit(main())
