"""End to end: `dvc repro` of a micro profile in a fresh copy of the project, as a user runs it."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.slow

MICRO = {
    "resolution": 32, "ball_resolution": 32, "ball_samples": 8, "views_per_scene": 1, "lights_per_view": 2,
    "scenes": {"train": 2, "val": 1, "test": 1}, "cycles": {"samples": 8, "adaptive_min_samples": 4},
}


def _run(args, cwd, env):
    r = subprocess.run(args, cwd=cwd, env=env, capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, f"{args}\n{r.stdout}\n{r.stderr}"
    return r.stdout


@pytest.fixture(scope="module")
def project(tmp_path_factory):
    """A fresh git + DVC project holding this checkout's code and a micro params.yaml."""
    d = tmp_path_factory.mktemp("project")
    for name in ("pilight", "stages"):
        shutil.copytree(ROOT / name, d / name, ignore=shutil.ignore_patterns("__pycache__"))
    for name in ("dvc.yaml", ".gitignore"):
        shutil.copy(ROOT / name, d / name)
    params = yaml.safe_load((ROOT / "params.yaml").read_text())
    params["render"].update(MICRO)
    (d / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    env = {**os.environ, "DVC_NO_ANALYTICS": "1", "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"}
    _run(["git", "init", "-q"], d, env)
    _run([sys.executable, "-m", "dvc", "init", "-q"], d, env)
    _run([sys.executable, "-m", "dvc", "repro"], d, env)
    return d, env


def _dvc(project, *args):
    d, env = project
    return _run([sys.executable, "-m", "dvc", *args], d, env)


def test_repro_produces_renders_and_shards(project):
    d, _ = project
    manifest = json.loads((d / "data" / "renders" / "manifest.json").read_text())
    assert {s["split"] for s in manifest["scenes"]} == {"train", "val", "test"}
    index = json.loads((d / "data" / "shards" / "index.json").read_text())
    assert index["splits"]["train"]["samples"] == 2 * 1 * 2
    assert "dvc.lock" in os.listdir(d)


def test_nothing_reruns_and_shard_param_touches_only_shard(project):
    assert "Data and pipelines are up to date" in _dvc(project, "status")
    d, _ = project
    params = yaml.safe_load((d / "params.yaml").read_text())
    params["shard"]["pairs_per_view"] = 1
    (d / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    status = _dvc(project, "status", "--json")
    assert set(json.loads(status)) == {"shard"}, status
