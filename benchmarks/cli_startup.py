"""The whole `pilight relight` command, in fresh processes: what keeping the garbage collector off its start
and exit buys (pilight.process_gc).

    python benchmarks/cli_startup.py [--photo FILE] [--rounds 7] [--models DIR]

Two ways to run the same command, alternated round by round so that a drift of the machine hits both:
* console: the installed `pilight` entry point (pilight.cli.console: collection held while importing and
  loading, everything then frozen, frozen again at exit);
* main:    pilight.cli.main in a plain `python -c` process (CPython's default collector thresholds).
Prints each run's wall seconds, the medians, and the paired difference (main - console) as mean and
min..max over rounds, with the machine. Default photo: scikit-image's astronaut (512^2), written to a
temporary folder; default models: the pipeline's models/, else the shipped base (the command's own rule).
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def _astronaut(folder: Path) -> Path:
    from PIL import Image

    try:
        from skimage.data import astronaut
    except ImportError:
        raise SystemExit("no --photo given and scikit-image is not installed: pip install -e '.[test]'") from None
    path = folder / "astronaut.png"
    Image.fromarray(astronaut()).save(path)
    return path


def _wall(cmd: list[str], cwd: Path) -> float:
    t0 = time.perf_counter()
    done = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} exited {done.returncode}:\n{done.stderr[-2000:]}")
    return wall


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--photo", type=Path, default=None)
    ap.add_argument("--rounds", type=int, default=7)
    ap.add_argument("--models", type=Path, default=None, help="default: the command's own (models/, else the base)")
    args = ap.parse_args(argv)
    from pilight import machine

    console = Path(sys.executable).with_name("pilight")
    if not console.is_file():
        raise SystemExit(f"{console}: no installed `pilight` command beside this Python; pip install -e .")
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        photo = args.photo.resolve() if args.photo else _astronaut(work)
        tail = ["relight", str(photo), "--light", "left", "-o", "out", "--overwrite"]
        if args.models is not None:
            tail += ["--models", str(args.models.resolve())]
        ways = {
            "console": [str(console), *tail],
            "main": [sys.executable, "-c", "import sys; from pilight.cli import main; sys.exit(main())", *tail],
        }
        _wall(ways["console"], work)  # warm the file caches once, untimed
        walls: dict[str, list[float]] = {k: [] for k in ways}
        for r in range(args.rounds):
            for name in ways if r % 2 == 0 else reversed(list(ways)):
                walls[name].append(_wall(ways[name], work))
            print(f"round {r + 1}: console {walls['console'][-1]:.2f} s, main {walls['main'][-1]:.2f} s", flush=True)
    diffs = [m - c for m, c in zip(walls["main"], walls["console"])]
    print(f"\n{machine.one_line()}; photo {photo.name}; {args.rounds} rounds")
    print("| way | median s | min | max |")
    print("|---|---|---|---|")
    for name, w in walls.items():
        print(f"| {name} | {statistics.median(w):.2f} | {min(w):.2f} | {max(w):.2f} |")
    print(f"main - console: mean {statistics.mean(diffs):+.2f} s, per round {min(diffs):+.2f} .. {max(diffs):+.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
