"""The one training loop shared by both PI-Light stages (stage 1 intrinsics, stage 2 relighting).

A stage script builds a :class:`Task` and calls :func:`train`.  The same script runs

* on one process (CPU, or one GPU):   ``python stages/train_intrinsics.py``
* data-parallel on 2 CPU processes:   ``OMP_NUM_THREADS=1 torchrun --standalone --nproc_per_node 2 stages/train_intrinsics.py``
* data-parallel on 8 GPUs:            ``accelerate launch --multi_gpu --num_processes 8 stages/train_intrinsics.py``
* sharded, ZeRO-2's split (gradients and AdamW state sharded; FSDP2), on GPUs or CPU processes:
  ``accelerate launch --config_file profiles/accelerate_fsdp.yaml [--num_processes 2] stages/train_intrinsics.py``
* DeepSpeed ZeRO-2 (the paper's, profiles/accelerate_deepspeed_zero2.yaml) is refused with the reason,
  see :func:`pilight.train.sharding.sharding_requested`.

``train.batch_size`` is per process: N processes train on N x batch_size samples per step.

``accelerate`` handles device placement, autocast (``mixed_precision``), gradient accumulation,
fp16 loss scaling, the process group and the data-parallel wrapper: the trainable module goes
through ``accelerator.prepare`` (plain on one process, DDP under several), and the loop hands the
prepared model to ``task.loss``, which must call it (not its own module) for the forward pass with
gradients. The
model's forward embeds the condition itself, so every trainable parameter is used inside the
wrapped forward and DDP averages every gradient.  DDP's constructor broadcasts rank 0's weights.
Under several processes ``Task.batches`` returns this process's shard (webdataset
``split_by_node``); the ranks agree before every micro-batch that each of them has one, so an
epoch ends for all of them at the shortest rank's last batch and the collectives never hang, even
when the shards do not divide evenly.

Resume is automatic: if ``checkpoint_dir`` holds a complete checkpoint, :func:`train` restores
model, AdamW, LR scheduler, RNG states (one generator per process), step and epoch, rebuilds
``task.batches(epoch)`` and skips the batches already consumed (they are still read and decoded),
so on CPU a resumed run ends bit-identical to an uninterrupted one.  Multi-process resume needs a
shared ``checkpoint_dir`` and the same process count (else the RNG streams restart, with a warning).
Under ``dvc repro`` the checkpoint folder must be a ``persist: true`` output, or DVC deletes it
before the stage starts.  Checkpoints are safetensors only, see :mod:`pilight.train.checkpoint`.

Sharded (FSDP, see :mod:`pilight.train.sharding`): a sharded copy of ``task.trainable()`` trains and
is what ``task.loss`` gets; the module itself is emptied meanwhile and receives the whole weights
for previews (main process) and at the end (every process), so ``task.images`` and the caller's
save see plain tensors.  Checkpoints are gathered to full tensors and written by the main process
in the same format; on resume every process loads them and keeps its shard.  A request that cannot
be met (FSDP in a single unlaunched process, DeepSpeed) is an error, never a silent DDP run.

Optional Task hook: if the task has ``to(device)``, it is called first so frozen parts (VAE, text
encoder) follow the trainable module onto the accelerator's device.

Divergence (issue 36): the first logged loss is the run's start (kept in every checkpoint, so a resumed
run keeps it); a later logged loss above ``DIVERGENCE_FACTOR`` times it stops the run with a
:class:`DivergedError` before anything is checkpointed or saved. ``lr: 1.0`` once took a loss from
0.57 to 15,671 and saved that model with exit 0. Weights holding NaN/Inf stop the run before a preview
samples them (the sampler's own refusal blamed "the condition upstream").
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Iterable
from pathlib import Path
from typing import Any, Protocol

import numpy
import torch
from accelerate import Accelerator
from accelerate.utils import send_to_device
from tqdm.auto import tqdm

from pilight.machine import cpu_has_native_bf16
from pilight.params import TrainParams
from pilight.train import checkpoint as ckpt
from pilight.train import run_identity, sharded_state, sharding

# A logged loss (the mean over a log_every window) above this multiple of the run's first logged loss is
# divergence. Healthy runs of both stages end below their start; within a run the windows' means vary by a
# few times (which timesteps were drawn), never by two orders of magnitude.
DIVERGENCE_FACTOR = 100.0


class DivergedError(FloatingPointError):
    """The loss rose above DIVERGENCE_FACTOR x its start: the run stops, nothing is checkpointed or saved."""


class Task(Protocol):
    samples_per_batch: int

    def trainable(self) -> torch.nn.Module: ...
    def batches(self, epoch: int) -> Iterable[Any]: ...  # deterministic, this process's shard
    # model: the prepared module (a DDP wrapper under several processes); the forward with gradients calls it
    def loss(
        self, batch: Any, generator: torch.Generator, model: torch.nn.Module
    ) -> tuple[torch.Tensor, dict[str, float]]: ...
    def images(self, batch: Any) -> dict[str, numpy.ndarray]: ...  # must not draw from the global RNG it relies on


def _lr_schedule(
    optimizer: torch.optim.Optimizer, name: str, warmup: int, total: int
) -> torch.optim.lr_scheduler.LambdaLR:
    """diffusers' "constant_with_warmup" or "cosine" (warmup, then a half cosine to 0 at `total`).

    Cosine is stage 2's embedded default: a run of a few hundred steps that ends at a constant lr
    keeps the last updates' noise in its weights; decaying to 0 averages it out.  The curve is a
    function of `total`, so raising `train.steps` to continue a finished cosine run restarts the
    decay from the lr that the longer curve has at the resumed step."""
    from diffusers.optimization import get_scheduler

    return get_scheduler(
        "constant_with_warmup" if name == "constant" else name,
        optimizer,
        num_warmup_steps=warmup,
        num_training_steps=total,
    )


def resolve_mixed_precision(setting: str, cuda: bool | None = None) -> tuple[str, str]:
    """``train.mixed_precision`` -> (accelerate's name: "no" | "bf16" | "fp16", why). ``auto`` takes bf16
    on a GPU or where the CPU has native bf16 kernels, else fp32: emulated bf16 made a stage-1 step 13x
    slower than fp32 on an AVX2-only CPU. fp16 without a GPU falls back to fp32 (CPU autocast has no
    fp16 path worth taking)."""
    cuda = torch.cuda.is_available() if cuda is None else cuda
    native = cuda or cpu_has_native_bf16()
    where = "a GPU" if cuda else ("a CPU with native bf16 kernels" if native else "a CPU without native bf16 kernels")
    if setting == "auto":
        return ("bf16", f"auto: bf16 on {where}") if native else ("no", f"auto: fp32 on {where}")
    if setting == "fp16" and not cuda:
        return "no", "fp16 needs a GPU: fp32 on this CPU"
    return ("no" if setting == "fp32" else setting), f"{setting} as set, on {where}"


def _trainable(module: torch.nn.Module) -> list[torch.nn.Parameter]:
    params = [p for p in module.parameters() if p.requires_grad]
    if not params:
        raise ValueError("task.trainable() has no parameters with requires_grad=True")
    return params


def _optimizer(params: list[torch.nn.Parameter], cfg: TrainParams, acc: Accelerator):
    optimizer = torch.optim.AdamW(params, lr=cfg.lr, weight_decay=cfg.weight_decay)
    # accelerate steps a prepared scheduler num_processes times per optimizer step, hence the factor.
    scheduler = _lr_schedule(
        optimizer, cfg.lr_schedule, cfg.warmup_steps * acc.num_processes, cfg.steps * acc.num_processes
    )
    return optimizer, scheduler


def prepare_training(acc: Accelerator, task: Task, cfg: TrainParams):
    """What :func:`train` trains, also for benchmarks: (module, model, optimizer, scheduler, params, sharded).

    ``module`` is ``task.trainable()`` on the device; ``model`` what ``task.loss`` gets; ``params`` the
    trainable tensors that AdamW, clipping, the finiteness check and the EMA see (shards when sharded)."""
    sharded = sharding.sharding_requested(acc)
    if hasattr(task, "to"):
        task.to(acc.device)
    module = task.trainable().to(acc.device)
    if sharded:
        model, optimizer, scheduler = sharding.prepare_sharded(
            acc, module, lambda m: _optimizer(_trainable(m), cfg, acc)
        )
        return module, model, optimizer, scheduler, _trainable(model), True
    params = _trainable(module)
    optimizer, scheduler = _optimizer(params, cfg, acc)
    # One process: the module itself. Several: DDP (its constructor broadcasts rank 0's weights).
    # task.loss calls this prepared model, so the wrapper's hooks see the forward.
    model, optimizer, scheduler = acc.prepare(module, optimizer, scheduler)
    return module, model, optimizer, scheduler, params, False


def _rng_tensors(acc: Accelerator, generator: torch.Generator) -> dict[str, torch.Tensor]:
    """Every process's RNG states, gathered as uint8 tensors (no pickling) for the main process."""
    local = {"generator": generator.get_state(), "torch_cpu": torch.get_rng_state()}
    if acc.device.type == "cuda":
        local["cuda"] = torch.cuda.get_rng_state(acc.device)
    out = {}
    for name, t in local.items():
        rows = acc.gather(t.to(acc.device)).reshape(acc.num_processes, -1).cpu()
        out.update({f"rank{r}.{name}": rows[r] for r in range(acc.num_processes)})
    return out


def _restore_rng(acc: Accelerator, generator: torch.Generator, rng: dict[str, torch.Tensor]) -> None:
    r = acc.process_index
    if f"rank{r}.generator" not in rng:
        warnings.warn(
            f"checkpoint has no RNG state for process {r} (process count changed?); resume is not exact", stacklevel=2
        )
        return
    generator.set_state(rng[f"rank{r}.generator"])
    torch.set_rng_state(rng[f"rank{r}.torch_cpu"])
    if acc.device.type == "cuda" and f"rank{r}.cuda" in rng:
        torch.cuda.set_rng_state(rng[f"rank{r}.cuda"], acc.device)


def _all_have_batch(acc: Accelerator, have: bool) -> bool:
    """True when every process has a micro-batch (one tiny all-reduce); single process: ``have``."""
    if acc.num_processes == 1:
        return have
    flag = torch.tensor([1.0 if have else 0.0], device=acc.device)
    return bool(acc.reduce(flag, "sum").item() == acc.num_processes)


def _check_finite_before_saving(
    acc: Accelerator,
    win_loss: torch.Tensor,
    win_n: int,
    params: list[torch.nn.Parameter],
    ema: Any,
    step: int,
    sharded: bool = False,
) -> None:
    """NonFiniteError if the loss of the steps since the last log, or the weights (raw or EMA), hold NaN/Inf."""
    if win_n:
        pending = acc.reduce(win_loss / win_n, "mean").item()
        if not math.isfinite(pending):
            raise ckpt.NonFiniteError(f"non-finite loss {pending} at step {step}; not checkpointed")
    bad = ckpt.non_finite_tensors({str(i): sharding.local(p.detach()) for i, p in enumerate(params)})
    if ema is not None:
        shadow = {str(i): sharding.local(t) for i, t in enumerate(ema.shadow_params)}
        bad += [f"ema {k}" for k in ckpt.non_finite_tensors(shadow)]
    if sharded:  # each process sees only its own shards, and all of them must stop together
        if acc.reduce(torch.tensor([float(bool(bad))], device=acc.device), "sum").item() and not bad:
            bad = ["held by another process's shard"]
    if bad:
        raise ckpt.NonFiniteError(
            f"weights hold NaN/Inf after step {step} (trainable tensor(s) {bad[:3]}); not checkpointed (lower the lr?)"
        )


def _preview(acc: Accelerator, task: Task, batch: Any, live: Any, model: Any, module: Any, sharded: bool) -> None:
    """Log the task's preview grids of ``batch`` (main process); sharded, every process must call it."""
    if sharded:  # a collective: the main process receives the whole weights for its previews
        sharding.whole_weights(model, module, everywhere=False)
    if live is not None:
        # fork_rng: image sampling on the main process must not shift any training RNG stream.
        devices = [acc.device] if acc.device.type == "cuda" else []
        with torch.no_grad(), acc.autocast(), torch.random.fork_rng(devices=devices):
            for name, grid in task.images(send_to_device(batch, acc.device)).items():
                live.log_image(f"{name}.png", numpy.asarray(grid))
        model.train()
    if sharded:
        sharding.release(module)


def _score_initial_weights(
    acc: Accelerator,
    task: Task,
    generator: torch.Generator,
    model: Any,
    module: Any,
    live: Any,
    sharded: bool,
) -> float:
    """``train.steps: 0``: the loss of the untouched weights on the first batch (no gradient), logged at
    step 0 with the previews, so a run that trains nothing still leaves the metrics and pictures the
    stage declares (and says how good its starting point is). Returns that loss."""
    batch = next(iter(task.batches(0)), None)
    if not _all_have_batch(acc, batch is not None):
        raise RuntimeError("task.batches(0) yielded no batches; nothing to score the initial weights on")
    with torch.no_grad(), acc.autocast():
        loss, scalars = task.loss(send_to_device(batch, acc.device), generator, model)
    value = acc.reduce(loss.detach().float(), "mean").item()
    if not math.isfinite(value):
        raise ckpt.NonFiniteError(f"non-finite loss {value} of the initial weights (train.steps: 0); nothing saved")
    if live is not None:
        live.step = 0
        live.log_metric("loss", value)
        for k, v in scalars.items():
            live.log_metric(k, float(v))
        live.next_step()
    _preview(acc, task, batch, live, model, module, sharded)
    return value


def _truncate_history(metrics_dir: Path, step: int) -> None:
    """Drop dvclive rows logged after the checkpoint we resume from (they will be logged again)."""
    for tsv in metrics_dir.rglob("*.tsv"):
        lines = tsv.read_text(encoding="utf-8").splitlines(keepends=True)
        if not lines:
            continue
        col = lines[0].rstrip("\r\n").split("\t").index("step")
        kept = [ln for ln in lines[1:] if ln.strip() and int(ln.split("\t")[col]) <= step]
        tsv.write_text("".join([lines[0], *kept]), encoding="utf-8")


def _open_live(live_dir: Path, resumed_from: int | None):
    from dvclive import Live  # imports dvc: keep it off the import path of pilight.train

    # save_dvc_exp=False: the pipeline (dvc repro / dvc exp run) owns experiments; no git commits from here.
    # dvcyaml=None: dvc.yaml of the repo declares metrics/plots; dvclive must not write its own.
    live = Live(str(live_dir), resume=resumed_from is not None, save_dvc_exp=False, dvcyaml=None, report=None)
    if resumed_from is not None:
        _truncate_history(Path(live.plots_dir) / "metrics", resumed_from)
    return live


def train(
    task: Task,
    cfg: TrainParams,
    checkpoint_dir: Path,
    live_dir: Path | None,
    *,
    seed: int = 0,
    progress: bool = True,
    identity: dict | None = None,
) -> dict:
    """Train ``task`` for ``cfg.steps`` optimizer steps, resuming from ``checkpoint_dir`` when it can.

    ``cfg`` is the stage's ``train`` params section itself (pilight.params.TrainParams, validated
    there); ``seed`` is ``base.seed``: process k draws from a generator seeded ``seed + k``.

    ``identity`` (JSON-able: the params that shape the weights and a data hash) ties the
    checkpoints to one run, see :func:`pilight.train.run_identity.claim_run`; without it any
    checkpoint in the folder is trusted."""
    checkpoint_dir = Path(checkpoint_dir)
    cuda = torch.cuda.is_available()
    mixed, why = resolve_mixed_precision(cfg.mixed_precision, cuda)
    if cfg.mixed_precision == "fp16" and not cuda:
        warnings.warn("fp16 mixed precision needs a GPU; training in fp32 on CPU", stacklevel=2)
    if mixed == "bf16" and not cuda and not cpu_has_native_bf16():
        warnings.warn(
            "train.mixed_precision: bf16 on a CPU without native bf16 kernels (AVX512-BF16 or AMX): "
            "oneDNN emulates them and a step is likely slower than in fp32; set mixed_precision: auto or fp32",
            stacklevel=2,
        )
    acc = Accelerator(mixed_precision=mixed, gradient_accumulation_steps=cfg.grad_accum, cpu=not cuda)
    acc.print(f"train.mixed_precision: {why}")
    module, model, optimizer, scheduler, params, sharded = prepare_training(acc, task, cfg)
    ema = None
    if cfg.ema_decay > 0:
        from diffusers.training_utils import EMAModel

        ema = EMAModel(params, decay=cfg.ema_decay)
    # One stream per process so the shards draw different noise; the loop never uses the global RNG.
    generator = torch.Generator().manual_seed(seed + acc.process_index)

    step, epoch, consumed, resumed_from, prior_seconds, final_loss, start_loss = 0, 0, 0, None, 0.0, None, None
    if acc.is_main_process:
        ckpt.remove_stale_tmp(checkpoint_dir)
        if identity is not None:
            for line in run_identity.claim_run(checkpoint_dir, identity, cfg.steps):
                acc.print(line)
    acc.wait_for_everyone()
    latest, notes = ckpt.find_resume(checkpoint_dir, max_step=cfg.steps)
    if acc.is_main_process:
        for note in notes:  # a damaged checkpoint and the fallback are said, never silent
            warnings.warn(note, stacklevel=2)
    if latest is not None:  # sharded: every process loads the full tensors and keeps its shard
        state, rng = ckpt.load_checkpoint(
            latest,
            model=model if sharded else acc.unwrap_model(model),
            optimizer=optimizer.optimizer if sharded else optimizer,
            scheduler=scheduler,
            ema=ema,
        )
        _restore_rng(acc, generator, rng)
        step, epoch, consumed = state["step"], state["epoch"], state["batches_in_epoch"]
        resumed_from, prior_seconds, final_loss = step, state.get("seconds", 0.0), state.get("final_loss")
        start_loss = state.get("start_loss")
        acc.print(f"resuming from {latest} (step {step}, epoch {epoch}, batch {consumed})")

    live = _open_live(Path(live_dir), resumed_from) if live_dir is not None and acc.is_main_process else None
    bar = tqdm(
        total=cfg.steps,
        initial=min(step, cfg.steps),
        unit="step",
        dynamic_ncols=True,
        disable=not (progress and acc.is_local_main_process),
    )
    start, micro = time.perf_counter(), 0
    win_t, win_n, win_loss, win_scalars = start, 0, torch.zeros((), device=acc.device), {}
    model.train()
    if cfg.steps == 0:  # the initial weights are the model (a shipped base used as is): scored, not trained
        final_loss = _score_initial_weights(acc, task, generator, model, module, live, sharded)
    while step < cfg.steps:
        seen = 0
        batches = iter(task.batches(epoch))
        while True:
            batch = next(batches, None)
            if not _all_have_batch(acc, batch is not None):  # every rank ends the epoch at the same batch
                break
            seen += 1
            if seen <= consumed:  # fast-forward over batches a previous run already trained on
                continue
            with acc.accumulate(model):
                with acc.autocast():
                    loss, scalars = task.loss(send_to_device(batch, acc.device), generator, model)
                acc.backward(loss)  # divides by grad_accum; DDP averages the gradients over processes here
                if acc.sync_gradients and cfg.max_grad_norm is not None:
                    acc.clip_grad_norm_(params, cfg.max_grad_norm)
                optimizer.step()  # these three are no-ops until the last micro-batch of an accumulation
                scheduler.step()
                optimizer.zero_grad(set_to_none=True)
            consumed, micro, win_n = seen, micro + 1, win_n + 1
            win_loss += loss.detach().float()  # no .item() per micro-batch: avoids a GPU sync
            for k, v in scalars.items():
                win_scalars[k] = win_scalars.get(k, 0.0) + float(v)
            if not acc.sync_gradients:
                continue
            step += 1
            bar.update(1)
            if ema is not None:
                ema.step(params)

            if step % cfg.log_every == 0 or step == cfg.steps:
                now = time.perf_counter()
                final_loss = acc.reduce(win_loss / win_n, "mean").item()  # all processes reach this together
                if not math.isfinite(final_loss):  # stop before a checkpoint of diverged weights replaces a good one
                    raise ckpt.NonFiniteError(
                        f"non-finite loss {final_loss} at step {step}; not checkpointed, "
                        f"{checkpoint_dir} keeps its last good checkpoint"
                    )
                if start_loss is None:
                    start_loss = final_loss
                elif start_loss > 0 and final_loss > DIVERGENCE_FACTOR * start_loss:
                    raise DivergedError(
                        f"training diverged: the loss at step {step}, {final_loss:.4g}, is over {DIVERGENCE_FACTOR:g}x "
                        f"its start ({start_loss:.4g}, the first logged loss); stopped with nothing checkpointed or "
                        f"saved, {checkpoint_dir} keeps its last good checkpoint. Lower train.lr (now {cfg.lr:g}) or "
                        "raise train.warmup_steps"
                    )
                rate = win_n * task.samples_per_batch * acc.num_processes / max(now - win_t, 1e-9)
                bar.set_postfix(loss=f"{final_loss:.4f}")
                if live is not None:
                    live.step = step  # x axis = optimizer step, also across resumes
                    live.log_metric("loss", final_loss)
                    for k, v in win_scalars.items():
                        live.log_metric(k, v / win_n)
                    live.log_metric("lr", scheduler.get_last_lr()[0])
                    live.log_metric("samples_per_second", rate)
                    live.next_step()
                win_t, win_n, win_loss, win_scalars = now, 0, torch.zeros((), device=acc.device), {}

            # The last step previews too: a run shorter than image_every still leaves its pictures (dvc.yaml's out).
            if live_dir is not None and (step % cfg.image_every == 0 or step == cfg.steps):
                # The preview samples the weights: NaN there is the training's failure, said as such, not a
                # sampler traceback. Every process checks (sharded: a collective), so none waits alone.
                _check_finite_before_saving(acc, win_loss, win_n, params, ema, step, sharded)
                _preview(acc, task, batch, live, model, module, sharded)

            if step % cfg.checkpoint_every == 0 or step == cfg.steps:
                # checkpoint_every < log_every: the loss check above has not seen these steps yet, and
                # a finite loss can precede NaN weights (the update after it diverged). Every process
                # checks, so none is left waiting in a collective when the main one would refuse.
                _check_finite_before_saving(acc, win_loss, win_n, params, ema, step, sharded)
                rng = _rng_tensors(acc, generator)  # collective: every process, before the main one writes
                # Sharded: full CPU copies gathered onto the main process (a collective too).
                saved = (
                    sharded_state.gather_sharded(model, optimizer.optimizer, ema)
                    if sharded
                    else (acc.unwrap_model(model), optimizer, ema)
                )
                if acc.is_main_process:
                    seconds = prior_seconds + time.perf_counter() - start
                    ckpt.save_checkpoint(
                        checkpoint_dir,
                        step,
                        model=saved[0],
                        optimizer=saved[1],
                        scheduler=scheduler,
                        rng=rng,
                        keep=cfg.keep_checkpoints,
                        ema=saved[2],
                        progress={
                            "epoch": epoch,
                            "batches_in_epoch": consumed,
                            "seconds": seconds,
                            "final_loss": final_loss,
                            "start_loss": start_loss,
                        },
                    )
                acc.wait_for_everyone()
            if step >= cfg.steps:
                break
        if seen == 0:
            raise RuntimeError(f"task.batches({epoch}) yielded no batches; an empty epoch would loop forever")
        if seen < consumed:
            raise RuntimeError(
                f"task.batches({epoch}) yielded {seen} batches but the checkpoint consumed "
                f"{consumed}: batches() is not deterministic, cannot resume"
            )
        if step < cfg.steps:  # epoch exhausted (not a mid-epoch stop): next epoch from its first batch
            epoch, consumed = epoch + 1, 0
    bar.close()
    if ema is not None:  # checkpoints keep the raw weights (to continue training); the module leaves as the EMA
        ema.copy_to(params)
    if sharded:  # the task's module leaves holding the trained weights, whole, on every process
        sharding.whole_weights(model, module, everywhere=True)

    seconds = time.perf_counter() - start
    stats = {
        "steps": step,
        "seconds": prior_seconds + seconds,
        "samples_per_second": micro * task.samples_per_batch * acc.num_processes / max(seconds, 1e-9),
        "final_loss": final_loss,
        "resumed_from": resumed_from,
    }
    if live is not None:
        live.summary.update({k: v for k, v in stats.items() if v is not None})
        live.end()
    acc.wait_for_everyone()
    return stats
