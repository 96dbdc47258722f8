"""End to end: `python -m pilight.seeds` in a micro project (fixtures/micro_project.py), 2 seeds x 2 arms
up to train_intrinsics (one training step: the cheapest seeded stage with metrics), on one render."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from fixtures.micro_project import make_micro_project

pytestmark = pytest.mark.slow

ONE_STEP = {"steps": 1, "checkpoint_every": 1, "image_every": 1}
UP_TO = [
    "--target",
    "train_intrinsics",
    "--metrics-file",
    "dvclive/intrinsics/metrics.json",
    "--keys",
    "final_loss",
    "loss",
]
VARIANT = ["-S", "intrinsics.train.terminal_fraction=1.0"]  # every sample at t = T-1: another step-1 loss
COMMAND = ["--seeds", "42", "43", *UP_TO, *VARIANT]


def _run(args, cwd, env):
    r = subprocess.run(args, cwd=cwd, env=env, capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, f"{args}\n{r.stdout}\n{r.stderr}"
    return r.stdout


@pytest.fixture(scope="module")
def project(tmp_path_factory):
    """The micro project with its renders and shards made and dvc.lock committed, as a user has it."""
    d = tmp_path_factory.mktemp("seeds")
    env = make_micro_project(d, train=ONE_STEP)
    _run([sys.executable, "-m", "dvc", "repro", "shard"], d, env)
    _run(["git", "add", "dvc.lock"], d, env)
    _run(["git", "-c", "user.name=ci", "-c", "user.email=ci@localhost", "commit", "-qm", "renders and shards"], d, env)
    return d, env


def seeds(project, *args):
    d, env = project
    return _run([sys.executable, "-m", "pilight.seeds", *args], d, env)


def test_two_seeds_two_arms_on_the_same_renders(project):
    d, _ = project
    out = seeds(project, *COMMAND, "--json", str(d / "summary.json"))
    assert "[4/4] variant seed 43: dvc exp run --temp -n seeds-variant-s43-" in out and "ETA" in out, out
    summary = json.loads((d / "summary.json").read_text())
    assert [(r["arm"], r["seed"], r["reused"]) for r in summary["runs"]] == [
        ("default", 42, False),
        ("variant", 42, False),
        ("default", 43, False),
        ("variant", 43, False),
    ]
    assert len({r["rev"] for r in summary["runs"]}) == 4
    assert set(summary["metrics"]) == {"final_loss", "loss"}
    row = summary["metrics"]["final_loss"]
    for arm in ("default", "variant"):
        assert row[arm]["seeds"] == [42, 43] and row[arm]["n"] == 2 and row[arm]["sd"] is not None
        assert row[arm]["values"][0] != row[arm]["values"][1], "the two training seeds gave the same loss"
    diff = row["difference"]
    assert diff["n"] == 2 and diff["values"] == [
        v - d for v, d in zip(row["variant"]["values"], row["default"]["values"])
    ]
    assert diff["ci95"][0] <= diff["mean"] <= diff["ci95"][1]
    assert "variant - default" in out and "95% CI" in out and "final_loss" in out
    for run in summary["runs"]:  # every run checked the one render out of the cache
        log = (d / "logs" / "seeds" / f"{run['experiment']}.log").read_text()
        assert "Stage 'render' didn't change, skipping" in log and "Running stage 'train_intrinsics'" in log, log


def test_a_second_call_reuses_the_experiments(project):
    out = seeds(project, *COMMAND)
    assert out.count("reused experiment seeds-") == 4 and "dvc exp run" not in out, out


def test_changed_code_is_not_reused(project):
    d, _ = project
    script = d / "stages" / "train_intrinsics.py"
    script.write_text(script.read_text() + "# changed\n")
    out = seeds(project, "--seeds", "43", *UP_TO)  # the default arm alone, seed 43
    assert "[1/1] default seed 43: dvc exp run --temp" in out and "reused" not in out, out
