"""Memory per process of ONE stage-2 training step (RelightTask: the UNet forward, the decode of the x0
estimate with gradients, backward, clip, AdamW), data-parallel (DDP) against sharded (FSDP2).

    OMP_NUM_THREADS=1 python benchmarks/sharded_memory.py                       # ddp, fsdp (ZeRO-2 split), fsdp_full
    python benchmarks/sharded_memory.py --nproc 8 --modes ddp fsdp --params P   # GPUs: CUDA peak allocated

Each mode runs in fresh processes, set up exactly as pilight.train.loop.train sets them up
(``loop.prepare_training``): ``ddp`` under torchrun (gloo on CPU, NCCL on GPUs); ``fsdp`` through
``accelerate launch --config_file profiles/accelerate_fsdp.yaml`` (gradients and AdamW state sharded,
parameters gathered for forward and backward: SHARD_GRAD_OP); ``fsdp_full`` the same with
``--fsdp_reshard_after_forward true`` (FULL_SHARD, ZeRO-3's split). Every process takes its first
batch; step 1 warms up (AdamW allocates its state), step 2 is measured. Per process:

* trained tensors: the bytes of the parameters, gradients (after backward) and AdamW state that this
  process holds (local shards under FSDP); "whole copy": what the task's own module still holds
  under FSDP, which the loop empties while a sharded copy trains (pilight.train.sharding.prepare_sharded), so 0;
* CPU: peak RSS during step 2 (VmHWM, reset through /proc/self/clear_refs before the step), its rise
  over the RSS before the step, and ru_maxrss (the whole process, setup included);
* CUDA: torch.cuda.max_memory_allocated during step 2.

One line per mode, ranks side by side. DDP's gradient buckets (a second copy of the gradients) are
not tensors the script can see; they show in the RSS.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MODES = ("ddp", "fsdp", "fsdp_full")
MiB = 2**20


def _launch(mode: str, nproc: int, out: Path, args: argparse.Namespace) -> None:
    worker = [
        str(Path(__file__).resolve()),
        "--worker",
        str(out),
        "--params",
        args.params,
        "--shards",
        str(args.shards),
        "--pred",
        str(args.pred),
    ]
    if mode == "ddp":
        cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", str(nproc), *worker]
    else:
        cmd = [
            sys.executable,
            "-m",
            "accelerate.commands.launch",
            "--config_file",
            str(args.fsdp_config),
            "--num_processes",
            str(nproc),
            "--main_process_port",
            "0",
            "--fsdp_reshard_after_forward",
            "true" if mode == "fsdp_full" else "false",
            *worker,
        ]
    env = {
        **os.environ,
        "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "1"),
        "PYTHONPATH": os.pathsep.join([str(ROOT), *filter(None, [os.environ.get("PYTHONPATH")])]),
    }
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"{mode}: the processes failed (exit {proc.returncode}):\n{proc.stderr[-4000:]}")


def _status_kib(field: str) -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    raise KeyError(field)


def _reset_peak_rss() -> bool:
    try:  # Linux >= 4.0: "5" resets VmHWM to the current RSS
        Path("/proc/self/clear_refs").write_text("5")
        return True
    except OSError:
        return False


def _local_bytes(tensors) -> int:
    from torch.distributed.tensor import DTensor

    total = 0
    for t in tensors:
        t = t.to_local() if isinstance(t, DTensor) else t
        total += t.numel() * t.element_size()
    return total


def _worker(args: argparse.Namespace) -> None:
    import torch
    from accelerate import Accelerator
    from accelerate.utils import send_to_device

    from pilight.params import load_section
    from pilight.train import loop
    from pilight.train.relight import RelightTask

    base, p = load_section("base", args.params), load_section("relight", args.params)
    cfg = p.train
    cuda = torch.cuda.is_available()
    acc = Accelerator(
        mixed_precision="no"
        if cfg.mixed_precision == "fp32" or not cuda and cfg.mixed_precision == "fp16"
        else cfg.mixed_precision,
        cpu=not cuda,
    )
    torch.manual_seed(base.seed)
    task = RelightTask(p, args.shards, seed=base.seed, pred_dir=args.pred)
    module, model, optimizer, scheduler, params, sharded = loop.prepare_training(acc, task, cfg)
    batch = send_to_device(next(iter(task.batches(0))), acc.device)
    generator = torch.Generator().manual_seed(base.seed + acc.process_index)
    model.train()

    def step() -> int:
        with acc.autocast():
            loss, _ = task.loss(batch, generator, model)
        acc.backward(loss)
        grad_bytes = _local_bytes([q.grad for q in params if q.grad is not None])
        acc.clip_grad_norm_(params, 1.0)
        optimizer.step()
        scheduler.step()
        optimizer.zero_grad(set_to_none=True)
        return grad_bytes

    step()  # warm-up: AdamW allocates its state, the allocator its pools
    acc.wait_for_everyone()
    if cuda:
        torch.cuda.synchronize()
        torch.cuda.reset_peak_memory_stats()
    rss_before, hwm_reset = _status_kib("VmRSS"), _reset_peak_rss()
    t0 = time.perf_counter()
    grad_bytes = step()
    seconds = time.perf_counter() - t0
    opt = getattr(optimizer, "optimizer", optimizer)
    row = {
        "rank": acc.process_index,
        "sharded": sharded,
        "seconds": seconds,
        "params": _local_bytes(params),
        "grads": grad_bytes,
        "adamw": _local_bytes(t for s in opt.state.values() for t in s.values() if torch.is_tensor(t)),
        "whole_copy": _local_bytes(module.parameters()) if sharded else 0,
        "rss_before": rss_before * 1024,
        "step_peak_rss": _status_kib("VmHWM") * 1024 if hwm_reset else None,
        "ru_maxrss": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024,
        "cuda_peak": torch.cuda.max_memory_allocated() if cuda else None,
    }
    Path(args.worker, f"rank{acc.process_index}.json").write_text(json.dumps(row))
    acc.wait_for_everyone()


def _line(mode: str, rows: list[dict]) -> str:
    def each(key: str, fmt=lambda v: f"{v / MiB:.1f}") -> str:
        return "/".join("-" if r[key] is None else fmt(r[key]) for r in rows)

    trained = [r["params"] + r["grads"] + r["adamw"] for r in rows]
    text = (
        f"{mode:9s} {len(rows)} procs (MiB per rank {'/'.join(str(r['rank']) for r in rows)}): "
        f"params {each('params')} + grads {each('grads')} + AdamW {each('adamw')} = trained "
        f"{'/'.join(f'{t / MiB:.1f}' for t in trained)}; whole copy {each('whole_copy')}"
    )
    if rows[0]["cuda_peak"] is not None:
        return (
            text
            + f"; CUDA peak allocated in the step {each('cuda_peak')}; step {each('seconds', lambda v: f'{v:.2f}')} s"
        )
    rise = "/".join(
        "-" if r["step_peak_rss"] is None else f"{(r['step_peak_rss'] - r['rss_before']) / MiB:.0f}" for r in rows
    )
    return (
        text + f"; step peak RSS {each('step_peak_rss', lambda v: f'{v / MiB:.0f}')} (+{rise} over before the step); "
        f"ru_maxrss {each('ru_maxrss', lambda v: f'{v / MiB:.0f}')}; step {each('seconds', lambda v: f'{v:.2f}')} s"
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--params", default=str(ROOT / "params.yaml"))
    ap.add_argument("--shards", type=Path, default=ROOT / "data/shards")
    ap.add_argument("--pred", type=Path, default=ROOT / "data/intrinsics_pred")
    ap.add_argument("--nproc", type=int, default=2)
    ap.add_argument("--modes", nargs="+", choices=MODES, default=list(MODES))
    ap.add_argument("--fsdp-config", type=Path, default=ROOT / "profiles/accelerate_fsdp.yaml")
    ap.add_argument("--worker", help=argparse.SUPPRESS)  # internal: the folder a launched process reports to
    args = ap.parse_args(argv)
    if args.worker:
        _worker(args)
        return 0
    for mode in args.modes:
        with tempfile.TemporaryDirectory() as tmp:
            _launch(mode, args.nproc, Path(tmp), args)
            rows = sorted((json.loads(f.read_text()) for f in Path(tmp).glob("rank*.json")), key=lambda r: r["rank"])
        if rows and rows[0]["sharded"] != (mode != "ddp"):
            raise SystemExit(
                f"{mode}: the loop {'sharded' if rows[0]['sharded'] else 'did not shard'}; nothing to compare"
            )
        print(_line(mode, rows), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
