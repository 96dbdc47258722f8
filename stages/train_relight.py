"""DVC stage `train_relight` (stage 2): a diffusion UNet that relights an image, predicting the relit
image, its diffuse shading D and specular S together (three branches, cross-batch attention,
one-hot branch labels), trained with L_vpred + (1/t)(lambda_ds L_DS + lambda_ps L_PS + lambda_rec L_rec)
on the decoded x0 estimate (see pilight.train.relight).

    python stages/train_relight.py                                     # CPU or one GPU
    accelerate launch --multi_gpu --num_processes 8 stages/train_relight.py
    accelerate launch --config_file profiles/accelerate_fsdp.yaml stages/train_relight.py   # ZeRO-2's split (FSDP)

Reads params `base` and `relight`; data/shards (+ data/intrinsics_pred when relight.conditions is
pred or mix) -> models/relight (weights + config), checkpoints/relight (resumed automatically),
dvclive/relight.
"""

from __future__ import annotations

import sys
from pathlib import Path

from pilight.stage_cli import run_stage


def options(ap) -> None:
    ap.add_argument("--shards", type=Path, default=Path("data/shards"))
    ap.add_argument(
        "--pred",
        type=Path,
        default=Path("data/intrinsics_pred"),
        help="stage-1 predictions (used when relight.conditions is pred or mix)",
    )
    ap.add_argument("--out", type=Path, default=Path("models/relight"))
    ap.add_argument("--checkpoints", type=Path, default=Path("checkpoints/relight"))
    ap.add_argument("--live", type=Path, default=Path("dvclive/relight"))


def body(args, base, p) -> int:
    from pilight.train.relight import RelightTask
    from pilight.train.stage import run_training_stage

    data = [args.shards] + ([args.pred] if p.conditions != "gt" else [])  # predictions only when they are used
    # after the shards: the stage's own train.seed, else base.train_seed, else base.seed
    seed = base.stage_training_seed(p.train)
    return run_training_stage(
        "train_relight",
        "relight",
        base.model_copy(update={"seed": seed}),
        p,
        lambda: RelightTask(p, args.shards, seed=seed, pred_dir=args.pred),
        shards=args.shards,
        data=data,
        out=args.out,
        checkpoints=args.checkpoints,
        live=args.live,
    )


def main(argv: list[str] | None = None) -> int:
    return run_stage(
        "train_relight",
        __doc__,
        argv,
        ["base", "relight"],
        options,
        body,
        outputs=lambda a: [a.out, a.checkpoints, a.live],
    )


if __name__ == "__main__":
    sys.exit(main())
