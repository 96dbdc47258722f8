"""Issue 18: a missing, cut or damaged prediction tar is a DataError naming it."""

from __future__ import annotations

import json
import os
import stat
import tarfile
from pathlib import Path

import numpy as np
import pytest

from pilight.data.predictions import read_predictions, write_predictions
from pilight.data.schema import DataError

KEYS = [f"scene_v00_l{i:02d}" for i in range(4)]


def _items(nan_key: str | None = None):
    rng = np.random.default_rng(0)
    for key in KEYS:
        albedo = rng.random((4, 4, 3), dtype=np.float32)
        if key == nan_key:
            albedo[1, 1, 0] = np.nan
        yield key, {"albedo": albedo, "roughness": rng.random((4, 4, 1), dtype=np.float32)}, "{}"


@pytest.fixture
def pred(tmp_path: Path) -> Path:
    write_predictions(tmp_path / "pred", {"test": _items()}, {"domains": ["albedo", "roughness"]})
    return tmp_path / "pred"


def _tar(pred: Path) -> Path:
    return pred / "test" / json.loads((pred / "index.json").read_text())["splits"]["test"]["shards"][0]


def _cut_after_two_samples(path: Path) -> None:
    with tarfile.open(path) as tf:
        third = next(m for m in tf.getmembers() if m.name.startswith(KEYS[2] + "."))
    os.chmod(path, 0o644)
    with open(path, "r+b") as fh:
        fh.truncate(third.offset)


def test_round_trip(pred):
    got = read_predictions(pred, "test")
    assert sorted(got) == KEYS and got[KEYS[0]]["albedo"].shape == (4, 4, 3)
    entry = json.loads((pred / "index.json").read_text())["splits"]["test"]
    assert entry["shard_checks"][entry["shards"][0]]["samples"] == 4


def test_missing_tar_is_named(pred):
    path = _tar(pred)
    path.unlink()
    # Before: a raw FileNotFoundError traceback from webdataset.
    with pytest.raises(DataError, match=rf"{path}: prediction tar missing"):
        read_predictions(pred, "test")


def test_cut_tar_is_named(pred):
    path = _tar(pred)
    _cut_after_two_samples(path)
    # Before: 2 of the 4 predictions came back, silently.
    with pytest.raises(DataError, match=rf"{path}: damaged prediction tar: sha256 differs.*2 of its 4 samples"):
        read_predictions(pred, "test")


def test_cut_tar_without_recorded_checks_fails_on_the_count(pred):
    index = json.loads((pred / "index.json").read_text())
    index["splits"]["test"].pop("shard_checks", None)
    (pred / "index.json").write_text(json.dumps(index))
    _cut_after_two_samples(_tar(pred))
    with pytest.raises(DataError, match=r"2 predictions read but .*index.json says 4"):
        read_predictions(pred, "test")


def test_non_finite_prediction_names_the_key(tmp_path):
    with pytest.raises(DataError, match=rf"prediction test/{KEYS[2]} 'albedo': refusing to write non-finite"):
        write_predictions(tmp_path / "pred", {"test": _items(nan_key=KEYS[2])}, {})
    assert list(tmp_path.iterdir()) == []


def test_prediction_folder_follows_the_umask(tmp_path):
    old = os.umask(0o027)
    try:
        write_predictions(tmp_path / "pred", {"test": _items()}, {})
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "pred").stat().st_mode) == 0o750
