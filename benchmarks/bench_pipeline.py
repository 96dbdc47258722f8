"""Seconds per stage of the pipeline, one line per stage, with its work per second.

    python benchmarks/bench_pipeline.py                      # every stage of dvc.yaml, in order
    python benchmarks/bench_pipeline.py --stages train_relight relight --json /tmp/after.json

Each stage runs as `dvc repro --force --single-item STAGE` (so dvc.lock stays true and the time
includes DVC's own hashing), from the repository root, with its output hidden in a log file. The
work column is read from params.yaml and the stage's outputs: (view, light) bundles rendered,
samples sharded, optimizer steps, images predicted, pairs relit. Stages run strictly one after the
other; on 2 cores anything else running beside them is measured too, so run it on an idle machine.
It reruns everything asked for: the whole pipeline takes as long as `dvc repro` from nothing.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]


def work_units(stage: str, params: dict) -> tuple[float | None, str]:
    """(amount, unit) of the work a stage does, from params.yaml and its outputs; (None, '') if unknown."""
    r = params["render"]
    if stage == "render":
        return sum(r["scenes"].values()) * r["views_per_scene"] * r["lights_per_view"], "bundles"
    if stage == "shard":
        index = json.loads((ROOT / "data/shards/index.json").read_text())
        return sum(s["samples"] for s in index["splits"].values()), "samples"
    if stage in ("train_intrinsics", "train_relight"):
        section = "intrinsics" if stage == "train_intrinsics" else "relight"
        return params[section]["train"]["steps"], "steps"
    if stage == "infer_intrinsics":
        return len(list((ROOT / "data/intrinsics_pred").glob("*/*/albedo.exr"))), "images"
    if stage == "relight":
        return len(list((ROOT / "data/relit").glob("*/*/relit.exr"))), "pairs"
    return None, ""


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--stages", nargs="*", help="default: every stage of dvc.yaml, in its order")
    ap.add_argument("--json", type=Path, help="also write the rows here")
    ap.add_argument("--log", type=Path, default=ROOT / "logs/bench_pipeline.log")
    args = ap.parse_args(argv)
    order = list(yaml.safe_load((ROOT / "dvc.yaml").read_text())["stages"])
    stages = args.stages or order
    unknown = [s for s in stages if s not in order]
    if unknown:
        print(f"bench_pipeline: no stage {unknown} in dvc.yaml (stages: {order})", file=sys.stderr)
        return 2
    params = yaml.safe_load((ROOT / "params.yaml").read_text())
    args.log.parent.mkdir(parents=True, exist_ok=True)
    rows, total = [], 0.0
    print("| stage | seconds | work | per second |\n|---|---|---|---|", flush=True)
    with open(args.log, "a") as log:
        for stage in stages:
            log.write(f"\n=== {stage} ({time.strftime('%Y-%m-%d %H:%M:%S')})\n")
            log.flush()
            t0 = time.perf_counter()
            rc = subprocess.run(
                ["dvc", "repro", "--force", "--single-item", stage], cwd=ROOT, stdout=log, stderr=subprocess.STDOUT
            ).returncode
            seconds = time.perf_counter() - t0
            if rc != 0:
                print(f"bench_pipeline: stage {stage} failed (exit {rc}); its output is in {args.log}", file=sys.stderr)
                return 1
            amount, unit = work_units(stage, params)
            total += seconds
            rows.append({"stage": stage, "seconds": seconds, "work": amount, "unit": unit})
            rate = f"{amount / seconds:.2f} {unit}/s" if amount else ""
            work = f"{amount:g} {unit}" if amount else ""
            print(f"| {stage} | {seconds:.1f} | {work} | {rate} |", flush=True)
    print(f"| **total** | **{total:.1f}** | | |")
    if args.json:
        args.json.write_text(json.dumps({"rows": rows, "total_seconds": total}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
