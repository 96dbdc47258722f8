"""DVC stage `train_relight` (stage 2): a diffusion UNet that relights an image, predicting the relit
image, its diffuse shading D and specular S together (three branches, cross-batch attention,
one-hot branch labels), trained with L_vpred + (1/t)(lambda_ds L_DS + lambda_ps L_PS + lambda_rec L_rec)
on the decoded x0 estimate (see pilight.train.relight).

    python stages/train_relight.py                                     # CPU or one GPU
    accelerate launch --multi_gpu --num_processes 8 stages/train_relight.py
    accelerate launch --use_deepspeed --zero_stage 2 stages/train_relight.py   # the paper's ZeRO-2

Reads params `base` and `relight`; data/shards (+ data/intrinsics_pred when relight.conditions is
pred or mix) -> models/relight (weights + config), checkpoints/relight (resumed automatically),
dvclive/relight.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pilight.params import ParamsError, load_section  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--params", default="params.yaml")
    ap.add_argument("--shards", type=Path, default=Path("data/shards"))
    ap.add_argument("--pred", type=Path, default=Path("data/intrinsics_pred"),
                    help="stage-1 predictions (used when relight.conditions is pred or mix)")
    ap.add_argument("--out", type=Path, default=Path("models/relight"))
    ap.add_argument("--checkpoints", type=Path, default=Path("checkpoints/relight"))
    ap.add_argument("--live", type=Path, default=Path("dvclive/relight"))
    args = ap.parse_args(argv)
    try:
        base, p = load_section("base", args.params), load_section("relight", args.params)
    except ParamsError as exc:
        print(f"train_relight: {exc}", file=sys.stderr)
        return 2
    from pilight.train.relight import RelightTask
    from pilight.data.schema import DataError
    from pilight.train.build import ModelError
    from pilight.train.checkpoint import CheckpointError
    from pilight.train.stage import run_training_stage

    data = [args.shards] + ([args.pred] if p.conditions != "gt" else [])  # predictions only when they are used
    # Damage found once training runs (a shard, a checkpoint, a diverged loss, a full disk) is a
    # message naming the file and exit 1, like damage found before it starts.
    try:
        return run_training_stage("train_relight", "relight", base, p,
                                  lambda: RelightTask(p, args.shards, seed=base.seed, pred_dir=args.pred),
                                  shards=args.shards, data=data, out=args.out, checkpoints=args.checkpoints,
                                  live=args.live)
    except (DataError, ModelError, CheckpointError, FloatingPointError, OSError) as exc:
        print(f"train_relight: error: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
