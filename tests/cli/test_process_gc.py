"""The `pilight` command keeps the garbage collector off its start and exit (pilight.process_gc), and gives
it back for the work: a long batch or the app's server must collect at CPython's own thresholds, and an
in-process caller of pilight.cli.main (these tests, a notebook) must keep its collector as it was."""

from __future__ import annotations

import gc
import subprocess
import sys
import tomllib

import numpy as np
from PIL import Image

from fixtures.stage_scripts import REPO, stage_env
from pilight import process_gc


def test_release_restores_the_thresholds_and_freezes_what_the_start_made():
    before = gc.get_threshold()
    try:
        process_gc.hold_collection()
        assert gc.get_threshold()[0] == process_gc.STARTUP_THRESHOLD
        assert gc.get_threshold()[1:] == before[1:]
        process_gc.release_collection()
        assert gc.get_threshold() == before
        assert gc.get_freeze_count() > 0
    finally:
        gc.unfreeze()
        gc.set_threshold(*before)


def test_release_without_hold_leaves_an_in_process_caller_alone():
    before = gc.get_threshold()
    process_gc.release_collection()
    assert gc.get_threshold() == before
    assert gc.get_freeze_count() == 0


def test_the_installed_command_is_the_console_entry_point():
    scripts = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["scripts"]
    assert scripts["pilight"] == "pilight.cli:console"


CHILD = """
import gc, sys
from pilight.cli import console
start = gc.get_threshold()
sys.argv = ["pilight", *sys.argv[1:]]
rc = console()
print(rc, gc.get_threshold() == start, gc.get_freeze_count() > 0)
"""


def test_a_relight_through_the_console_collects_at_cpythons_thresholds_after_loading(tiny_models, tmp_path):
    photo = tmp_path / "photo.png"
    Image.fromarray(np.random.default_rng(0).integers(0, 256, (32, 40, 3), dtype=np.uint8)).save(photo)
    args = ["relight", str(photo), "--light", "left", "--models", str(tiny_models), "-o", str(tmp_path / "out")]
    r = subprocess.run(
        [sys.executable, "-c", CHILD, *args], capture_output=True, text=True, cwd=tmp_path, env=stage_env(), timeout=300
    )
    assert r.returncode == 0, r.stderr[-2000:]
    rc, restored, frozen = r.stdout.split()
    assert (rc, restored, frozen) == ("0", "True", "True")  # thresholds given back once the models were loaded
    assert (tmp_path / "out" / "photo" / "left" / "relit.png").is_file()
