"""Crash test: SIGKILL a stage at a random moment, rerun `dvc repro`, and check the outputs are
byte-identical to a clean run's.

    python benchmarks/crash_test.py --kills 10 [--seed 0] [--keep DIR]

Works in a fresh copy of this project (git + DVC, the code of this checkout) with a micro params
profile (tests/test_pipeline_e2e.py's), so it takes minutes, not hours:

1. a clean `dvc repro` gives the reference digest of every deterministic output and each stage's time;
2. each kill picks a stage (render, shard, train_intrinsics, infer_intrinsics, train_relight,
   relight), removes its `persist: true` work (the renders, the training checkpoints: otherwise the
   forced run would find everything done and finish before the kill), runs
   `dvc repro --force --single-item STAGE` in its own process group and SIGKILLs the group after a
   random fraction of that stage's clean time;
3. then plain `dvc repro` (what a user types after a crash) must finish, and every output must
   match the reference byte for byte.

Printed per kill: the stage, when it was killed, whether the rerun survived (exit 0 and identical
bytes), and the rerun's seconds against a clean run of the stages it reran ("redone"). The outputs
of `evaluate`, `trade` and `render_trade` hold timings or are derived from the others; they are
rerun but not compared.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
STAGES = ["render", "shard", "train_intrinsics", "infer_intrinsics", "train_relight", "relight"]
COMPARED = ["data/renders", "data/shards", "models/intrinsics", "data/intrinsics_pred", "models/relight", "data/relit"]
PERSISTED = {
    "render": ["data/renders"],
    "train_intrinsics": ["checkpoints/intrinsics"],
    "train_relight": ["checkpoints/relight"],
}  # dvc.yaml's persist: true outputs


def micro_project(d: Path) -> dict:
    sys.path.insert(0, str(ROOT))
    from tests.micro_project import make_micro_project

    return make_micro_project(d, train={"steps": 12})  # long enough to be killed mid-training


def digest(d: Path) -> dict[str, str]:
    out = {}
    for rel in COMPARED:
        for p in sorted((d / rel).rglob("*")):
            if p.is_file():
                out[str(p.relative_to(d))] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def dvc(d: Path, env: dict, *args: str, log) -> tuple[int, float]:
    t0 = time.perf_counter()
    rc = subprocess.run(
        [sys.executable, "-m", "dvc", *args], cwd=d, env=env, stdout=log, stderr=subprocess.STDOUT
    ).returncode
    return rc, time.perf_counter() - t0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--kills", type=int, default=10)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--keep", type=Path, help="work here (kept) instead of a temporary folder")
    args = ap.parse_args(argv)
    rng = random.Random(args.seed)
    d = args.keep or Path(tempfile.mkdtemp(prefix="pilight_crash_"))
    d.mkdir(parents=True, exist_ok=True)
    env = micro_project(d)
    log = open(d / "crash_test.log", "a")
    clean = {}
    for stage in [*STAGES, "evaluate", "trade", "render_trade"]:
        rc, clean[stage] = dvc(d, env, "repro", "--single-item", stage, log=log)
        if rc:
            print(f"crash_test: the clean run failed at {stage}; see {d / 'crash_test.log'}", file=sys.stderr)
            return 1
    reference = digest(d)
    print(f"clean run: {sum(clean.values()):.0f} s; {len(reference)} output files compared; in {d}")
    print("| kill | stage | killed after | rerun exit | identical | rerun s | clean s of the stages rerun |")
    print("|---|---|---|---|---|---|---|")
    survived = 0
    for k in range(1, args.kills + 1):
        stage = rng.choice(STAGES)
        after = rng.uniform(0.1, 0.9) * clean[stage]
        log.write(f"\n=== kill {k}: {stage} after {after:.1f} s\n")
        log.flush()
        for rel in PERSISTED.get(stage, []):
            shutil.rmtree(d / rel, ignore_errors=True)
        finished = False
        proc = subprocess.Popen(
            [sys.executable, "-m", "dvc", "repro", "--force", "--single-item", stage],
            cwd=d,
            env=env,
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        try:
            proc.wait(timeout=after)
            finished = True  # the stage ended before its kill time: this kill interrupted nothing
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        rc, seconds = dvc(d, env, "repro", log=log)
        # what a clean run of the same stages costs: the killed stage and everything after it
        redone = sum(clean[s] for s in [*STAGES, "evaluate", "trade", "render_trade"][STAGES.index(stage) :])
        same = rc == 0 and digest(d) == reference
        survived += same
        when = f"{after:.1f} s" + (" (it had ended)" if finished else "")
        print(
            f"| {k} | {stage} | {when} | {rc} | {'yes' if same else 'NO'} | {seconds:.0f} | {redone:.0f} |", flush=True
        )
    print(f"survived {survived} of {args.kills} kills")
    return 0 if survived == args.kills else 1


if __name__ == "__main__":
    sys.exit(main())
