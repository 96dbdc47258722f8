"""pilight.train.loop: bit-exact resume, epochs, mixed precision, dvclive outputs."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from accelerate.state import AcceleratorState
from safetensors.torch import load_file

from pilight.params import TrainParams
from pilight.train import checkpoint as ckpt
from pilight.train import run_identity as run_id
from pilight.train.loop import train


@pytest.fixture(autouse=True)
def _fresh_accelerate_state():
    # accelerate keeps process-wide singletons; mixed_precision cannot change between Accelerators otherwise.
    AcceleratorState._reset_state(True)
    yield
    AcceleratorState._reset_state(True)


class ToyTask:
    """Denoise a fixed linear map; noise, timesteps and dropout all come from the loop's generator."""

    samples_per_batch = 4

    def __init__(self, n_batches: int = 5, crash_after: int | None = None, model_seed: int = 123):
        torch.manual_seed(model_seed)  # different init per run would be fine too: weights are restored
        self.net = torch.nn.Sequential(torch.nn.Linear(8, 16), torch.nn.GELU(), torch.nn.Linear(16, 8))
        self.n_batches, self.crash_after, self.calls = n_batches, crash_after, 0

    def trainable(self) -> torch.nn.Module:
        return self.net

    def batches(self, epoch: int):
        g = torch.Generator().manual_seed(1000 + epoch)  # deterministic per epoch, reshuffled per epoch
        for _ in range(self.n_batches):
            x = torch.randn(self.samples_per_batch, 8, generator=g)
            yield {"x": x, "y": x.flip(-1) * 0.5}

    def loss(self, batch, generator, model=None):
        self.calls += 1
        if self.crash_after is not None and self.calls > self.crash_after:
            raise KeyboardInterrupt("simulated kill")
        t = torch.rand(batch["x"].shape[0], 1, generator=generator)
        noise = torch.randn(batch["x"].shape, generator=generator)
        keep = (torch.rand(batch["x"].shape, generator=generator) > 0.1).float()
        pred = (model or self.net)((batch["x"] + t * noise) * keep)
        loss = torch.nn.functional.mse_loss(pred.float(), batch["y"])
        return loss, {"t_mean": float(t.mean())}

    def images(self, batch):
        pred = self.net(batch["x"]).float()
        v = ((pred - pred.min()) / (pred.max() - pred.min() + 1e-8) * 255).to(torch.uint8).cpu().numpy()
        return {"grid": np.repeat(np.repeat(v, 4, 0)[..., None], 3, -1)}  # H=16, W=8, 3


# The loop's settings are the stages' own params section; these are the toy runs' values.
LOOP = dict(lr=1e-4, warmup_steps=0, checkpoint_every=100, image_every=100, log_every=10)


def cfg(**kw) -> TrainParams:
    base = dict(steps=12, lr=1e-2, warmup_steps=3, checkpoint_every=4, keep_checkpoints=2, log_every=2, image_every=5)
    return TrainParams(**{**LOOP, **base, **kw})


def weights(task: ToyTask) -> dict[str, torch.Tensor]:
    return {k: v.detach().clone() for k, v in task.net.state_dict().items()}


