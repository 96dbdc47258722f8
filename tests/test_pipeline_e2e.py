"""End to end: `dvc repro` of a micro profile in a fresh copy of the project, as a user runs it."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest
import yaml

from fixtures.micro_project import make_micro_project

pytestmark = pytest.mark.slow


def _run(args, cwd, env, *, both: bool = False):
    r = subprocess.run(args, cwd=cwd, env=env, capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, f"{args}\n{r.stdout}\n{r.stderr}"
    return r.stdout + r.stderr if both else r.stdout


REPRO_OUTPUT: dict[str, str] = {}  # what the fixture's `dvc repro` printed (stdout + stderr)


@pytest.fixture(scope="module")
def project(tmp_path_factory):
    """A fresh git + DVC project holding this checkout's code and a micro params.yaml."""
    d = tmp_path_factory.mktemp("project")
    env = make_micro_project(d)
    REPRO_OUTPUT["repro"] = _run([sys.executable, "-m", "dvc", "repro"], d, env, both=True)
    return d, env


def test_blender_output_goes_to_the_log_not_the_terminal(project):
    """Blender prints a 'Saved:' line per rendered file; the user sees progress bars and summaries."""
    d, _ = project
    out = REPRO_OUTPUT["repro"]
    assert "Saved:" not in out
    assert "render: " in out and "logs/render.log" in out
    assert "Saved:" in (d / "logs" / "render.log").read_text()
    assert "Saved:" in (d / "logs" / "render_trade.log").read_text()


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
    assert (d / "reports" / "intrinsics_grid.png").is_file() and (d / "reports" / "relight.md").is_file()


def test_repro_measures_the_speed_accuracy_trade(project):
    d, _ = project
    trade = json.loads((d / "metrics" / "trade.json").read_text())
    # steps x spacing (4) + single-step + cfg 2.0 + ensemble 2; cfg 1.0 / ensemble 1 coincide with single-step
    assert [p["label"] for p in trade["intrinsics"]["points"]][-3:] == [
        "1-step, cfg 1, ens 1",
        "1-step, cfg 2, ens 1",
        "1-step, cfg 1, ens 2",
    ]
    for stage in ("intrinsics", "relight"):
        pts = trade[stage]["points"]
        assert all(p["seconds_per_image"] > 0 for p in pts)
        assert any(v for p in pts for k, v in p.items() if k.startswith("pareto_"))
    render = json.loads((d / "metrics" / "render_trade.json").read_text())["points"]
    assert {p["scene"] for p in render} <= {"object", "room"} and all(p["seconds"] > 0 for p in render)
    for png in ("trade_intrinsics.png", "trade_relight.png", "relit_lights.png", "render_trade.png"):
        assert (d / "reports" / png).stat().st_size > 1000, png
    plots = json.loads(_dvc(project, "plots", "show", "--json", "--split"))
    assert not plots.get("errors") and "stage-1 normal error vs seconds per image" in plots["data"], plots.get("errors")


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
    _edit_params(project, "shard", "pairs_per_view", None)
    assert "Data and pipelines are up to date" in _dvc(project, "status")


def test_a_stage_2_param_reruns_only_stage_2(project):
    """relight.lambda_image: render, shard and stage 1 stay cached; the persisted stage-2 checkpoints of
    the previous run are dropped, not resumed (else the new experiment would train nothing). Not
    lambda_ps: in physics-first mode L_PS is 0 by construction, so the retrained model can be
    byte-identical and DVC rightly skips what follows."""
    _edit_params(project, "relight", "lambda_image", 0.5)
    assert set(json.loads(_dvc(project, "status", "--json"))) == {"train_relight"}
    out = _dvc(project, "repro")
    for stage in ("render", "shard", "train_intrinsics", "infer_intrinsics", "render_trade"):
        assert f"Stage '{stage}' didn't change, skipping" in out, out
    for stage in ("train_relight", "relight", "evaluate", "trade"):
        assert f"Running stage '{stage}'" in out, out
    assert "checkpoint(s) of another run dropped (changed: relight)" in out, out
    assert "Data and pipelines are up to date" in _dvc(project, "status")
