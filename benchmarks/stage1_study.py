"""Stage 1 alone, trained and scored in one process: the study behind `intrinsics.objective`/`layout`
and the scaling study (docs: stage 1).

    python benchmarks/stage1_study.py --shards data/shards -S intrinsics.train.steps=600 --seeds 42 43 44 \\
        --json /tmp/paper.json
    python benchmarks/stage1_study.py --shards data/shards -S intrinsics.objective=task \\
        -S intrinsics.layout=joint -S intrinsics.schedule.terminal_input=zero --seeds 42 43 44 --json /tmp/task.json
    python benchmarks/stage1_study.py --compare /tmp/paper.json /tmp/task.json

Each seed trains the params' `intrinsics` section with the -S overrides (dotted keys, YAML values)
through the training loop the stage uses (accelerate, autocast, the same batches), then predicts the
test split single-step and prints the held-out figures beside the wall-clock seconds of training and
the CPU it ran on. ``--train-images N`` also scores N training images (memorisation shows as the gap).
``--also-score NAME=SHARDS`` scores the same weights on another test split too (figures prefixed NAME_).
``--compare`` prints, per metric, each run's mean +- sd and the paired difference (by seed) with its
95% t-interval. Nothing is written but the --json file; checkpoints live in a temporary folder.
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))  # normal_frame

from pilight.params import IntrinsicsParams, SamplingParams, read_params  # noqa: E402

SINGLE_STEP = SamplingParams(mode="single_step", cfg_scale=1.0)
# t quantiles (two-sided 95%) for n - 1 degrees of freedom, n = 2..10
T95 = {1: 12.706, 2: 4.303, 3: 3.182, 4: 2.776, 5: 2.571, 6: 2.447, 7: 2.365, 8: 2.306, 9: 2.262}


def cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                flags = Path("/proc/cpuinfo").read_text()
                native = "avx512_bf16" in flags or "amx_bf16" in flags
                return f"{line.split(':', 1)[1].strip()} ({'AVX512-BF16' if native else 'no native bf16'})"
    except OSError:
        pass
    return platform.processor() or "unknown CPU"


def apply_overrides(section: dict, overrides: list[str], root: str = "intrinsics") -> dict:
    for item in overrides:
        key, _, value = item.partition("=")
        parts = key.split(".")
        if parts[0] != root:
            raise SystemExit(f"-S {item}: only {root}.* keys are studied here")
        node = section
        for p in parts[1:-1]:
            node = node.setdefault(p, {})
        node[parts[-1]] = yaml.safe_load(value)
    return section


@torch.no_grad()
def score(task, shards: Path, split: str, limit: int | None = None) -> dict[str, float]:
    """Held-out figures of ``task``'s model on ``split`` (single-step), masked as evaluate does."""
    from pilight.data.shard_reader import intrinsics_dataset, make_loader
    from pilight.eval.metrics import angular_errors, masked_mae, masked_psnr, normal_metrics
    from pilight.train.map_losses import albedo_scale

    preds, gts, n = {k: [] for k in ("albedo", "normal", "roughness", "metallic")}, [], 0
    for b in make_loader(intrinsics_dataset(shards, split, shuffle=False), 8):
        out = task.predict(b["image"], tuple(preds), SINGLE_STEP)
        for k in preds:
            preds[k].append(out[k].cpu())
        gts.append({k: b[k] for k in ("image", "mask", *preds)})
        n += b["image"].shape[0]
        if limit is not None and n >= limit:
            break
    p = {k: torch.cat(v) for k, v in preds.items()}
    g = {k: torch.cat([x[k] for x in gts]) for k in gts[0]}
    m = g["mask"]
    alpha = albedo_scale(p["albedo"], g["albedo"], (m > 0.5).float())[:, None, None, None]
    a_in = g["image"].clamp(0, 1)
    alpha_in = albedo_scale(a_in, g["albedo"], (m > 0.5).float())[:, None, None, None]
    normals = normal_metrics(angular_errors(p["normal"], g["normal"], m))
    turns = [normal_turn(p["normal"][i], g["normal"][i], m[i, 0] > 0.5) for i in range(len(m)) if m[i].sum() > 0]
    return {
        "albedo_psnr": masked_psnr(p["albedo"], g["albedo"], m),
        "albedo_si_psnr": masked_psnr((alpha * p["albedo"]).clamp(0, 1), g["albedo"], m),
        "input_albedo_si_psnr": masked_psnr((alpha_in * a_in).clamp(0, 1), g["albedo"], m),
        "normal_mean": normals["mean_deg"],
        "normal_median": normals["median_deg"],
        "roughness_mae": masked_mae(p["roughness"], g["roughness"], m),
        "metallic_mae": masked_mae(p["metallic"], g["metallic"], m),
        # benchmarks/normal_frame.py: the turn about the camera's x axis that best aligns an image's normals
        # (mean over images), and the normals' mean error at each image's best turn (a perfect-pitch oracle)
        "normal_turn_deg": statistics.mean(t[0] for t in turns),
        "normal_mean_turned": statistics.mean(t[1] for t in turns),
        "images": n,
    }


