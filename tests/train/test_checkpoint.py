"""pilight.train.checkpoint: safetensors-only, atomic, retention, damaged folders ignored."""

from __future__ import annotations

import json
import struct
from pathlib import Path

import pytest
import torch
from safetensors import safe_open

from pilight.train import checkpoint as ckpt
from pilight.train import run_identity as run_id


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
    return ckpt.save_checkpoint(
        d,
        step,
        model=model,
        optimizer=opt,
        scheduler=sched,
        rng=rng,
        progress={"epoch": 2, "batches_in_epoch": 3},
        keep=keep,
    )


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
    assert sorted(p.name for p in path.iterdir()) == sorted(ckpt.FILES + (ckpt.CHECKSUM_FILE,))
    for f in path.iterdir():
        if f.name == ckpt.CHECKSUM_FILE:
            continue
        raw = f.read_bytes()
        (n,) = struct.unpack("<Q", raw[:8])  # safetensors: u64 header length, then a JSON header
        json.loads(raw[8 : 8 + n])
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


# --- issue 18: checksums, named damage, explicit fallback, nothing non-finite written ---------
def _flip_weight_bytes(f: Path, n: int = 64) -> None:
    raw = bytearray(f.read_bytes())
    (header,) = struct.unpack("<Q", raw[:8])
    for i in range(8 + header, min(len(raw), 8 + header + n)):  # tensor data only: the header still parses
        raw[i] ^= 0xFF
    f.write_bytes(bytes(raw))


def test_checksums_cover_every_file(tmp_path: Path):
    model, opt, sched = _setup()
    _train_a_bit(model, opt, sched, 1)
    path = _save(tmp_path, 1, model, opt, sched)
    sums = json.loads((path / ckpt.CHECKSUM_FILE).read_text())["sha256"]
    assert sorted(sums) == sorted(ckpt.FILES)
    assert all(sums[n] == ckpt.sha256_file(path / n) for n in sums)
    assert ckpt.damage(path) is None


def test_flipped_weight_bytes_are_caught_and_the_fallback_is_named(tmp_path: Path):
    model, opt, sched = _setup()
    _train_a_bit(model, opt, sched, 1)
    good = _save(tmp_path, 5, model, opt, sched)
    bad = _save(tmp_path, 6, model, opt, sched)
    _flip_weight_bytes(bad / ckpt.MODEL_FILE)
    assert ckpt.is_complete(bad)  # the header check alone passed it: it used to be resumed silently
    path, notes = ckpt.find_resume(tmp_path)
    assert path == good and ckpt.latest_checkpoint(tmp_path) == good
    assert any(str(bad) in n and "model.safetensors: sha256 differs" in n for n in notes)
    assert any(str(good) in n and str(bad) in n for n in notes)  # the fallback names both folders


def test_truncated_only_checkpoint_says_training_restarts(tmp_path: Path):
    model, opt, sched = _setup()
    _train_a_bit(model, opt, sched, 1)
    bad = _save(tmp_path, 3, model, opt, sched)
    f = bad / ckpt.OPTIMIZER_FILE
    f.write_bytes(f.read_bytes()[:-17])
    path, notes = ckpt.find_resume(tmp_path)
    assert path is None
    assert any(str(bad) in n and "optimizer.safetensors" in n for n in notes)
    assert any("starts from step 0" in n for n in notes)


def test_checkpoint_without_checksums_is_not_resumed(tmp_path: Path):
    # Issue 36: a missing manifest is damage, not a pass (it let flipped weights resume unseen).
    model, opt, sched = _setup()
    _train_a_bit(model, opt, sched, 1)
    path = _save(tmp_path, 2, model, opt, sched)
    (path / ckpt.CHECKSUM_FILE).unlink()
    found, notes = ckpt.find_resume(tmp_path)
    assert found is None and any("checksums.json missing" in n for n in notes), notes


def test_non_finite_weights_are_never_checkpointed(tmp_path: Path):
    model, opt, sched = _setup()
    _train_a_bit(model, opt, sched, 1)
    good = _save(tmp_path, 1, model, opt, sched)
    with torch.no_grad():
        model[0].weight[0, 0] = float("nan")
    with pytest.raises(ckpt.NonFiniteError, match=r"step 2: weights hold NaN/Inf \(0.weight\)"):
        _save(tmp_path, 2, model, opt, sched)
    assert sorted(p.name for p in tmp_path.iterdir()) == [good.name]


@pytest.mark.parametrize("content", ["{not json", "[1, 2]"])
def test_bad_run_json_is_a_message(tmp_path: Path, content: str):
    model, opt, sched = _setup()
    _train_a_bit(model, opt, sched, 1)
    _save(tmp_path, 1, model, opt, sched)
    (tmp_path / run_id.RUN_FILE).write_text(content)
    with pytest.raises(ckpt.CheckpointError, match=rf"{tmp_path / run_id.RUN_FILE}: .*delete {tmp_path}"):
        run_id.claim_run(tmp_path, {"seed": 1}, 10)
    assert ckpt.latest_checkpoint(tmp_path) is not None  # nothing was deleted on a guess


def test_checkpoint_of_another_architecture_is_a_message(tmp_path: Path):
    model, opt, sched = _setup()
    _train_a_bit(model, opt, sched, 1)
    path = _save(tmp_path, 1, model, opt, sched)
    other = torch.nn.Sequential(torch.nn.Linear(4, 7), torch.nn.ReLU(), torch.nn.Linear(7, 2))
    opt2 = torch.optim.AdamW(other.parameters())
    sched2 = torch.optim.lr_scheduler.LambdaLR(opt2, lambda s: 1.0)
    with pytest.raises(ckpt.CheckpointError, match=rf"{path}: cannot resume"):
        ckpt.load_checkpoint(path, model=other, optimizer=opt2, scheduler=sched2)
