"""DVC stage `relight`: relight the test pairs with the trained stage-2 model and write them in the
prediction shard format (pilight/eval/relit_pairs.py: the splits, keys, conditions and measurements).

    python stages/relight.py

A stage of its own so that changing relight_infer reruns sampling only, never training. Conditions:
stage-1 predictions when data/intrinsics_pred holds the split, else ground truth (relight.conditions
is a training setting); mask and target ball come from the shards. Also the paper's flipped-normal
check (pilight/eval/flip_check.py). Reads params `base`, `relight` (the model) and `relight_infer`;
models/relight + data/shards (+ data/intrinsics_pred) -> data/relit (byte-deterministic); timings,
the identity residual and the flip check -> metrics/relight.json.
"""

from __future__ import annotations

import sys
from pathlib import Path

from pilight import atomic
from pilight.failure import CommandFailure
from pilight.stage_cli import fails_on, run_stage


def options(ap) -> None:
    ap.add_argument("--shards", type=Path, default=Path("data/shards"))
    ap.add_argument("--pred", type=Path, default=Path("data/intrinsics_pred"))
    ap.add_argument("--model", type=Path, default=Path("models/relight"))
    ap.add_argument("--out", type=Path, default=Path("data/relit"))
    ap.add_argument("--metrics", type=Path, default=Path("metrics/relight.json"))
    ap.add_argument("--no-flip-check", action="store_true", help="skip the flipped-normal check (one extra batch)")


def body(args, base, p, ip) -> int:
    from pilight.base_model import check_saved_params
    from pilight.data.shard_reader import read_index
    from pilight.eval.relit_pairs import relight_split
    from pilight.models.folder import load_model
    from pilight.models.relight import RelightModel
    from pilight.models.stack import ModelError, check_image_size
    from pilight.relight.conditions import optional_predictions

    with fails_on(ModelError, FileNotFoundError, ValueError):
        index = read_index(args.shards)
        if not index["splits"].get(ip.split, {}).get("shards"):
            raise CommandFailure(f"{args.shards}: the {ip.split} split has no shards")
        model = RelightModel(p)
        check_image_size(tuple(index["sizes"]["image"][:2]), model.stack.codec.factor, f"{args.shards}/index.json")
        load_model(model.stack, args.model)
        check_saved_params(args.model, "relight", p)
        preds = optional_predictions(args.shards, args.pred, ip.split, "relight")
    model.stack.model.eval()
    m = relight_split(model, args.shards, args.out, ip.split, ip, base.training_seed, preds, not args.no_flip_check)
    atomic.write_json(args.metrics, m, sort_keys=True)
    print(
        f"relight: {m['pairs']} pairs, {m['seconds_per_pair']:.3f} s/pair ({ip.mode}, {ip.steps} steps, "
        f"cfg {ip.cfg_scale}, ensemble {ip.ensemble}, conditions {'pred' if preds is not None else 'gt'}) -> {args.out}"
    )
    return 0


def main(argv: list[str] | None = None) -> int:
    return run_stage(
        "relight",
        __doc__,
        argv,
        ["base", "relight", "relight_infer"],
        options,
        body,
        outputs=lambda a: [a.out, a.metrics],
    )


if __name__ == "__main__":
    sys.exit(main())
