"""Issue 18: the stages exit 1 with a message naming the file, not a traceback, on damage found
while they run (a cut shard, a bad run.json, a truncated model).  Called in-process (``main(argv)``)
to stay fast; the scripts do nothing else around ``main``."""

from __future__ import annotations

import os
import tarfile
from pathlib import Path

import pytest
from accelerate.state import AcceleratorState

from fixtures.script_modules import load_stage
from fixtures.stage_scripts import params_file, tiny_shards, training_outputs
from pilight.data.shard_reader import read_index

TINY = {
    "unet": {
        "block_out_channels": [8, 8],
        "layers_per_block": 1,
        "attention_head_dim": 4,
        "cross_attention_dim": 8,
        "init": "scratch",  # whatever the default's init (a shipped base need not exist here)
        "path": None,
    },
    "codec": {"kind": "pixel", "factor": 4},
    "train": {
        "steps": 2,
        "batch_size": 2,
        "checkpoint_every": 1,
        "image_every": 100,
        "log_every": 1,
        "warmup_steps": 0,
    },
}


def _main(script: str):
    return load_stage(script).main


@pytest.fixture(autouse=True)
def _fresh_accelerate_state():
    AcceleratorState._reset_state(True)
    yield
    AcceleratorState._reset_state(True)


@pytest.fixture
def setup(tmp_path: Path):
    shards = tiny_shards(tmp_path)
    params = params_file(tmp_path, {"intrinsics": TINY, "infer_intrinsics": {"steps": 1, "splits": ["train"]}})
    return shards, params


def _train_args(tmp_path: Path, shards: Path, params: Path) -> list[str]:
    return [
        "--params",
        str(params),
        "--shards",
        str(shards),
        *map(str, training_outputs(tmp_path)),
    ]


def test_cut_shard_fails_training_by_name(setup, tmp_path, capsys):
    shards, params = setup
    path = shards / "train" / read_index(shards)["splits"]["train"]["shards"][0]
    with tarfile.open(path) as tf:
        last = tf.getmembers()[-1]
    os.chmod(path, 0o644)
    with open(path, "r+b") as fh:
        fh.truncate(last.offset)  # a valid tar, one member short
    rc = _main("train_intrinsics")(_train_args(tmp_path, shards, params))
    err = capsys.readouterr().err
    assert rc == 1 and f"{path}: damaged shard" in err and "Traceback" not in err, err
    assert not (tmp_path / "model").exists()


def test_bad_run_json_fails_training_with_a_message(setup, tmp_path, capsys):
    shards, params = setup
    (tmp_path / "ckpt").mkdir()
    (tmp_path / "ckpt" / "step_0000001").mkdir()  # a checkpoint whose run cannot be told
    (tmp_path / "ckpt" / "run.json").write_text("{truncated")
    rc = _main("train_intrinsics")(_train_args(tmp_path, shards, params))
    err = capsys.readouterr().err
    assert rc == 1 and f"{tmp_path / 'ckpt' / 'run.json'}: unreadable" in err, err


def test_truncated_model_fails_inference_with_a_message(setup, tmp_path, capsys):
    shards, params = setup
    (tmp_path / "model").mkdir()
    (tmp_path / "model" / "model.safetensors").write_bytes(b'\x10\x00\x00\x00\x00\x00\x00\x00{"a":')
    rc = _main("infer_intrinsics")(
        [
            "--params",
            str(params),
            "--shards",
            str(shards),
            "--model",
            str(tmp_path / "model"),
            "--out",
            str(tmp_path / "pred"),
            "--metrics",
            str(tmp_path / "m.json"),
        ]
    )
    err = capsys.readouterr().err
    # No manifest vouches for it (issue 36): refused before its bytes are read
    assert rc == 1 and f"{tmp_path / 'model' / 'checksums.json'}: missing" in err, err
    assert not (tmp_path / "pred").exists()


def _infer_test_split(setup, tmp_path):
    shards, _ = setup
    params = params_file(tmp_path, {"intrinsics": TINY, "infer_intrinsics": {"steps": 1, "splits": ["test"]}})
    assert _main("train_intrinsics")(_train_args(tmp_path, shards, params)) == 0
    assert (
        _main("infer_intrinsics")(
            [
                "--params",
                str(params),
                "--shards",
                str(shards),
                "--model",
                str(tmp_path / "model"),
                "--out",
                str(tmp_path / "pred"),
                "--metrics",
                str(tmp_path / "m.json"),
            ]
        )
        == 0
    )
    return shards, params


def _evaluate(tmp_path, shards, params):
    return _main("evaluate")(
        [
            "--params",
            str(params),
            "--shards",
            str(shards),
            "--pred",
            str(tmp_path / "pred"),
            "--relit",
            str(tmp_path / "no_relit"),
            "--metrics",
            str(tmp_path / "eval.json"),
            "--reports",
            str(tmp_path / "reports"),
        ]
    )


def test_evaluate_fails_on_a_missing_prediction_and_removes_stale_reports(setup, tmp_path, capsys, monkeypatch):
    """One test image without its predicted albedo: exit 1 naming it, not 'n/a' with exit 0. A run
    without relit pairs removes last run's relight report and grid instead of leaving them."""
    import pilight.eval.intrinsics as ev

    shards, params = _infer_test_split(setup, tmp_path)
    reports = tmp_path / "reports"
    reports.mkdir()
    for stale in ("relight.md", "relight_grid.png"):
        (reports / stale).write_text("last run's")
    assert _evaluate(tmp_path, shards, params) == 0
    assert not (reports / "relight.md").exists() and not (reports / "relight_grid.png").exists()
    assert (reports / "intrinsics_grid.png").is_file()
    read = ev.read_predictions

    def one_albedo_short(pred_dir, split):  # the prediction tars are checksummed; drop it after reading
        preds = read(pred_dir, split)
        del preds[sorted(preds)[0]]["albedo"]
        return preds

    monkeypatch.setattr(ev, "read_predictions", one_albedo_short)
    capsys.readouterr()
    assert _evaluate(tmp_path, shards, params) == 1
    err = capsys.readouterr().err
    assert "no predicted albedo" in err and "rerun infer_intrinsics" in err, err
