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
import json
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
    import torch

    from pilight.data.schema import DataError
    from pilight.data.shards import read_index
    from pilight.train.build import ModelError, check_image_size, save_model
    from pilight.train.checkpoint import run_identity
    from pilight.train.loop import loop_config, train
    from pilight.train.relight import RelightTask

    try:
        index = read_index(args.shards)
        if not index["splits"].get("train", {}).get("shards"):
            raise DataError(f"{args.shards}: the train split has no shards")
        task = RelightTask(p, args.shards, seed=base.seed, pred_dir=args.pred)
        check_image_size(tuple(index["sizes"]["image"][:2]), task.stack.codec.factor, f"{args.shards}/index.json")
    except (DataError, ModelError, FileNotFoundError, ValueError) as exc:
        print(f"train_relight: {exc}", file=sys.stderr)
        return 1
    print(f"train_relight: {task.describe()}")
    torch.manual_seed(base.seed)
    cfg = loop_config(p.train, base.seed)
    identity = run_identity(base.seed, "relight", p.model_dump(mode="json"),
                            [args.shards] + ([args.pred] if p.conditions != "gt" else []))
    stats = train(task, cfg, args.checkpoints, args.live, identity=identity)
    save_model(task.stack, args.out, p.model_dump(mode="json"))
    # What each substituted part is (e.g. pooled-rgb, not DINO, for L_rec), for reports.
    (args.out / "task.json").write_text(json.dumps(task.describe(), indent=1, sort_keys=True) + "\n")
    print(f"train_relight: {stats['steps']} steps in {stats['seconds']:.0f} s "
          f"({stats['samples_per_second']:.2f} samples/s), final loss {stats['final_loss']:.4f} -> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
