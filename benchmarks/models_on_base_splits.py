"""A models folder (the default's models/, or a base) on the base's two test splits: the base test split and
the held-out shapes and textures (issue #33: "the same figures on the held-out split").

    python benchmarks/models_on_base_splits.py --models models [--json /tmp/heldout.json] [--train-batches 24]

Needs the base's shards (`cd base && dvc repro` made them: base/data/shards, base/data/shards_heldout).
Stage 1: single step, scored by benchmarks/stage1_study.py's ``score`` (masked as evaluate does). Stage 2:
ground-truth maps, scored by benchmarks/stage2_study.py's ``score`` (change_r2 on the mask and PSNR, the
model against its zero-gain physics anchor, relative and absolute tiers). Prints one JSON line per split,
with the machine.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.stage1_study import score as score_stage1  # noqa: E402
from benchmarks.stage2_study import score as score_stage2  # noqa: E402

SPLITS = {"base test": "base/data/shards", "held-out shapes and textures": "base/data/shards_heldout"}


def load(models: Path):
    from pilight.models.folder import load_model
    from pilight.models.intrinsics import IntrinsicsModel
    from pilight.models.relight import RelightModel
    from pilight.params import IntrinsicsParams, RelightParams

    params = lambda stage: json.loads((models / stage / "config.json").read_text())["params"]
    m1 = IntrinsicsModel(IntrinsicsParams.model_validate(params("intrinsics")))
    # training-only keys that name files of the training machine: inference reads neither
    raw = params("relight") | {"conditions": "gt", "rec_features": "pooled-rgb", "dinov2_path": None}
    m2 = RelightModel(RelightParams.model_validate(raw))
    for m, stage in ((m1, "intrinsics"), (m2, "relight")):
        load_model(m.stack, models / stage)
        m.stack.model.eval()
    return m1, m2


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--models", type=Path, default=REPO / "models")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument(
        "--train-batches",
        type=int,
        default=0,
        help="also score stage 2 (ground-truth maps) on the first N batches of 8 of the base's train split: "
        "what the network learnt on pairs it trained on, against the test split (the generalisation gap)",
    )
    args = ap.parse_args(argv)
    from pilight import machine

    m1, m2 = load(args.models)
    out = {"models": str(args.models), "machine": machine.one_line()}
    for name, shards in SPLITS.items():
        if not (REPO / shards / "index.json").is_file():
            raise SystemExit(f"{REPO / shards}: no shards; run `cd base && dvc repro` first")
        out[name] = {
            "stage1": score_stage1(m1, REPO / shards, "test"),
            "stage2_gt_maps": score_stage2(m2, REPO / shards),
        }
        print(json.dumps({"split": name, **out[name]}), flush=True)
    if args.train_batches:
        train = score_stage2(m2, REPO / SPLITS["base test"], "train", args.train_batches)
        out["base train"] = {"stage2_gt_maps": train, "batches": args.train_batches}
        print(
            json.dumps({"split": f"base train (first {args.train_batches} batches)", "stage2_gt_maps": train}),
            flush=True,
        )
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
