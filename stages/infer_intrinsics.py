"""DVC stage `infer_intrinsics`: DDIM or single-step sampling with CFG; all requested intrinsics
of an image in one batched pass; writes predictions in the shard stage's schema and keys.

    python stages/infer_intrinsics.py

Reads params `base`, `intrinsics` (the model) and `infer_intrinsics` (steps, cfg_scale,
timestep_spacing, ensemble, domains, splits); models/intrinsics + data/shards -> data/intrinsics_pred.
"""

from __future__ import annotations

import sys
from pathlib import Path

from pilight import atomic
from pilight.stage_cli import fails_on, run_stage


def options(ap) -> None:
    ap.add_argument("--shards", type=Path, default=Path("data/shards"))
    ap.add_argument("--model", type=Path, default=Path("models/intrinsics"))
    ap.add_argument("--out", type=Path, default=Path("data/intrinsics_pred"))
    ap.add_argument("--metrics", type=Path, default=Path("metrics/infer_intrinsics.json"))


def body(args, base, p, ip) -> int:
    from pilight.data.shard_reader import read_index
    from pilight.eval.predict_intrinsics import predict_intrinsics_splits
    from pilight.models.folder import load_model
    from pilight.models.intrinsics import IntrinsicsModel
    from pilight.models.stack import ModelError

    with fails_on(ModelError, FileNotFoundError, ValueError):
        index = read_index(args.shards)
        model = IntrinsicsModel(p)
        load_model(model.stack, args.model)
    model.stack.model.eval()
    with fails_on(ValueError, OSError):  # shards are read (and verified) while predicting; or a full disk
        m = predict_intrinsics_splits(model, args.shards, index, args.out, ip, base.training_seed, model.describe())
        atomic.write_json(args.metrics, m)
    print(
        f"infer_intrinsics: {m['images']} images, {m['seconds_per_image']:.3f} s/image ({ip.mode}, {ip.steps} steps, "
        f"cfg {ip.cfg_scale}, ensemble {ip.ensemble}, domains {list(ip.domains)}) -> {args.out}"
    )
    return 0


def main(argv: list[str] | None = None) -> int:
    return run_stage(
        "infer_intrinsics",
        __doc__,
        argv,
        ["base", "intrinsics", "infer_intrinsics"],
        options,
        body,
        outputs=lambda a: [a.out, a.metrics],
    )


if __name__ == "__main__":
    sys.exit(main())
