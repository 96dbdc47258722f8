"""pilight.train.checkpoint: safetensors-only, atomic, retention, damaged folders ignored."""

from __future__ import annotations

import json
import struct
from pathlib import Path

import pytest
import torch
from safetensors import safe_open

from pilight.train import checkpoint as ckpt


def _setup(seed: int = 0):
    torch.manual_seed(seed)
    model = torch.nn.Sequential(torch.nn.Linear(4, 6), torch.nn.ReLU(), torch.nn.Linear(6, 2))
    opt = torch.optim.AdamW(model.parameters(), lr=1e-3, weight_decay=0.01)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: min(1.0, (s + 1) / 5))
    return model, opt, sched


def _train_a_bit(model, opt, sched, n=3):
    for _ in range(n):
        model(torch.randn(3, 4)).square().mean().backward()
        opt.step()
        sched.step()
        opt.zero_grad()


def _save(d: Path, step: int, model, opt, sched, keep: int = 3) -> Path:
    gen = torch.Generator().manual_seed(5)
    rng = {"rank0.generator": gen.get_state(), "rank0.torch_cpu": torch.get_rng_state()}
    return ckpt.save_checkpoint(d, step, model=model, optimizer=opt, scheduler=sched, rng=rng,
                                progress={"epoch": 2, "batches_in_epoch": 3}, keep=keep)


def test_roundtrip_restores_everything(tmp_path: Path):
    model, opt, sched = _setup(0)
    _train_a_bit(model, opt, sched)
    path = _save(tmp_path, 3, model, opt, sched)
    assert path == tmp_path / "step_0000003" and ckpt.latest_checkpoint(tmp_path) == path

    model2, opt2, sched2 = _setup(1)
    progress, rng = ckpt.load_checkpoint(path, model=model2, optimizer=opt2, scheduler=sched2)
    assert progress == {"epoch": 2, "batches_in_epoch": 3, "step": 3}
    for a, b in zip(model.state_dict().values(), model2.state_dict().values()):
        assert torch.equal(a, b)
    s1, s2 = opt.state_dict(), opt2.state_dict()
    assert s1["param_groups"] == [{**g, "betas": tuple(g["betas"])} for g in s2["param_groups"]]
    for i in s1["state"]:
        for k in s1["state"][i]:
            assert torch.equal(s1["state"][i][k], s2["state"][i][k]), (i, k)
    assert sched2.last_epoch == sched.last_epoch and sched2.get_last_lr() == sched.get_last_lr()
    assert rng["rank0.generator"].dtype == torch.uint8

    # Continuing both gives identical weights: the optimizer state is really complete.
    torch.manual_seed(9)
    _train_a_bit(model, opt, sched, 2)
    torch.manual_seed(9)
    _train_a_bit(model2, opt2, sched2, 2)
    for a, b in zip(model.state_dict().values(), model2.state_dict().values()):
        assert torch.equal(a, b)


def test_files_are_plain_safetensors(tmp_path: Path):
    model, opt, sched = _setup()
    _train_a_bit(model, opt, sched)
    path = _save(tmp_path, 1, model, opt, sched)
    assert sorted(p.name for p in path.iterdir()) == sorted(ckpt.FILES)
    for f in path.iterdir():
        raw = f.read_bytes()
        (n,) = struct.unpack("<Q", raw[:8])  # safetensors: u64 header length, then a JSON header
        json.loads(raw[8:8 + n])
        assert not raw.startswith(b"\x80") and not raw.startswith(b"PK")  # not a pickle, not a torch zip
        with safe_open(str(f), framework="pt") as fh:
            list(fh.keys())
    with safe_open(str(path / ckpt.OPTIMIZER_FILE), framework="pt") as fh:
        assert {"state.0.exp_avg", "state.0.exp_avg_sq", "state.0.step"} <= set(fh.keys())
        assert json.loads(fh.metadata()["param_groups"])[0]["lr"] == pytest.approx(opt.param_groups[0]["lr"])


def test_retention_and_resave(tmp_path: Path):
    model, opt, sched = _setup()
    _train_a_bit(model, opt, sched, 1)
    for step in (10, 20, 30, 40):
        _save(tmp_path, step, model, opt, sched, keep=2)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["step_0000030", "step_0000040"]
    _save(tmp_path, 40, model, opt, sched, keep=2)  # same step again replaces, never nests
    assert sorted(p.name for p in tmp_path.iterdir()) == ["step_0000030", "step_0000040"]


@pytest.mark.parametrize("damage", ["missing", "truncated", "tmp"])
def test_damaged_or_partial_checkpoint_is_ignored(tmp_path: Path, damage: str):
    model, opt, sched = _setup()
    _train_a_bit(model, opt, sched, 1)
    good = _save(tmp_path, 5, model, opt, sched)
    bad = _save(tmp_path, 6, model, opt, sched)
    if damage == "missing":
        (bad / ckpt.OPTIMIZER_FILE).unlink()
    elif damage == "truncated":
        f = bad / ckpt.MODEL_FILE
        f.write_bytes(f.read_bytes()[:-17])
    else:  # a write interrupted before the rename
        bad.rename(tmp_path / f"{ckpt.TMP_PREFIX}step_0000006-1234")
    assert ckpt.latest_checkpoint(tmp_path) == good
    ckpt.remove_stale_tmp(tmp_path)
    assert not any(p.name.startswith(ckpt.TMP_PREFIX) for p in tmp_path.iterdir())


def test_no_checkpoint(tmp_path: Path):
    assert ckpt.latest_checkpoint(tmp_path / "absent") is None
    (tmp_path / "step_0000001").mkdir()
    (tmp_path / "notes.txt").write_text("x")
    assert ckpt.latest_checkpoint(tmp_path) is None
