"""`pilight decompose/relight` over a folder on 2 CPU processes (torchrun, as `accelerate launch` would
start them): every photo is done by exactly one process, the outputs equal one process's byte for
byte, and a rerun skips what is complete."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from PIL import Image

ROOT = Path(__file__).resolve().parents[2]


def _cli(args: list, processes: int) -> subprocess.CompletedProcess:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT)}  # same threads, same bytes
    launch = (
        [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", str(processes), "-m"]
        if processes > 1
        else [sys.executable, "-m"]
    )
    return subprocess.run(
        [*launch, "pilight.cli", *map(str, args)], env=env, capture_output=True, text=True, timeout=300
    )


def _files(out: Path) -> dict[str, bytes]:
    return {str(p.relative_to(out)): p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()}


def test_two_processes_split_a_folder_and_a_rerun_skips(tmp_path, tiny_models, astronaut):
    photos = tmp_path / "photos"
    photos.mkdir()
    for i in range(5):  # 5 photos on 2 processes: shares of 3 and 2
        Image.fromarray(astronaut[i * 16 : i * 16 + 64 : 2, ::16]).save(photos / f"p{i}.png")
    common = ["--models", tiny_models, "--resolution", "32", "--device", "cpu"]
    one = _cli(["relight", photos, "-o", tmp_path / "one", "--light", "left", *common], 1)
    assert one.returncode == 0, one.stderr[-3000:]
    two = _cli(["relight", photos, "-o", tmp_path / "two", "--light", "left", *common], 2)
    assert two.returncode == 0, two.stderr[-3000:]
    done = sorted(
        int(line.split("relit ")[1].split()[0])
        for line in two.stderr.splitlines()
        if line.startswith("pilight: relit ")
    )
    assert done == [2, 3], two.stderr[-2000:]  # each photo by exactly one process
    assert _files(tmp_path / "two") == _files(tmp_path / "one")
    assert len({k.split("/")[0] for k in _files(tmp_path / "two")}) == 5

    before = {p: p.stat().st_mtime_ns for p in (tmp_path / "two").rglob("*") if p.is_file()}
    again = _cli(["relight", photos, "-o", tmp_path / "two", "--light", "left", *common], 2)
    assert again.returncode == 0, again.stderr[-3000:]
    assert again.stderr.count("already complete") == 2
    assert {p: p.stat().st_mtime_ns for p in (tmp_path / "two").rglob("*") if p.is_file()} == before

    dec = _cli(["decompose", photos, "-o", tmp_path / "dec", *common], 2)
    assert dec.returncode == 0, dec.stderr[-3000:]
    assert sorted(p.name for p in (tmp_path / "dec").iterdir()) == [f"p{i}" for i in range(5)]
