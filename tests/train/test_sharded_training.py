"""Issue 20, item 2: the loop under FSDP (gradients and AdamW state sharded), 2 CPU processes (gloo),
started the way the README says, through ``accelerate launch --config_file profiles/accelerate_fsdp.yaml``."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from accelerate.state import AcceleratorState
from safetensors.torch import load_file
from test_train_loop import ShardedToyTask, assert_bit_equal, ddp_cfg

from pilight.train import checkpoint as ckpt
from pilight.train.loop import train

ROOT = Path(__file__).parents[2]


@pytest.fixture(autouse=True)
def _fresh_accelerate_state():
    AcceleratorState._reset_state(True)
    yield
    AcceleratorState._reset_state(True)


# Each rank records what task.loss was handed: the proof that the weights it trained were shards.
_SCRIPT = """
import os, sys, torch
sys.path.insert(0, {here!r})
from test_train_loop import ShardedToyTask, ddp_cfg
from pilight.train.loop import train
from safetensors.torch import save_file
from torch.distributed.fsdp import FSDPModule
from torch.distributed.tensor import DTensor

out, rank = sys.argv[1], int(os.environ["RANK"])


class Recording(ShardedToyTask):
    def loss(self, batch, generator, model):
        assert isinstance(model, FSDPModule), f"not sharded: task.loss got a {{type(model).__name__}}"
        w = model[0].weight
        assert isinstance(w, DTensor) and w.to_local().shape == (8, 8), (type(w), w.shape)  # 16 rows, half each
        assert self.net[0].weight.numel() == 0, "the task's own module is emptied while its sharded copy trains"
        return super().loss(batch, generator, model)

    def images(self, batch):  # the main process, every image_every steps: the whole weights are back
        assert rank == 0 and self.net[0].weight.shape == (16, 8)
        self.previews = getattr(self, "previews", 0) + 1
        return {{}}


# (run, steps, EMA decay, previews the main process draws: every 4 steps and at the last, in the EMA runs)
for name, steps, ema, previews in (("fsdp", 12, 0.0, 0), ("resumed", 7, 0.0, 0), ("resumed", 12, 0.0, 0),
                                   ("ema", 12, 0.9, 3), ("ema_resumed", 7, 0.9, 2), ("ema_resumed", 12, 0.9, 2)):
    task = Recording(rank=rank, world=2, model_seed=123 + rank)  # another init per rank: rank 0's is broadcast
    live = f"{{out}}/live-{{name}}" if ema else None
    train(task, ddp_cfg(steps).model_copy(update=dict(ema_decay=ema, image_every=4)), f"{{out}}/{{name}}", live,
          progress=False)
    assert getattr(task, "previews", 0) == (previews if rank == 0 else 0), (name, steps, task.__dict__.get("previews"))
    assert not isinstance(task.net[0].weight, DTensor)  # the module leaves whole, holding the trained weights
    save_file({{k: v.contiguous() for k, v in task.net.state_dict().items()}}, f"{{out}}/{{name}}-{{rank}}.st")
