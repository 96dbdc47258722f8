"""DVC stage `train_intrinsics` (stage 1): a diffusion UNet predicting albedo, normal, roughness
and metallic together, with cross-batch attention and one-hot domain labels (v-prediction,
masked latent loss).

    python stages/train_intrinsics.py                                  # CPU or one GPU
    accelerate launch --multi_gpu --num_processes 8 stages/train_intrinsics.py
    accelerate launch --config_file profiles/accelerate_fsdp.yaml stages/train_intrinsics.py   # ZeRO-2's split (FSDP)

Reads params `base` and `intrinsics`; data/shards -> models/intrinsics (weights + config),
checkpoints/intrinsics (resumed automatically after an interruption), dvclive/intrinsics.
"""

from __future__ import annotations

import sys
from pathlib import Path

from pilight.stage_cli import run_stage


def options(ap) -> None:
    ap.add_argument("--shards", type=Path, default=Path("data/shards"))
    ap.add_argument("--out", type=Path, default=Path("models/intrinsics"))
    ap.add_argument("--checkpoints", type=Path, default=Path("checkpoints/intrinsics"))
    ap.add_argument("--live", type=Path, default=Path("dvclive/intrinsics"))


def body(args, base, p) -> int:
    from pilight.train.intrinsics import IntrinsicsTask
    from pilight.train.stage import run_training_stage

    # after the shards: the stage's own train.seed, else base.train_seed, else base.seed
    seed = base.stage_training_seed(p.train)
    return run_training_stage(
        "train_intrinsics",
        "intrinsics",
        base.model_copy(update={"seed": seed}),
        p,
        lambda: IntrinsicsTask(p, args.shards, seed=seed),
        shards=args.shards,
        data=[args.shards],
        out=args.out,
        checkpoints=args.checkpoints,
        live=args.live,
    )


def main(argv: list[str] | None = None) -> int:
    return run_stage(
        "train_intrinsics",
        __doc__,
        argv,
        ["base", "intrinsics"],
        options,
        body,
        outputs=lambda a: [a.out, a.checkpoints, a.live],
    )


if __name__ == "__main__":
    sys.exit(main())
