"""Flip test-time averaging: a prediction averaged with the un-mirrored prediction of the mirrored input.

    python benchmarks/flip_average.py score                    # stage 1 on the test split, plain vs averaged
    python benchmarks/flip_average.py run --stage1 stages/infer_intrinsics.py   # a stage with it patched in
    python benchmarks/flip_average.py run --stage1 --stage2 stages/relight.py

Both mirrors are exact symmetries of the renders: stage 1's mirrored image has the mirrored maps with
the normal's x negated (and stage 1 trains with that flip, `intrinsics.augment.flip`); stage 2's whole
pairs batch mirrored (images, maps, balls: a mirrored ball is the mirrored light) has the mirrored relit
image. Averaging the two predictions is the cheapest ensemble a deterministic single-step model has
(Marigold averages noise draws instead; ours repeat one prediction).

``score`` predicts the test split twice with models/intrinsics (params.yaml's infer_intrinsics, the
stage's seed) into a temporary folder, prints the evaluate stage's stage-1 figures for each, and the
paired per-image difference (averaged - plain) of the normals' mean angular error and the roughness
and metallic MAE on the mask, with its 95% t-interval over the test images. ``run`` runs a stage script
with the averaging patched into IntrinsicsModel.predict (--stage1) and RelightModel.predict (--stage2;
the zero-gain anchor is left alone): rerun infer_intrinsics, relight and evaluate that way in a
scratch clone to see what it does downstream. Nothing is written but temporary predictions (score) or
what the stage writes (run).
"""

from __future__ import annotations

import argparse
import json
import math
import runpy
import sys
import tempfile
from pathlib import Path

import torch
import torch.nn.functional as F

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from pilight.data.mirror import mirrored as mirror_map  # noqa: E402
from pilight.models.intrinsics import IntrinsicsModel  # noqa: E402
from pilight.models.relight import RelightModel  # noqa: E402

T95_LARGE = 1.98  # two-sided 95% t quantile for ~50-150 degrees of freedom


def mirrored(key: str, v):
    """A batch entry mirrored left-right (pilight.data.mirror); what is not an image passes as it is."""
    return mirror_map(key, v) if torch.is_tensor(v) and v.ndim >= 3 else v


def averaged_intrinsics(predict):
    def predict_flip_averaged(self, image, domains, sp, generator=None):
        a = predict(self, image, domains, sp, generator)
        b = predict(self, image.flip(-1), domains, sp, generator)
        out = {}
        for d in domains:
            y = mirrored(d, b[d])
            out[d] = F.normalize(a[d] + y, dim=1, eps=1e-6) if d == "normal" else (a[d] + y) / 2
        return out

    return predict_flip_averaged


def averaged_relight(predict):
    def predict_flip_averaged(self, batch, sp, generator=None, intr=None, **kw):
        a = predict(self, batch, sp, generator, intr, **kw)
        if kw.get("zero_gains"):  # the physics anchor is the baseline: graded as it is
            return a
        flipped = {k: mirrored(k, v) for k, v in batch.items()}
        b = predict(
            self, flipped, sp, generator, None if intr is None else {k: mirrored(k, v) for k, v in intr.items()}, **kw
        )
        return {k: (a[k] + mirrored(k, b[k])) / 2 for k in a}

    return predict_flip_averaged


def per_image(pred_dir: Path, shards: Path) -> torch.Tensor:
    """(3, images with a mask): normals' mean angular error (deg), roughness MAE, metallic MAE on the mask."""
    from pilight.data.predictions import read_predictions
    from pilight.eval.intrinsics import _collect
    from pilight.eval.metrics import angular_errors

    d = _collect(shards, "test", read_predictions(pred_dir, "test"))
    rows = []
    for i in range(d["gt_mask"].shape[0]):
        m = d["gt_mask"][i : i + 1]
        on = m[0, 0] > 0.5
        if not on.any():
            continue
        err = float(angular_errors(d["pred_normal"][i : i + 1], d["gt_normal"][i : i + 1], m).mean())
        mae = [float((d[f"pred_{k}"][i, 0] - d[f"gt_{k}"][i, 0]).abs()[on].mean()) for k in ("roughness", "metallic")]
        rows.append([err, *mae])
    return torch.tensor(rows).T


def score(args) -> int:
    from pilight.data.shard_reader import read_index
    from pilight.eval.intrinsics import evaluate_intrinsics
    from pilight.eval.predict_intrinsics import predict_intrinsics_splits
    from pilight.models.folder import load_model
    from pilight.params import load_section

    base, p, ip = (load_section(s, args.params) for s in ("base", "intrinsics", "infer_intrinsics"))
    ip = ip.model_copy(update={"splits": ("test",)})
    model = IntrinsicsModel(p)
    load_model(model.stack, args.model)
    model.stack.model.eval()
    index = read_index(args.shards)
    arms = {"plain": IntrinsicsModel.predict, "averaged": averaged_intrinsics(IntrinsicsModel.predict)}
    rows, figures = {}, {}
    with tempfile.TemporaryDirectory() as tmp:
        for name, predict in arms.items():
            IntrinsicsModel.predict = predict
            out = Path(tmp) / name
            m = predict_intrinsics_splits(model, args.shards, index, out, ip, base.training_seed, model.describe())
            figures[name] = {
                "seconds_per_image": m["seconds_per_image"],
                **evaluate_intrinsics(args.shards, out)["model"],
            }
            rows[name] = per_image(out, args.shards)
    IntrinsicsModel.predict = arms["plain"]
    print("| figure | plain | flip-averaged |\n|---|---|---|")
    for k, v in figures["plain"].items():
        print(f"| {k} | {v:.4f} | {figures['averaged'][k]:.4f} |")
    diff = rows["averaged"] - rows["plain"]
    n = diff.shape[1]
    print(f"\naveraged - plain, per test image (n = {n}), mean [95% t-interval]:")
    for name, row in zip(("normal mean error (deg)", "roughness MAE", "metallic MAE"), diff, strict=True):
        mean, half = float(row.mean()), T95_LARGE * float(row.std()) / math.sqrt(n)
        print(f"  {name}: {mean:+.4f} [{mean - half:+.4f}, {mean + half:+.4f}]")
    if args.json:
        Path(args.json).write_text(json.dumps(figures, indent=1))
    return 0


def run(args) -> int:
    if args.stage1:
        IntrinsicsModel.predict = averaged_intrinsics(IntrinsicsModel.predict)
    if args.stage2:
        RelightModel.predict = averaged_relight(RelightModel.predict)
    print(f"flip averaging: stage 1 {'on' if args.stage1 else 'off'}, stage 2 {'on' if args.stage2 else 'off'}")
    sys.argv = [args.script, *args.script_args]
    runpy.run_path(args.script, run_name="__main__")
    return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="command", required=True)
    s = sub.add_parser("score", help="stage 1 on the test split, plain vs flip-averaged")
    s.add_argument("--params", type=Path, default=Path("params.yaml"))
    s.add_argument("--model", type=Path, default=Path("models/intrinsics"))
    s.add_argument("--shards", type=Path, default=Path("data/shards"))
    s.add_argument("--json", type=Path)
    r = sub.add_parser("run", help="run a stage script with flip averaging patched in")
    r.add_argument("--stage1", action="store_true")
    r.add_argument("--stage2", action="store_true")
    r.add_argument("script")
    r.add_argument("script_args", nargs=argparse.REMAINDER)
    args = ap.parse_args()
    return score(args) if args.command == "score" else run(args)


if __name__ == "__main__":
    sys.exit(main())
