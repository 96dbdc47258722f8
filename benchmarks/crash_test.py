"""Crash test: SIGKILL a stage at a random moment, rerun `dvc repro`, and check the outputs are
byte-identical to a clean run's; then the same for the photo CLI's relight path.

    python benchmarks/crash_test.py --kills 10 --cli-kills 10 [--seed 0] [--keep DIR]
    python benchmarks/crash_test.py --kills 0 --cli-kills 20      # the CLI part alone (a minute or two)

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
bytes), the temporaries of killed writes still in the project after the rerun (a stage sweeps its own
when it runs; one DVC restores from its run cache does not run, so they wait for its next run), and
the rerun's seconds against a clean run of the stages it reran ("redone"). The outputs
of `evaluate`, `trade` and `render_trade` hold timings or are derived from the others; they are
rerun but not compared.

The CLI part (``--cli-kills``, issue 36): `pilight relight` of CLI_PHOTOS photos under CLI_LIGHTS lights
each, with a tiny model pair saved by save_model (random weights: the path, not the accuracy). A clean run
gives the reference bytes. Then, each time from an empty output folder, the command runs in its own
process group and is SIGKILLed after a random 10-90 % of the clean run's time. Checked right after the
kill: no light folder under its final name lacks any of its files. Then the same command (what a user
types) must exit 0, say it removed the killed run's temporary when there was one, leave no temporary,
and end with the reference bytes. Printed per kill: when, the light folders complete at the kill, partial
ones under a final name (must be 0), temporaries left, the rerun's exit, whether identical, the rerun's
seconds against the clean run's.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import random
import re
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
    from fixtures.micro_project import make_micro_project

    return make_micro_project(d, train={"steps": 12})  # long enough to be killed mid-training


def digest(d: Path) -> dict[str, str]:
    out = {}
    for rel in COMPARED:
        for p in sorted((d / rel).rglob("*")):
            if p.is_file():
                out[str(p.relative_to(d))] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def temporaries(d: Path) -> int:
    """What killed writes leave in the project's output folders (pilight.atomic.sweep_temporaries' patterns)."""
    sys.path.insert(0, str(ROOT))
    from pilight.atomic import _FILE_TEMP, _INNER_TEMP

    beside = re.compile(r"^\..+\.(tmp-.+|old-.+|tmp|old)$")
    found = 0
    for top in ("data", "models", "metrics", "reports", "plots", "checkpoints"):
        for p in (d / top).rglob(".*") if (d / top).is_dir() else []:
            found += bool(beside.match(p.name) or _FILE_TEMP.match(p.name) or _INNER_TEMP.match(p.name))
    return found


def dvc(d: Path, env: dict, *args: str, log) -> tuple[int, float]:
    t0 = time.perf_counter()
    rc = subprocess.run(
        [sys.executable, "-m", "dvc", *args], cwd=d, env=env, stdout=log, stderr=subprocess.STDOUT
    ).returncode
    return rc, time.perf_counter() - t0


CLI_PHOTOS = 4
CLI_LIGHTS = ["--light", "left", "--light", "right", "--azimuth", "45", "--elevation", "20"]
CLI_LIGHT_COUNT = 3  # left, right and the azimuth-45 light
CLI_FILES_PER_LIGHT = 9  # relit, diffuse, specular (.exr + .png), ball.exr, ball.png, contact.png


def cli_setup(d: Path) -> tuple[list[str], dict]:
    """Tiny models, CLI_PHOTOS photos (256 x 192, smooth random colour fields) and the relight command."""
    import numpy as np
    from PIL import Image

    sys.path.insert(0, str(ROOT))
    from fixtures.tiny_models import save_tiny_models

    models = save_tiny_models(d / "cli_models")
    photos = d / "cli_photos"
    photos.mkdir(exist_ok=True)
    g = np.random.default_rng(0)
    for i in range(CLI_PHOTOS):
        coarse = g.random((6, 8, 3))
        img = np.kron(coarse, np.ones((32, 32, 1)))  # 192 x 256
        Image.fromarray((img * 255).astype(np.uint8)).save(photos / f"photo{i}.png")
    cmd = [sys.executable, "-m", "pilight.cli", "relight", str(photos), "--models", str(models), *CLI_LIGHTS]
    cmd += ["--resolution", "64", "--device", "cpu"]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    return cmd, env


def tree(out: Path) -> dict[str, str]:
    return {
        str(p.relative_to(out)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(out.rglob("*"))
        if p.is_file()
    }


def light_folders(out: Path) -> tuple[int, int, int]:
    """(complete light folders, partial ones under a final name, temporaries) in a relight output folder."""
    complete = partial = temps = 0
    for photo in sorted(out.iterdir()) if out.is_dir() else []:
        if photo.name.startswith("."):
            temps += 1
            continue
        for light in sorted(photo.iterdir()):
            if light.name.startswith("."):
                temps += 1
            elif len([f for f in light.iterdir() if not f.name.startswith(".")]) == CLI_FILES_PER_LIGHT:
                complete += 1
            else:
                partial += 1
    return complete, partial, temps


def cli_crash_test(d: Path, kills: int, rng: random.Random, log) -> int:
    """The CLI part (module docstring); returns the kills survived."""
    cmd, env = cli_setup(d)
    ref = d / "cli_reference"
    t0 = time.perf_counter()
    rc = subprocess.run([*cmd, "-o", str(ref)], env=env, stdout=log, stderr=subprocess.STDOUT).returncode
    clean = time.perf_counter() - t0
    if rc:
        print(f"crash_test: the clean CLI run failed; see {d / 'crash_test.log'}", file=sys.stderr)
        return 0
    reference = tree(ref)
    print(
        f"\nCLI: `pilight relight` of {CLI_PHOTOS} photos x {CLI_LIGHT_COUNT} lights: clean run "
        f"{clean:.1f} s, {len(reference)} output files compared"
    )
    print(
        "| kill | killed after | lights complete at the kill | partial under a final name | temporaries left "
        "| rerun exit | identical | rerun s | clean s |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    survived = 0
    out = d / "cli_out"
    for k in range(1, kills + 1):
        shutil.rmtree(out, ignore_errors=True)
        after = rng.uniform(0.1, 0.9) * clean
        log.write(f"\n=== CLI kill {k}: after {after:.1f} s\n")
        log.flush()
        proc = subprocess.Popen(
            [*cmd, "-o", str(out)], env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True
        )
        finished = False
        try:
            proc.wait(timeout=after)
            finished = True
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        complete, partial, temps = light_folders(out)
        t0 = time.perf_counter()
        r = subprocess.run([*cmd, "-o", str(out)], env=env, capture_output=True, text=True)
        seconds = time.perf_counter() - t0
        log.write(r.stderr)
        said = temps == 0 or "left by a killed run" in r.stderr
        same = r.returncode == 0 and partial == 0 and said and light_folders(out)[2] == 0 and tree(out) == reference
        survived += same
        when = f"{after:.1f} s" + (" (it had ended)" if finished else "")
        print(
            f"| {k} | {when} | {complete} | {partial} | {temps} | {r.returncode} | {'yes' if same else 'NO'} "
            f"| {seconds:.1f} | {clean:.1f} |",
            flush=True,
        )
    print(f"CLI: survived {survived} of {kills} kills")
    return survived


def stage_crash_test(d: Path, kills: int, rng: random.Random, log) -> int | None:
    """The DVC part; the kills survived, None when the clean run failed."""
    env = micro_project(d)
    clean = {}
    for stage in [*STAGES, "evaluate", "trade", "render_trade"]:
        rc, clean[stage] = dvc(d, env, "repro", "--single-item", stage, log=log)
        if rc:
            print(f"crash_test: the clean run failed at {stage}; see {d / 'crash_test.log'}", file=sys.stderr)
            return None
    reference = digest(d)
    print(f"clean run: {sum(clean.values()):.0f} s; {len(reference)} output files compared; in {d}")
    print(
        "| kill | stage | killed after | rerun exit | identical | temporaries left | rerun s | clean s of the stages rerun |"
    )
    print("|---|---|---|---|---|---|---|---|")
    survived = 0
    for k in range(1, kills + 1):
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
            f"| {k} | {stage} | {when} | {rc} | {'yes' if same else 'NO'} | {temporaries(d)} | {seconds:.0f} "
            f"| {redone:.0f} |",
            flush=True,
        )
    print(f"survived {survived} of {kills} kills")
    return survived


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--kills", type=int, default=10, help="kills of DVC stages (0: skip that part)")
    ap.add_argument("--cli-kills", type=int, default=10, help="kills of `pilight relight` (0: skip that part)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--keep", type=Path, help="work here (kept) instead of a temporary folder")
    args = ap.parse_args(argv)
    rng = random.Random(args.seed)
    d = args.keep or Path(tempfile.mkdtemp(prefix="pilight_crash_"))
    d.mkdir(parents=True, exist_ok=True)
    log = open(d / "crash_test.log", "a")
    survived = args.kills and stage_crash_test(d, args.kills, rng, log)
    cli_survived = args.cli_kills and cli_crash_test(d, args.cli_kills, random.Random(args.seed), log)
    if survived is None:
        return 1
    return 0 if survived == args.kills and cli_survived == args.cli_kills else 1


if __name__ == "__main__":
    sys.exit(main())
