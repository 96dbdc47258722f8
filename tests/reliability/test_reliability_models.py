"""Issue 18: a damaged, truncated, mismatched or non-finite model file is a ModelError naming it."""

from __future__ import annotations

import json
import struct
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch

from pilight.models.folder import CHECKSUM_FILE, MODEL_FILE, load_model, save_model
from pilight.models.stack import ModelError


def _stack(width: int = 4, seed: int = 0) -> SimpleNamespace:
    torch.manual_seed(seed)
    model = torch.nn.Sequential(torch.nn.Linear(3, width), torch.nn.Linear(width, 2))
    return SimpleNamespace(model=model, describe=lambda: {"codec": "toy"})


def _saved(tmp_path: Path) -> tuple[SimpleNamespace, Path]:
    stack = _stack()
    save_model(stack, tmp_path / "m", {"p": 1})
    return stack, tmp_path / "m"


def test_round_trip_with_checksum(tmp_path: Path):
    stack, d = _saved(tmp_path)
    assert sorted(p.name for p in d.iterdir()) == sorted([MODEL_FILE, "config.json", CHECKSUM_FILE])
    other = _stack(seed=1)
    load_model(other, d)
    for a, b in zip(stack.model.state_dict().values(), other.model.state_dict().values()):
        assert torch.equal(a, b)


def test_truncated_model_is_a_message(tmp_path: Path):
    _, d = _saved(tmp_path)
    (d / CHECKSUM_FILE).unlink()  # the safetensors check on its own (a folder made by hand, trusted)
    f = d / MODEL_FILE
    f.write_bytes(f.read_bytes()[:-9])
    with (
        pytest.warns(UserWarning, match="UNVERIFIED"),
        pytest.raises(ModelError, match=rf"{f}: unreadable safetensors"),
    ):
        load_model(_stack(), d, trust_unverified=True)


def test_flipped_weight_bytes_are_caught(tmp_path: Path):
    _, d = _saved(tmp_path)
    f = d / MODEL_FILE
    raw = bytearray(f.read_bytes())
    (n,) = struct.unpack("<Q", raw[:8])
    raw[8 + n] ^= 0xFF  # one weight byte: the file still parses and loads
    f.write_bytes(bytes(raw))
    with pytest.raises(ModelError, match=rf"{f}: sha256 differs"):
        load_model(_stack(), d)


def test_mismatched_model_is_a_message(tmp_path: Path):
    _, d = _saved(tmp_path)
    with pytest.raises(ModelError, match=rf"{d / MODEL_FILE}: does not match the params' model \(.*size mismatch"):
        load_model(_stack(width=5), d)


def test_bad_checksum_file_is_a_message(tmp_path: Path):
    _, d = _saved(tmp_path)
    (d / CHECKSUM_FILE).write_text("{")
    with pytest.raises(ModelError, match=rf"{d / CHECKSUM_FILE}: unreadable"):
        load_model(_stack(), d)


def test_non_finite_weights_are_not_saved(tmp_path: Path):
    stack = _stack()
    with torch.no_grad():
        stack.model[1].bias[0] = float("inf")
    with pytest.raises(ModelError, match=r"not saved, the trained weights hold NaN/Inf \(1.bias\)"):
        save_model(stack, tmp_path / "m", {})
    assert not (tmp_path / "m").exists()


def test_same_weights_give_the_same_bytes(tmp_path: Path):
    save_model(_stack(), tmp_path / "a", {"p": 1})
    save_model(_stack(), tmp_path / "b", {"p": 1})
    for name in (MODEL_FILE, "config.json", CHECKSUM_FILE):
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes()
    assert json.loads((tmp_path / "a" / CHECKSUM_FILE).read_text())["sha256"].keys() == {MODEL_FILE, "config.json"}