"""


def _launch(tmp_path: Path) -> subprocess.CompletedProcess:
    script = tmp_path / "sharded.py"
    script.write_text(_SCRIPT.format(here=str(Path(__file__).parent)))
    env = {
        **os.environ,
        "OMP_NUM_THREADS": "1",
        "PYTHONPATH": os.pathsep.join([str(ROOT), *filter(None, [os.environ.get("PYTHONPATH")])]),
    }
    # The profile as users run it (its bf16 yields to the loop's mixed_precision, fp32 here); the toy
    # has no UNet blocks for the profile's wrap policy, so each Linear is its own FSDP unit.
    cmd = [
        sys.executable,
        "-m",
        "accelerate.commands.launch",
        "--config_file",
        str(ROOT / "profiles/accelerate_fsdp.yaml"),
        "--num_processes",
        "2",
        "--main_process_port",
        "0",
        "--fsdp_transformer_layer_cls_to_wrap",
        "Linear",
        str(script),
        str(tmp_path),
    ]
    return subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300, cwd=tmp_path)


def test_fsdp_on_two_processes_trains_what_one_process_trains_and_resumes_exactly(tmp_path: Path):
    """FSDP2 on 2 gloo processes: the weights equal, to float tolerance, one process trained on the
    two ranks' concatenated batches (gradients averaged, not summed: the toy's loss sits near AdamW's
    eps); a run stopped at step 7 and resumed from its gathered safetensors checkpoint ends as the
    uninterrupted sharded run, with and without an EMA of the weights."""
    proc = _launch(tmp_path)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-4000:]
    w = {
        (n, r): load_file(str(tmp_path / f"{n}-{r}.st"))
        for n in ("fsdp", "resumed", "ema", "ema_resumed")
        for r in (0, 1)
    }
    for name in ("fsdp", "ema"):
        assert_bit_equal(w[name, 0], w[name, 1])  # every rank's module leaves with the same whole weights
    # Resume: the same process count and the same order of reductions, so bit for bit.
    assert_bit_equal(w["fsdp", 0], w["resumed", 0])
    assert_bit_equal(w["ema", 0], w["ema_resumed", 0])
    assert_bit_equal(w["ema_resumed", 0], w["ema_resumed", 1])

    # The checkpoint is the unsharded format: full tensors, optimizer state by parameter index.
    last = ckpt.latest_checkpoint(tmp_path / "resumed")
    assert last.name == "step_0000012" and ckpt.damage(last) is None
    assert {k: v.shape for k, v in load_file(str(last / ckpt.MODEL_FILE)).items()} == {
        k: v.shape for k, v in w["fsdp", 0].items()
    }
    opt = load_file(str(last / ckpt.OPTIMIZER_FILE))
    assert opt["state.0.exp_avg"].shape == (16, 8) and "state.3.exp_avg_sq" in opt
    assert_bit_equal(load_file(str(last / ckpt.MODEL_FILE)), w["fsdp", 0])  # raw weights of step 12, no EMA

    one = ShardedToyTask(world=1)  # rank 0's init, every row of every common batch
    train(one, ddp_cfg(12), tmp_path / "one", None, progress=False)
    start = ShardedToyTask(world=1).net.state_dict()
    for k, ref in one.net.state_dict().items():
        assert not torch.allclose(ref, start[k], atol=1e-3), f"{k} barely trained: the test would prove nothing"
        torch.testing.assert_close(w["fsdp", 0][k], ref, rtol=1e-5, atol=1e-6, msg=lambda m: f"{k}: {m}")  # noqa: B023 (called within this iteration)
    assert not torch.equal(w["ema", 0]["0.weight"], w["fsdp", 0]["0.weight"])  # the EMA runs ended on the EMA


def test_fsdp_requested_in_a_single_unlaunched_process_is_an_error(tmp_path: Path, monkeypatch):
    """No silent fallback: ACCELERATE_USE_FSDP without a launcher has nothing to shard across."""
    monkeypatch.setenv("ACCELERATE_USE_FSDP", "true")
    monkeypatch.setenv("FSDP_VERSION", "2")
    with pytest.raises(RuntimeError, match="FSDP was requested"):
        train(ShardedToyTask(world=1), ddp_cfg(2), tmp_path / "c", None, progress=False)


def test_deepspeed_is_refused_not_run_as_plain_data_parallel(tmp_path: Path, monkeypatch):
    """On CPU accelerate would train plain DDP under a DeepSpeed request without a word, and under ZeRO the
    checkpoints could not hold the optimizer state. Without the deepspeed package accelerate itself refuses."""
    monkeypatch.setenv("ACCELERATE_USE_DEEPSPEED", "true")
    with pytest.raises((RuntimeError, ImportError), match="DeepSpeed"):
        train(ShardedToyTask(world=1), ddp_cfg(2), tmp_path / "c", None, progress=False)