def normal_turn(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor) -> tuple[float, float]:
    """(best turn in degrees, mean angular error there) of one image's normals (3, H, W) on ``mask`` (H, W)."""
    from normal_frame import MAX_DEG, best_turn

    unit = lambda n: torch.nn.functional.normalize(n.float(), dim=0)[:, mask]
    return best_turn(unit(pred), unit(gt), range(-MAX_DEG, MAX_DEG + 1))


def run_seed(
    raw: dict,
    shards: Path,
    seed: int,
    train_images: int,
    eval_shards: Path | None = None,
    also: dict[str, Path] | None = None,
) -> dict:
    from pilight.train.intrinsics import IntrinsicsTask
    from pilight.train.loop import train

    p = IntrinsicsParams.model_validate(raw)
    torch.manual_seed(seed)
    task = IntrinsicsTask(p, shards, seed=seed)
    if p.unet.init == "base":
        from pilight.base_model import init_from_base

        init_from_base(task.stack, p, "intrinsics")
    with tempfile.TemporaryDirectory() as ckpt:
        stats = train(task, p.train, Path(ckpt), None, seed=seed)
    task.stack.model.eval()
    t0 = time.perf_counter()
    test = eval_shards or shards
    out = {"seed": seed, "train_seconds": stats["seconds"], "steps": stats["steps"], **score(task, test, "test")}
    out["predict_seconds"] = time.perf_counter() - t0
    if train_images:
        out |= {f"train_{k}": v for k, v in score(task, shards, "train", train_images).items()}
    for name, extra in (also or {}).items():  # the same weights on other test splits, prefixed by their name
        out |= {f"{name}_{k}": v for k, v in score(task, extra, "test").items()}
    return out


def compare(paths: list[Path]) -> None:
    runs = [json.loads(p.read_text()) for p in paths]
    base = {r["seed"]: r for r in runs[0]["seeds"]}
    metrics = [k for k, v in runs[0]["seeds"][0].items() if isinstance(v, int | float) and k != "seed"]
    print(
        f"| metric | {' | '.join(r['name'] for r in runs)} | "
        + " | ".join(f"{r['name']} - {runs[0]['name']}" for r in runs[1:])
        + " |"
    )
    print("|---" * (2 * len(runs)) + "|")
    for k in metrics:
        cells = []
        for r in runs:
            vals = [s[k] for s in r["seeds"] if s.get(k) is not None]
            sd = statistics.stdev(vals) if len(vals) > 1 else float("nan")
            cells.append(f"{statistics.mean(vals):.3f} ± {sd:.3f}")
        for r in runs[1:]:
            diffs = [s[k] - base[s["seed"]][k] for s in r["seeds"] if s["seed"] in base and s.get(k) is not None]
            if len(diffs) > 1:
                m, sd = statistics.mean(diffs), statistics.stdev(diffs)
                half = T95.get(len(diffs) - 1, 1.96) * sd / math.sqrt(len(diffs))
                cells.append(f"{m:+.3f} [{m - half:+.3f}, {m + half:+.3f}]")
            else:
                cells.append("n/a")
        print(f"| {k} | " + " | ".join(cells) + " |")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--params", type=Path, default=Path("params.yaml"))
    ap.add_argument("--shards", type=Path, default=Path("data/shards"))
    ap.add_argument("-S", dest="overrides", action="append", default=[], metavar="intrinsics.KEY=VALUE")
    ap.add_argument("--seeds", type=int, nargs="+", default=[42])
    ap.add_argument("--name", default=None, help="the run's name in --compare tables (default: the overrides)")
    ap.add_argument("--train-images", type=int, default=0)
    ap.add_argument("--eval-shards", type=Path, default=None, help="score the test split of these shards instead")
    ap.add_argument(
        "--also-score",
        action="append",
        default=[],
        metavar="NAME=SHARDS",
        help="also score the test split of these shards, figures prefixed NAME_ (repeatable)",
    )
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--compare", type=Path, nargs="+", default=None, help="print a table of these --json files")
    args = ap.parse_args(argv)
    if args.compare:
        compare(args.compare)
        return 0
    if args.threads:
        torch.set_num_threads(args.threads)
    raw = apply_overrides(read_params(args.params)["intrinsics"], args.overrides)
    IntrinsicsParams.model_validate(raw)  # a bad override fails before any training
    also = {}
    for item in args.also_score:
        name, sep, path = item.partition("=")
        if not sep or not name or not (Path(path) / "index.json").is_file():
            raise SystemExit(f"--also-score {item}: want NAME=SHARDS, a shard folder with an index.json")
        also[name] = Path(path)
    result = {"name": args.name or " ".join(args.overrides) or "params", "overrides": args.overrides}
    result |= {"cpu": cpu_name(), "threads": torch.get_num_threads(), "seeds": []}
    for seed in args.seeds:
        r = run_seed(raw, args.shards, seed, args.train_images, args.eval_shards, also)
        result["seeds"].append(r)
        print(json.dumps(r), flush=True)
        if args.json:
            args.json.write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
