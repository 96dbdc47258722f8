"""Issue 18: the training loop never checkpoints NaN, and says when it passes over a damaged checkpoint."""

from __future__ import annotations

import struct
import warnings
from pathlib import Path

import pytest
import torch
from accelerate.state import AcceleratorState

from pilight.params import TrainParams
from pilight.train import checkpoint as ckpt
from pilight.train.loop import train


@pytest.fixture(autouse=True)
def _fresh_accelerate_state():
    AcceleratorState._reset_state(True)
    yield
    AcceleratorState._reset_state(True)


class Toy:
    samples_per_batch = 2

    def __init__(self):
        torch.manual_seed(0)
        self.net = torch.nn.Linear(4, 4)

    def trainable(self):
        return self.net

    def batches(self, epoch):
        g = torch.Generator().manual_seed(epoch)
        for _ in range(3):
            yield torch.randn(2, 4, generator=g)

    def loss(self, batch, generator, model):
        return (model(batch) - batch.flip(-1)).square().mean(), {}

    def images(self, batch):
        return {}


def _cfg(**kw):
    return TrainParams(
        **{
            **dict(
                warmup_steps=0,
                steps=6,
                lr=1e-2,
                checkpoint_every=2,
                keep_checkpoints=3,
                log_every=3,
                image_every=100,
                max_grad_norm=None,
            ),
            **kw,
        }
    )


def _all_finite(folder: Path) -> bool:
    from safetensors.torch import load_file

    return all(
        torch.isfinite(t).all()
        for p in ckpt.list_checkpoints(folder)
        for t in load_file(str(p / ckpt.MODEL_FILE)).values()
    )


def test_infinite_lr_writes_no_nan_checkpoint(tmp_path: Path):
    # lr = inf, checkpoint_every (1) < log_every (5): step 1's loss is finite, its update is not.
    # Before: NaN checkpoints were written at steps 1..4, before the loss check at step 5 fired.
    with pytest.raises(FloatingPointError, match="step 1"):
        train(
            Toy(),
            _cfg(checkpoint_every=1, log_every=5).model_copy(update={"lr": float("inf")}),
            tmp_path / "c",
            None,
            progress=False,
        )
    assert ckpt.list_checkpoints(tmp_path / "c") == []


def test_damaged_newest_checkpoint_is_warned_about_and_the_previous_one_used(tmp_path: Path):
    ref = Toy()
    train(ref, _cfg(), tmp_path / "ref", None, progress=False)
    train(Toy(), _cfg(steps=4), tmp_path / "c", None, progress=False)  # checkpoints at steps 2 and 4
    newest = ckpt.checkpoint_path(tmp_path / "c", 4) / ckpt.MODEL_FILE
    raw = bytearray(newest.read_bytes())
    (n,) = struct.unpack("<Q", raw[:8])
    raw[8 + n : 8 + n + 32] = bytes(b ^ 0xFF for b in raw[8 + n : 8 + n + 32])
    newest.write_bytes(bytes(raw))
    resumed = Toy()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        stats = train(resumed, _cfg(), tmp_path / "c", None, progress=False)
    text = "\n".join(str(w.message) for w in caught)
    assert "step_0000004" in text and "sha256 differs" in text
    assert "resuming from the previous checkpoint" in text and "step_0000002" in text
    assert stats["resumed_from"] == 2
    # Resumed from the good step-2 checkpoint, the run ends exactly as an uninterrupted one.
    for a, b in zip(ref.net.state_dict().values(), resumed.net.state_dict().values()):
        assert torch.equal(a, b)
    assert _all_finite(tmp_path / "c")
