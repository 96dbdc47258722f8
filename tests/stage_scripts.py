"""Helpers for tests that run the stage scripts as a user does: tiny shards, a params file, a subprocess."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import yaml

from pilight.data.shard_params import ShardParams
from pilight.data.shards import write_shards
from tests.data.test_shards import write_fake_renders

REPO = Path(__file__).resolve().parents[1]

# The stage-script tests' network: a tiny UNet from scratch (whatever the default's unet.init) on the
# lossless pixel codec, shared by both stages' tests so they build the same small model.
TINY_NETWORK = {
    "unet": {
        "init": "scratch",
        "block_out_channels": [32, 32],
        "layers_per_block": 1,
        "attention_head_dim": 8,
        "cross_attention_dim": 32,
    },
    "codec": {"kind": "pixel", "factor": 4},
}


def tiny_shards(root: Path) -> Path:
    """Shards of fake 16^2 renders (8^2 balls) under root/shards."""
    renders = write_fake_renders(root / "renders", size=16, ball=8)
    write_shards(renders, root / "shards", ShardParams(), seed=3)
    return root / "shards"


def params_file(tmp_path: Path, sections: dict[str, dict]) -> Path:
    """The repo's params.yaml with ``sections`` merged in (dict values one level deep), as tmp_path/params.yaml."""
    p = yaml.safe_load((REPO / "params.yaml").read_text())
    for section, changes in sections.items():
        for k, v in changes.items():
            p[section][k] = {**p[section].get(k, {}), **v} if isinstance(v, dict) else v
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump(p))
    return path


def training_outputs(root: Path) -> list:
    """The output flags of a training stage script (model, checkpoints, dvclive), all under root."""
    return ["--out", root / "model", "--checkpoints", root / "ckpt", "--live", root / "live"]


def stage_env(root: Path = REPO) -> dict[str, str]:
    """The environment a stage script runs in: `root`'s pilight first. The scripts import the installed
    package; an editable install of another checkout must not stand in for the code under test."""
    return {**os.environ, "PYTHONPATH": os.pathsep.join([str(root), *filter(None, [os.environ.get("PYTHONPATH")])])}


def run_stage(script: str, *args) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, str(REPO / "stages" / script), *map(str, args)],
        capture_output=True,
        text=True,
        cwd=REPO,
        timeout=600,
        env=stage_env(),
    )
