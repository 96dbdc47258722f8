"""A fresh git + DVC project holding this checkout's code and a micro params.yaml: what the e2e test
and benchmarks/crash_test.py run `dvc repro` in (plumbing, not accuracy)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]

MICRO = {
    "resolution": 32,
    "ball_resolution": 32,
    "ball_samples": 8,
    "views_per_scene": 1,
    "lights_per_view": 2,
    "scenes": {"train": 2, "val": 1, "test": 1},
    "cycles": {"samples": 8, "adaptive_min_samples": 4},
}
MICRO_UNET = {"block_out_channels": [32, 32], "cross_attention_dim": 32}
MICRO_TRAIN = {"steps": 3, "batch_size": 2, "checkpoint_every": 2, "image_every": 2, "log_every": 1, "warmup_steps": 0}
MICRO_TRADE = {
    "images": 2,
    "steps": [1, 2],
    "spacings": ["leading", "trailing"],
    "intrinsics_cfg": [1.0, 2.0],
    "relight_cfg": [1.5],
    "ensemble": [1, 2],
    "render_spp": [2, 4],
    "render_reference_spp": 8,
}


def save_micro_base(folder: Path, params: dict) -> Path:
    """A stand-in for the shipped base (weights/pilight-base) that the micro params' `unet.init: base` loads:
    their own tiny networks, untrained, saved as the export stage saves the real one (float16)."""
    import torch

    from pilight.models.folder import save_model
    from pilight.params import IntrinsicsParams, RelightParams
    from pilight.train.intrinsics import IntrinsicsTask
    from pilight.train.relight import RelightTask

    torch.manual_seed(0)
    for stage, cls, task in (("intrinsics", IntrinsicsParams, IntrinsicsTask), ("relight", RelightParams, RelightTask)):
        raw = {**params[stage], "unet": {**params[stage]["unet"], "init": "scratch"}}
        if stage == "relight":
            raw["conditions"] = "gt"  # building the network needs no predictions
        p = cls.model_validate(raw)
        save_model(task(p, folder, seed=0).stack, folder / stage, p.model_dump(mode="json"), dtype=torch.float16)
    return folder


def make_micro_project(d: Path, train: dict | None = None) -> dict[str, str]:
    """Populate `d` (code, dvc.yaml, micro params; `train` overrides both stages' train section),
    git init + dvc init + one commit; returns the environment to run dvc in."""
    for name in ("pilight", "stages"):
        shutil.copytree(ROOT / name, d / name, ignore=shutil.ignore_patterns("__pycache__"))
    for name in ("dvc.yaml", ".gitignore"):
        shutil.copy(ROOT / name, d / name)
    params = yaml.safe_load((ROOT / "params.yaml").read_text())
    params["render"].update(MICRO)
    for stage in ("intrinsics", "relight"):  # a tiny UNet and a few steps
        params[stage]["unet"].update(MICRO_UNET)
        params[stage]["train"].update({**MICRO_TRAIN, **(train or {})})
    for stage in ("infer_intrinsics", "relight_infer"):
        params[stage]["steps"] = 2
    params["evaluate"]["trade"].update(MICRO_TRADE)
    params["evaluate"].update(grid_images=2, relight_lights=3)
    (d / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    save_micro_base(d / "weights" / "pilight-base", params)
    # PYTHONPATH: the stage scripts import the installed package; here that is the project's own copy.
    env = {
        **os.environ,
        "DVC_NO_ANALYTICS": "1",
        "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}",
        "PYTHONPATH": os.pathsep.join([str(d), *filter(None, [os.environ.get("PYTHONPATH")])]),
    }
    # A user's project has commits (dvclive and `dvc exp` need a HEAD).
    for cmd in (
        ["git", "init", "-q"],
        [sys.executable, "-m", "dvc", "init", "-q"],
        ["git", "add", "-A"],
        ["git", "-c", "user.name=ci", "-c", "user.email=ci@localhost", "commit", "-qm", "micro profile"],
    ):
        r = subprocess.run(cmd, cwd=d, env=env, capture_output=True, text=True)
        assert r.returncode == 0, f"{cmd}\n{r.stdout}\n{r.stderr}"
    return env
