"""Does stage 1 let the light flip on real photos? Stage-1 models (one per training seed, in arms) relit
under the left and the right light with one stage 2, on four scikit-image photos, and scored on a test split.

    python benchmarks/flip_study.py --arm B=b42/models,b43/models,b44/models \\
        --arm E=e42/models,e43/models,e44/models [--relight weights/pilight-base] [--shards data/shards]

Each arm's folders hold intrinsics/ (a pipeline's models/ or a base); stage 2 is --relight's for every
arm (the shipped base by default), so the arms differ only in stage 1. Per run it prints the relit
asymmetry (R - L)/(R + L) under the left / right light of each photo (the flip test's measure) and its
flip margin min(-left, right), > 0 when the sign flips; with --shards, stage 1's figures on that test split
(benchmarks/stage1_study.py's ``score``: single step, masked as evaluate does). With two arms of equal
size, the runs are paired in order (same training seed) and the table gives each figure's paired
difference, second arm minus first, its mean and sample standard deviation.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

PHOTOS = ("astronaut", "chelsea", "coffee", "rocket")  # skimage.data: a portrait, a cat, a cup from above, a rocket
FIGURES = {  # figure -> higher is better
    **dict.fromkeys(PHOTOS, True),
    "normal_mean": False,
    "normal_median": False,
    "albedo_si_psnr": True,
    "roughness_mae": False,
    "metallic_mae": False,
}


def run(pipe, folder: Path, shards: Path | None) -> dict[str, float]:
    import torch
    from skimage import data

    from benchmarks.stage1_study import score
    from pilight import lights
    from pilight.eval.photo_measures import halves_asymmetry
    from pilight.pipeline import load_stage

    pipe.intrinsics_model = load_stage(folder, "intrinsics", torch.device("cpu"))[0]
    row, shown = {}, []
    for name in PHOTOS:
        out = pipe.relight(getattr(data, name)(), [lights.named("left"), lights.named("right")], name=name)
        left, right = (halves_asymmetry(x) for x in out.relit)
        row[name] = min(-left, right)
        shown.append(f"{name} {left:+.3f} / {right:+.3f}")
    if shards is not None:
        torch.manual_seed(0)
        with torch.no_grad():
            s = score(pipe.intrinsics_model, shards, "test")
        row |= {k: s[k] for k in FIGURES if k in s}
    print(f"{folder}: " + "; ".join(shown), flush=True)
    return row


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--arm", action="append", required=True, help="NAME=FOLDER[,FOLDER...] (one per seed)")
    ap.add_argument("--relight", type=Path, default=None, help="models folder of stage 2 (default: the shipped base)")
    ap.add_argument("--shards", type=Path, default=None, help="a shards folder whose test split scores stage 1")
    args = ap.parse_args(argv)
    arms = {}
    for spec in args.arm:
        name, _, folders = spec.partition("=")
        if not folders:
            ap.error(f"--arm {spec!r}: expected NAME=FOLDER[,FOLDER...]")
        arms[name] = [Path(f) for f in folders.split(",")]
        for f in arms[name]:
            if not (f / "intrinsics" / "model.safetensors").is_file():
                ap.error(f"--arm {name}: {f / 'intrinsics' / 'model.safetensors'} not found")
    if args.shards is not None and not (args.shards / "index.json").is_file():
        ap.error(f"--shards {args.shards}: no index.json there")
    from pilight import machine
    from pilight.base_model import BASE_DIR
    from pilight.pipeline import PILightPipeline

    pipe = PILightPipeline.from_pretrained(args.relight or BASE_DIR, device="cpu", params=REPO / "params.yaml")
    results = {name: [run(pipe, f, args.shards) for f in folders] for name, folders in arms.items()}
    figures = [k for k in FIGURES if k in next(iter(results.values()))[0]]
    print("| figure | " + " | ".join(f"{n} ({len(r)} runs)" for n, r in results.items()) + " |")
    print("|---|" + "---|" * len(results))
    for k in figures:
        cells = [np.array([r[k] for r in runs]) for runs in results.values()]
        print(
            f"| {k} | " + " | ".join(f"{c.mean():.3f} ± {c.std(ddof=1) if len(c) > 1 else 0:.3f}" for c in cells) + " |"
        )
    names = list(results)
    if len(names) == 2 and len(results[names[0]]) == len(results[names[1]]) > 1:
        print(f"\npaired, {names[1]} - {names[0]}:\n| figure | mean ± sd | {names[1]} better in |\n|---|---|---|")
        for k in figures:
            d = np.array([b[k] - a[k] for a, b in zip(results[names[0]], results[names[1]])])
            better = int(((d > 0) if FIGURES[k] else (d < 0)).sum())
            print(f"| {k} | {d.mean():+.3f} ± {d.std(ddof=1):.3f} | {better} of {len(d)} |")
    for name, runs in results.items():
        print(f"{name}: {sum(r[p] > 0 for r in runs for p in PHOTOS)} of {len(runs) * len(PHOTOS)} photo-runs flip")
    print(f"machine: {machine.one_line()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