def assert_bit_equal(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for k in a:
        assert torch.equal(a[k], b[k]), k


@pytest.mark.parametrize("grad_accum", [1, 2])
def test_stop_and_resume_is_bit_exact(tmp_path: Path, grad_accum: int):
    # 5 batches/epoch with accumulation 2: optimizer steps straddle epoch boundaries, resume lands mid-epoch.
    ref = ToyTask()
    out_ref = train(ref, cfg(grad_accum=grad_accum), tmp_path / "ref", None, progress=False)
    assert out_ref["steps"] == 12 and out_ref["resumed_from"] is None

    first = ToyTask()  # same init as the reference run
    train(first, cfg(grad_accum=grad_accum, steps=7), tmp_path / "split", None, progress=False)
    assert ckpt.latest_checkpoint(tmp_path / "split").name == "step_0000007"  # final checkpoint at stop
    second = ToyTask(model_seed=99)  # fresh process: different init, weights come from the checkpoint
    out = train(second, cfg(grad_accum=grad_accum), tmp_path / "split", None, progress=False)
    assert out["resumed_from"] == 7 and out["steps"] == 12
    assert_bit_equal(weights(ref), weights(second))
    assert out["final_loss"] == out_ref["final_loss"]


@pytest.mark.parametrize("lr_schedule", ["constant", "cosine"])
def test_resume_after_crash_is_bit_exact(tmp_path: Path, lr_schedule: str):
    ref = ToyTask()
    train(ref, cfg(lr_schedule=lr_schedule), tmp_path / "ref", None, progress=False)

    crashing = ToyTask(crash_after=10)  # dies during step 11; last checkpoint is step 8
    with pytest.raises(KeyboardInterrupt):
        train(crashing, cfg(lr_schedule=lr_schedule), tmp_path / "run", tmp_path / "live", progress=False)
    assert ckpt.latest_checkpoint(tmp_path / "run").name == "step_0000008"
    AcceleratorState._reset_state(True)
    resumed = ToyTask()
    out = train(resumed, cfg(lr_schedule=lr_schedule), tmp_path / "run", tmp_path / "live", progress=False)
    assert out["resumed_from"] == 8
    assert_bit_equal(weights(ref), weights(resumed))

    # dvclive history continues at step 8 without duplicated rows from the crashed run (it logged step 10).
    rows = list(csv.DictReader(open(tmp_path / "live/plots/metrics/loss.tsv"), delimiter="\t"))
    assert [int(r["step"]) for r in rows] == [2, 4, 6, 8, 10, 12]
    lr = [float(r["lr"]) for r in csv.DictReader(open(tmp_path / "live/plots/metrics/lr.tsv"), delimiter="\t")]
    if lr_schedule == "constant":
        assert lr[-3:] == [1e-2] * 3  # after the 3 warmup steps
    else:  # the resumed run continues the same cosine: cos(pi * 8/9) -> 0.6% of lr at step 11 of 12
        assert lr[1] > lr[2] > lr[3] > lr[4] > lr[5] and lr[5] < 0.02 * 1e-2


def test_ema_run_resumes_bit_exact_and_ends_holding_the_ema(tmp_path: Path):
    """The module leaves as the EMA of its weights (diffusers' recursion, warmup (1+n)/(10+n)),
    the checkpoints keep the raw weights and the EMA, and a crashed run resumes to the same EMA."""
    decay = 0.9
    ref = ToyTask()
    raw = [[p.detach().clone() for p in ref.net.parameters()]]
    real_loss = ref.loss

    def recording_loss(batch, generator, model):  # the weights before each step's forward = after the previous step
        raw.append([p.detach().clone() for p in ref.net.parameters()])
        return real_loss(batch, generator, model)

    ref.loss = recording_loss
    train(ref, cfg(ema_decay=decay), tmp_path / "ref", None, progress=False)
    last_raw = load_file(str(ckpt.latest_checkpoint(tmp_path / "ref") / ckpt.MODEL_FILE))
    raw = raw[2:] + [[last_raw[k] for k, _ in ref.net.named_parameters()]]  # after steps 1..12
    ema = [t.clone() for t in raw[0]]  # diffusers: decay 0 at the first step
    for n, weights_after in enumerate(raw[1:], start=2):
        d = min((n - 1 + 1) / (10 + n - 1), decay)
        ema = [d * e + (1 - d) * w for e, w in zip(ema, weights_after)]
    for got, want in zip(ref.net.parameters(), ema):
        torch.testing.assert_close(got.detach(), want, rtol=1e-6, atol=1e-7)
    assert not torch.equal(next(ref.net.parameters()).detach(), raw[-1][0])

    crashing = ToyTask(crash_after=10)
    with pytest.raises(KeyboardInterrupt):
        train(crashing, cfg(ema_decay=decay), tmp_path / "run", None, progress=False)
    assert (ckpt.latest_checkpoint(tmp_path / "run") / ckpt.EMA_FILE).is_file()
    AcceleratorState._reset_state(True)
    resumed = ToyTask(model_seed=99)
    assert train(resumed, cfg(ema_decay=decay), tmp_path / "run", None, progress=False)["resumed_from"] == 8
    assert_bit_equal(weights(ref), weights(resumed))


def test_ema_run_refuses_a_checkpoint_without_its_ema(tmp_path: Path):
    train(ToyTask(), cfg(steps=4), tmp_path / "c", None, progress=False)  # no identity: the folder is trusted
    with pytest.raises(FileNotFoundError, match="no ema.safetensors"):
        train(ToyTask(), cfg(steps=8, ema_decay=0.9), tmp_path / "c", None, progress=False)


def test_already_finished_run_does_nothing(tmp_path: Path):
    task = ToyTask()
    first = train(task, cfg(steps=4), tmp_path / "c", None, progress=False)
    before = weights(task)
    again = train(ToyTask(), cfg(steps=4), tmp_path / "c", None, progress=False)
    assert again["resumed_from"] == 4 and again["steps"] == 4
    assert again["final_loss"] == first["final_loss"]
    assert ckpt.latest_checkpoint(tmp_path / "c").name == "step_0000004"
    assert_bit_equal(before, weights(task))


def test_checkpoints_of_another_run_are_dropped_not_resumed(tmp_path: Path):
    # persist: true keeps checkpoints across `dvc exp run -S ...`: a changed run must start over.
    fresh = ToyTask()
    train(fresh, cfg(steps=4), tmp_path / "fresh", None, progress=False)
    train(ToyTask(model_seed=7), cfg(steps=4), tmp_path / "c", None, progress=False, identity={"lr": 1})
    again = train(ToyTask(), cfg(steps=4), tmp_path / "c", None, progress=False, identity={"lr": 1})
    assert again["resumed_from"] == 4  # same run: resumed (here: already finished)
    task = ToyTask()
    out = train(task, cfg(steps=4), tmp_path / "c", None, progress=False, identity={"lr": 2})
    assert out["resumed_from"] is None
    assert_bit_equal(weights(fresh), weights(task))
    assert json.loads((tmp_path / "c" / run_id.RUN_FILE).read_text()) == {"lr": 2}


def test_lowering_steps_ends_at_the_new_step(tmp_path: Path):
    short = ToyTask()
    train(short, cfg(steps=8), tmp_path / "short", None, progress=False)
    train(ToyTask(), cfg(steps=12, keep_checkpoints=3), tmp_path / "c", None, progress=False, identity={})
    task = ToyTask(model_seed=5)
    out = train(task, cfg(steps=8), tmp_path / "c", None, progress=False, identity={})
    assert out["resumed_from"] == 8
    assert_bit_equal(weights(short), weights(task))
    assert [p.name for p in ckpt.list_checkpoints(tmp_path / "c")] == ["step_0000004", "step_0000008"]


def test_run_identity_ignores_steps_and_sees_the_data(tmp_path: Path):
    (tmp_path / "d").mkdir()
    (tmp_path / "d" / "a.tar").write_bytes(b"abc")
    p = {"lr": 1e-4, "train": {"steps": 10, "lr": 1e-4, "log_every": 5}}
    a = run_id.run_identity(42, "intrinsics", p, [tmp_path / "d"])
    b = run_id.run_identity(
        42, "intrinsics", {**p, "train": {**p["train"], "steps": 99, "log_every": 1}}, [tmp_path / "d"]
    )
    assert a == b and p["train"]["steps"] == 10  # the caller's dict is not modified
    assert run_id.run_identity(42, "intrinsics", {**p, "lr": 2e-4}, [tmp_path / "d"]) != a
    (tmp_path / "d" / "a.tar").write_bytes(b"abd")
    assert run_id.run_identity(42, "intrinsics", p, [tmp_path / "d"]) != a


def test_retention_keeps_newest(tmp_path: Path):
    train(ToyTask(), cfg(steps=12, checkpoint_every=2, keep_checkpoints=2), tmp_path / "c", None, progress=False)
    names = sorted(p.name for p in (tmp_path / "c").iterdir())
    assert names == ["step_0000010", "step_0000012"]


def test_empty_epoch_raises(tmp_path: Path):
    with pytest.raises(RuntimeError, match="no batches"):
        train(ToyTask(n_batches=0), cfg(), tmp_path / "c", None, progress=False)


def test_nondeterministic_epoch_detected_on_resume(tmp_path: Path):
    train(ToyTask(n_batches=5), cfg(steps=4), tmp_path / "c", None, progress=False)  # stops at batch 4 of epoch 0
    with pytest.raises(RuntimeError, match="not deterministic"):
        train(ToyTask(n_batches=2), cfg(steps=8), tmp_path / "c", None, progress=False)


def test_bf16_on_cpu_is_finite_and_takes_effect(tmp_path: Path):
    out = train(ToyTask(), cfg(mixed_precision="bf16", steps=6), tmp_path / "c", None, progress=False)
    assert np.isfinite(out["final_loss"])
    AcceleratorState._reset_state(True)
    fp32 = train(ToyTask(), cfg(mixed_precision="fp32", steps=6), tmp_path / "f", None, progress=False)
    assert out["final_loss"] != fp32["final_loss"]  # autocast ran the linear layers in bf16


def test_bf16_on_a_cpu_without_native_kernels_warns(tmp_path: Path, monkeypatch):
    if torch.cuda.is_available():
        pytest.skip("CPU-only behaviour")
    import pilight.train.loop as loop

    monkeypatch.setattr(loop, "cpu_has_native_bf16", lambda: False)
    with pytest.warns(UserWarning, match="without native bf16 kernels.*mixed_precision: auto or fp32"):
        train(ToyTask(), cfg(mixed_precision="bf16", steps=2), tmp_path / "c", None, progress=False)


@pytest.mark.parametrize("native", [True, False])
def test_auto_precision_takes_bf16_only_where_the_cpu_has_it(tmp_path: Path, monkeypatch, capsys, native: bool):
    if torch.cuda.is_available():
        pytest.skip("CPU-only behaviour")
    import pilight.train.loop as loop

    monkeypatch.setattr(loop, "cpu_has_native_bf16", lambda: native)
    assert loop.resolve_mixed_precision("auto") == (
        ("bf16", "auto: bf16 on a CPU with native bf16 kernels")
        if native
        else ("no", "auto: fp32 on a CPU without native bf16 kernels")
    )
    assert loop.resolve_mixed_precision("auto", cuda=True)[0] == "bf16"
    AcceleratorState._reset_state(True)
    out = train(ToyTask(), cfg(mixed_precision="auto", steps=6), tmp_path / "a", None, progress=False)
    assert ("auto: bf16" if native else "auto: fp32") in capsys.readouterr().out  # says which it chose
    AcceleratorState._reset_state(True)
    same = "bf16" if native else "fp32"
    ref = train(ToyTask(), cfg(mixed_precision=same, steps=6), tmp_path / "r", None, progress=False)
    assert out["final_loss"] == ref["final_loss"]  # and trains exactly as that setting does


def test_fp16_on_cpu_falls_back_to_fp32(tmp_path: Path):
    if torch.cuda.is_available():
        pytest.skip("CPU-only behaviour")
    with pytest.warns(UserWarning, match="fp32"):
        out = train(ToyTask(), cfg(mixed_precision="fp16", steps=2), tmp_path / "c", None, progress=False)
    assert np.isfinite(out["final_loss"])


def test_dvclive_outputs(tmp_path: Path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # no git/DVC repo around: dvclive must still work offline
    out = train(ToyTask(), cfg(steps=10), tmp_path / "ckpt", tmp_path / "live", progress=True)
    live = tmp_path / "live"
    metrics = json.loads((live / "metrics.json").read_text())
    assert metrics["steps"] == 10 and metrics["step"] == 10
    assert metrics["final_loss"] == pytest.approx(out["final_loss"]) == pytest.approx(metrics["loss"])
    assert metrics["seconds"] > 0 and metrics["samples_per_second"] > 0
    for name in ("loss", "lr", "samples_per_second", "t_mean"):
        rows = list(csv.DictReader(open(live / f"plots/metrics/{name}.tsv"), delimiter="\t"))
        assert [int(r["step"]) for r in rows] == [2, 4, 6, 8, 10], name
    lrs = [float(r["lr"]) for r in csv.DictReader(open(live / "plots/metrics/lr.tsv"), delimiter="\t")]
    assert lrs[0] == pytest.approx(1e-2 * 2 / 3) and lrs[-1] == pytest.approx(1e-2)  # warmup 3 then constant
    from PIL import Image

    img = np.asarray(Image.open(live / "plots/images/grid.png"))
    assert img.shape == (16, 8, 3) and img.dtype == np.uint8
    assert not (live / "dvc.yaml").exists() and not (tmp_path / "dvc.yaml").exists()
    assert set(out) == {"steps", "seconds", "samples_per_second", "final_loss", "resumed_from"}


def test_a_run_shorter_than_image_every_still_leaves_its_preview(tmp_path: Path, monkeypatch):
    """dvc.yaml declares each training stage's plots/images an output: `-S intrinsics.train.steps=20` with
    image_every 100 once failed the stage with "output ... does not exist". The last step previews too."""
    monkeypatch.chdir(tmp_path)
    train(ToyTask(), cfg(steps=3, image_every=100), tmp_path / "ckpt", tmp_path / "live", progress=False)
    assert (tmp_path / "live" / "plots" / "images" / "grid.png").is_file()


def test_zero_steps_keeps_the_weights_and_scores_them(tmp_path: Path, monkeypatch):
    """`train.steps: 0` (the default's stage 1 is the shipped base as is): the weights leave untouched, the
    loss of the first batch is logged at step 0 beside the preview (dvc.yaml's outputs), nothing is
    checkpointed, and a run of another length's checkpoints are dropped, not resumed."""
    monkeypatch.chdir(tmp_path)
    train(ToyTask(model_seed=5), cfg(steps=4), tmp_path / "ckpt", None, progress=False)  # someone else's checkpoints
    task = ToyTask()
    before = weights(task)
    expected = task.loss(next(iter(task.batches(0))), torch.Generator().manual_seed(0))[0].item()
    task.calls = 0
    out = train(task, cfg(steps=0), tmp_path / "ckpt", tmp_path / "live", progress=False, identity={"run": 2})
    assert_bit_equal(before, weights(task))
    assert out["steps"] == 0 and out["final_loss"] == pytest.approx(expected, rel=1e-6) and task.calls == 1
    rows = list(csv.DictReader(open(tmp_path / "live/plots/metrics/loss.tsv"), delimiter="\t"))
    assert [(int(r["step"]), float(r["loss"])) for r in rows] == [(0, pytest.approx(expected, rel=1e-6))]
    assert (tmp_path / "live/plots/metrics/t_mean.tsv").is_file()
    assert (tmp_path / "live/plots/images/grid.png").is_file()
    assert ckpt.list_checkpoints(tmp_path / "ckpt") == []


def test_invalid_config():
    with pytest.raises(ValueError):
        TrainParams(steps=10, grad_accum=0)
    with pytest.raises(ValueError):
        TrainParams(steps=10, mixed_precision="fp8")
    with pytest.raises(ValueError, match="lr_schedule"):
        TrainParams(steps=10, lr_schedule="linear")
    with pytest.raises(ValueError, match="ema_decay"):
        TrainParams(steps=10, ema_decay=1.0)
    with pytest.raises(ValueError, match="steps"):
        TrainParams(steps=-1)


class ShardedToyTask:
    """A deterministic regression whose global batch k is split across ranks: rank r of `world` gets
    rows [r b, (r + 1) b) of it, and one process (world = 1) gets all of them, so a 2-process run and a
    1-process run see the same data. Rank 0 holds one batch more per epoch than the others (shards
    that do not divide evenly); every rank must stop at the common count.

    The loss is scaled so that the gradients sit near AdamW's eps (1e-8). AdamW is otherwise blind to a
    constant gradient scale, so summed instead of averaged gradients (2x) would train the same weights;
    here they do not."""

    SCALE = 1e-6

    def __init__(self, rank: int = 0, world: int = 1, per_rank: int = 2, n_batches: int = 3, model_seed: int = 123):
        torch.manual_seed(model_seed)
        self.net = torch.nn.Sequential(torch.nn.Linear(8, 16), torch.nn.GELU(), torch.nn.Linear(16, 8))
        self.rank, self.world, self.per_rank, self.n_batches = rank, world, per_rank, n_batches
        self.samples_per_batch = per_rank * (2 if world == 1 else 1)

    def trainable(self):
        return self.net

    def batches(self, epoch: int):
        g = torch.Generator().manual_seed(1000 + epoch)
        extra = 1 if self.world > 1 and self.rank == 0 else 0
        for _k in range(self.n_batches + extra):
            x = torch.randn(2 * self.per_rank, 8, generator=g)  # the global batch of 2 ranks
            if self.world > 1:
                x = x[self.rank * self.per_rank : (self.rank + 1) * self.per_rank]
            yield {"x": x, "y": x.flip(-1) * 0.5}

    def loss(self, batch, generator, model):
        return torch.nn.functional.mse_loss(model(batch["x"]), batch["y"]) * self.SCALE, {}

    def images(self, batch):
        return {}


def ddp_cfg(steps: int) -> TrainParams:
    return TrainParams(
        **{**LOOP, **dict(steps=steps, lr=1e-2, checkpoint_every=4, keep_checkpoints=2, log_every=2, image_every=100)}
    )


_TWO_PROCESS_SCRIPT = """
import os, sys, torch
sys.path.insert(0, {here!r})
from test_train_loop import ShardedToyTask, ddp_cfg
from pilight.train.loop import train
from safetensors.torch import save_file
out, rank = sys.argv[1], int(os.environ["RANK"])
for name, steps in (("ddp", 12), ("resumed", 7), ("resumed", 12)):
    task = ShardedToyTask(rank=rank, world=2, model_seed=123 + rank)  # another init per rank: DDP broadcasts rank 0's
    train(task, ddp_cfg(steps), f"{{out}}/{{name}}", None, progress=False)
    save_file({{k: v.contiguous() for k, v in task.net.state_dict().items()}}, f"{{out}}/{{name}}-{{rank}}.st")
"""


def test_two_processes_train_what_one_process_trains_on_their_batches(tmp_path: Path):
    """torchrun, 2 CPU processes (gloo), through accelerate.prepare (DDP): the weights equal, to float
    tolerance, one process trained on the two ranks' concatenated batches; the ranks agree bit for bit;
    uneven batch counts do not hang; a resumed 2-process run is bit-exact."""
    import os
    import subprocess
    import sys

    script = tmp_path / "two.py"
    script.write_text(_TWO_PROCESS_SCRIPT.format(here=str(Path(__file__).parent)))
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(Path(__file__).parents[2])}
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "torch.distributed.run",
            "--standalone",
            "--nproc_per_node",
            "2",
            str(script),
            str(tmp_path),
        ],
        env=env,
        capture_output=True,
        text=True,
        timeout=180,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    w = {(n, r): load_file(str(tmp_path / f"{n}-{r}.st")) for n in ("ddp", "resumed") for r in (0, 1)}
    assert_bit_equal(w["ddp", 0], w["ddp", 1])
    assert_bit_equal(w["ddp", 0], w["resumed", 0])
    assert_bit_equal(w["ddp", 1], w["resumed", 1])
    with ckpt.safe_open(str(ckpt.latest_checkpoint(tmp_path / "resumed") / ckpt.STATE_FILE), framework="pt") as fh:
        assert {"rank0.generator", "rank1.generator"} <= set(fh.keys())

    one = ShardedToyTask(world=1)  # rank 0's init, every row of every common batch
    train(one, ddp_cfg(12), tmp_path / "one", None, progress=False)
    start = ShardedToyTask(world=1).net.state_dict()
    for k, ref in one.net.state_dict().items():
        assert not torch.allclose(ref, start[k], atol=1e-3), f"{k} barely trained: the test would prove nothing"
        torch.testing.assert_close(w["ddp", 0][k], ref, rtol=1e-5, atol=1e-6, msg=lambda m: f"{k}: {m}")  # noqa: B023 (called within this iteration)


def test_non_finite_loss_stops_training(tmp_path: Path):
    class NanTask(ToyTask):
        def loss(self, batch, generator, model=None):
            loss, scalars = super().loss(batch, generator, model)
            return loss * float("nan") if self.calls > 3 else loss, scalars

    with pytest.raises(FloatingPointError, match="step 4"):
        train(NanTask(), cfg(log_every=2, checkpoint_every=2), tmp_path / "c", None, progress=False)
    assert ckpt.latest_checkpoint(tmp_path / "c").name == "step_0000002"  # the good one survives
