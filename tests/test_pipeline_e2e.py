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


MICRO_UNET = {"block_out_channels": [32, 32], "cross_attention_dim": 32}
MICRO_TRAIN = {"steps": 3, "checkpoint_every": 2, "image_every": 2, "log_every": 1, "warmup_steps": 0}


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
    for stage in ("intrinsics", "relight"):  # a tiny UNet and a few steps: plumbing, not accuracy
        if stage in params:
            params[stage]["unet"].update(MICRO_UNET)
            params[stage]["train"].update(MICRO_TRAIN)
    for stage in ("infer_intrinsics", "relight_infer"):
        if stage in params:
            params[stage]["steps"] = 2
    (d / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    env = {**os.environ, "DVC_NO_ANALYTICS": "1", "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"}
    _run(["git", "init", "-q"], d, env)
    _run([sys.executable, "-m", "dvc", "init", "-q"], d, env)
    # A user's project has commits (dvclive and `dvc exp` need a HEAD).
    _run(["git", "add", "-A"], d, env)
    _run(["git", "-c", "user.name=ci", "-c", "user.email=ci@localhost", "commit", "-qm", "micro profile"], d, env)
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


def test_repro_trains_infers_and_evaluates(project):
    d, _ = project
    assert (d / "models" / "intrinsics" / "model.safetensors").is_file()
    pred = json.loads((d / "data" / "intrinsics_pred" / "index.json").read_text())
    assert pred["splits"]["test"]["samples"] == 2
    metrics = json.loads((d / "metrics" / "evaluate.json").read_text())
    assert metrics["intrinsics"]["model"]["albedo_psnr"] is not None
    assert "| albedo PSNR" in (d / "reports" / "intrinsics.md").read_text()
    shown = _dvc(project, "metrics", "show", "--json")  # what `dvc exp show` tabulates
    assert "albedo_psnr" in shown and "samples_per_second" in shown


def _edit_params(project, section, key, value):
    d, _ = project
    params = yaml.safe_load((d / "params.yaml").read_text())
    params[section][key] = value
    (d / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))


def test_nothing_reruns_and_a_param_marks_only_what_it_affects(project):
    assert "Data and pipelines are up to date" in _dvc(project, "status")
    _edit_params(project, "infer_intrinsics", "cfg_scale", 1.5)
    changed = set(json.loads(_dvc(project, "status", "--json")))
    assert "infer_intrinsics" in changed and not changed & {"render", "shard", "train_intrinsics"}, changed
    _edit_params(project, "infer_intrinsics", "cfg_scale", 1.0)
    _edit_params(project, "shard", "pairs_per_view", 1)
    changed = set(json.loads(_dvc(project, "status", "--json")))
    assert "shard" in changed and "render" not in changed, changed
