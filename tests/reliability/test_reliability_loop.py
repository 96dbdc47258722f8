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


# --- issue 36: divergence and NaN weights stop the run with the training's own message ---------------
def test_a_diverging_stage_stops_and_saves_no_model(tmp_path, capsys):
    """lr 1.0 (the allowed maximum) on the stage-1 script: the loss leaves its start by >100x within a few
    steps. Before: exit 0 and the diverged model saved to models/."""
    from fixtures.script_modules import load_stage
    from fixtures.stage_scripts import params_file, tiny_shards, training_outputs

    shards = tiny_shards(tmp_path)
    train = {"steps": 30, "batch_size": 2, "checkpoint_every": 100, "image_every": 100, "log_every": 1}
    train |= {"warmup_steps": 0, "lr": 1.0, "max_grad_norm": None, "lr_schedule": "constant", "grad_accum": 1}
    train |= {"cond_dropout": 0.1, "terminal_fraction": 0.5, "ema_decay": 0.0}
    unet = {"block_out_channels": [8, 8], "layers_per_block": 1, "attention_head_dim": 4, "cross_attention_dim": 8}
    unet |= {"init": "scratch", "path": None}
    # pinned whatever params.yaml's default is: the diffusion objective, one UNet item per domain
    stage = {"unet": unet, "codec": {"kind": "pixel", "factor": 4}, "train": train, "objective": "diffusion"}
    stage |= {"layout": "domains", "augment": {"flip": False, "crop": None}, "schedule": {"terminal_input": "noise"}}
    params = params_file(tmp_path, {"intrinsics": stage})
    rc = load_stage("train_intrinsics").main(
        ["--params", str(params), "--shards", str(shards), *map(str, training_outputs(tmp_path))]
    )
    err = capsys.readouterr().err
    assert rc == 1 and "train_intrinsics: training diverged: the loss at step" in err, err
    assert "over 100x its start" in err and "Lower train.lr (now 1)" in err
    assert not (tmp_path / "model").exists()
    assert ckpt.list_checkpoints(tmp_path / "ckpt") == []


class Diverging(Toy):
    """Its loss is 1000x larger after ``after`` calls: what a diverging run logs."""

    def __init__(self, after: int):
        super().__init__()
        self.calls, self.after = 0, after

    def loss(self, batch, generator, model):
        self.calls += 1
        base = (model(batch) - batch.flip(-1)).square().mean()
        return base * (1.0 if self.calls <= self.after else 1000.0), {}


def test_the_start_is_kept_across_a_resume(tmp_path: Path):
    # The run is checkpointed at step 4 (log_every 2: start = the loss of steps 1-2), then resumed: the
    # resumed run keeps that start, and stops at its first log above 100x it.
    cfg = _cfg(steps=4, log_every=2, checkpoint_every=4)
    train(Diverging(after=10**9), cfg, tmp_path / "c", None, progress=False)
    from safetensors import safe_open

    with safe_open(str(ckpt.checkpoint_path(tmp_path / "c", 4) / ckpt.STATE_FILE), framework="pt") as fh:
        import json

        start = json.loads(fh.metadata()["progress"])["start_loss"]
    assert start is not None and start > 0
    with pytest.raises(FloatingPointError, match=rf"step 6, .* over 100x its start \({start:.4g}"):
        train(Diverging(after=0), cfg.model_copy(update={"steps": 8}), tmp_path / "c", None, progress=False)
    assert [ckpt.step_of(p) for p in ckpt.list_checkpoints(tmp_path / "c")] == [4]


class Previewing(Toy):
    """A preview that fails as the sampler did on NaN weights, blaming its input."""

    def images(self, batch):
        if not bool(torch.isfinite(self.net.weight).all()):
            raise ValueError("the condition is broken upstream (image, codec or conditioning encoder)")
        return {}


def test_nan_weights_stop_training_before_a_preview_samples_them(tmp_path: Path):
    # An unbounded weight_decay (now refused by params) multiplied the weights by 1 - lr x wd < -1 each step:
    # NaN after a few steps, met first by the preview. The loop's own check now speaks first.
    cfg = _cfg(steps=60, log_every=100, checkpoint_every=100, image_every=1).model_copy(update={"weight_decay": 1e6})
    with pytest.raises(ckpt.NonFiniteError, match=r"(non-finite loss|weights hold NaN/Inf).* step \d+"):
        train(Previewing(), cfg, tmp_path / "c", tmp_path / "live", progress=False)
