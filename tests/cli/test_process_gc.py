"""The `pilight` command keeps the garbage collector off its start and exit (pilight.process_gc), and gives
it back for the work: a long batch or the app's server must collect at CPython's own thresholds, and an
in-process caller of pilight.cli.main (these tests, a notebook) must keep its collector as it was. The DVC
stages skip the exit's last collection too (pilight.stage_cli.run_stage)."""

from __future__ import annotations

import gc
import subprocess
import sys
import tomllib

import numpy as np
from PIL import Image

from fixtures.stage_scripts import REPO, stage_env
from pilight import process_gc


def _child(code: str, *args: str, cwd=REPO) -> str:
    """stdout of ``code`` run by a fresh interpreter with ``args``, which must exit 0."""
    r = subprocess.run(
        [sys.executable, "-c", code, *args], capture_output=True, text=True, cwd=cwd, env=stage_env(), timeout=300
    )
    assert r.returncode == 0, r.stderr[-2000:]
    return r.stdout


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
    rc, restored, frozen = _child(CHILD, *args, cwd=tmp_path).split()
    assert (rc, restored, frozen) == ("0", "True", "True")  # thresholds given back once the models were loaded
    assert (tmp_path / "out" / "photo" / "left" / "relit.png").is_file()


# A reference cycle with a finaliser, left for the interpreter's last collection: its line is printed
# only if that collection walks it, i.e. only if nothing froze it first.
CYCLE_AT_EXIT = """
class Cycle:
    def __del__(self):
        print("collected at exit", flush=True)
c = Cycle(); c.me = c; del c
print("end of program", flush=True)
"""


def test_without_the_freeze_the_exit_walks_what_is_left():  # the control: the probe below can see a walk
    assert _child(CYCLE_AT_EXIT).split() == ["end", "of", "program", "collected", "at", "exit"]


def test_freeze_at_exit_leaves_the_last_collection_nothing_to_walk():
    out = _child(
        "from pilight import process_gc\nprocess_gc.freeze_at_exit()\nprocess_gc.freeze_at_exit()\n" + CYCLE_AT_EXIT
    )
    assert out.split() == ["end", "of", "program"]


def test_a_stage_process_skips_the_exit_walk():
    run = (
        "from pilight.stage_cli import run_stage\n"
        "assert run_stage('probe', 'doc', [], ['base'], lambda ap: None, lambda args, base: 0) == 0\n"
    )
    assert _child(run + CYCLE_AT_EXIT).split() == ["end", "of", "program"]
