"""DVC stage `train_intrinsics` (stage 1): a diffusion UNet predicting albedo, normal, roughness
and metallic together, with cross-batch attention and one-hot domain labels (v-prediction,
masked latent loss).

    python stages/train_intrinsics.py                                  # CPU or one GPU
    accelerate launch --multi_gpu --num_processes 8 stages/train_intrinsics.py
    accelerate launch --use_deepspeed --zero_stage 2 stages/train_intrinsics.py   # the paper's ZeRO-2

Reads params `base` and `intrinsics`; data/shards -> models/intrinsics (weights + config),
checkpoints/intrinsics (resumed automatically after an interruption), dvclive/intrinsics.
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
    ap.add_argument("--out", type=Path, default=Path("models/intrinsics"))
    ap.add_argument("--checkpoints", type=Path, default=Path("checkpoints/intrinsics"))
    ap.add_argument("--live", type=Path, default=Path("dvclive/intrinsics"))
    args = ap.parse_args(argv)
    try:
        base, p = load_section("base", args.params), load_section("intrinsics", args.params)
    except ParamsError as exc:
        print(f"train_intrinsics: {exc}", file=sys.stderr)
        return 2
    from pilight.train.intrinsics import IntrinsicsTask
    from pilight.data.schema import DataError
    from pilight.train.build import ModelError
    from pilight.train.checkpoint import CheckpointError
    from pilight.train.stage import run_training_stage

    # Damage found once training runs (a shard, a checkpoint, a diverged loss, a full disk) is a
    # message naming the file and exit 1, like damage found before it starts.
    try:
        return run_training_stage("train_intrinsics", "intrinsics", base, p,
                                  lambda: IntrinsicsTask(p, args.shards, seed=base.seed), shards=args.shards,
                                  data=[args.shards], out=args.out, checkpoints=args.checkpoints, live=args.live)
    except (DataError, ModelError, CheckpointError, FloatingPointError, OSError) as exc:
        print(f"train_intrinsics: error: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
