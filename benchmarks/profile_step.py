"""Profile one training step of each stage on CPU: where the time of a step goes, and what the
candidate speed-ups would buy.

    python benchmarks/profile_step.py                       # both stages, params.yaml, data/shards
    python benchmarks/profile_step.py --stage relight --steps 8 --variants threads channels_last

A step is what pilight.train.loop does per optimizer step on one process: task.loss (batch already
decoded), backward, clip, AdamW. Batches are read once, before timing, so the loader is measured
separately ("load" row). For each variant the same batches, the same initial weights and the same
noise are used; the table prints milliseconds per step (median of --steps after one warm-up step),
and the profile of the baseline lists the operators with the most self CPU time.

Variants (each against the baseline, one at a time):
  threads        torch.set_num_threads(1) instead of all cores (oversubscription check)
  channels_last  the UNet in channels_last memory format
  bf16           the loss computed under torch.autocast("cpu", bfloat16) (oneDNN's bf16 kernels where the
                 CPU has AVX512-BF16/AMX), weights and optimizer in fp32, as accelerate's bf16 does
  no_physics     relight only: lambda_ds = lambda_ps = lambda_rec = lambda_image = 0 (the decode-with-
                 gradients path switched off; what the physics terms cost, not a proposal)
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch

from pilight.params import load_section


def make_task(stage: str, params: str, shards: Path, pred: Path, overrides: dict | None = None):
    base = load_section("base", params)
    p = load_section("intrinsics" if stage == "intrinsics" else "relight", params)
    if overrides:
        p = p.model_copy(update=overrides)
    torch.manual_seed(base.seed)
    if stage == "intrinsics":
        from pilight.train.intrinsics import IntrinsicsTask

        return IntrinsicsTask(p, shards, seed=base.seed), p
    from pilight.train.relight import RelightTask

    return RelightTask(p, shards, seed=base.seed, pred_dir=pred), p


def read_batches(task, n: int) -> tuple[list, float]:
    t0, out = time.perf_counter(), []
    for batch in task.batches(0):
        out.append(batch)
        if len(out) == n:
            break
    return out, (time.perf_counter() - t0) / max(len(out), 1)


def time_steps(task, p, batches: list, *, seed: int, profile: bool = False, bf16: bool = False):
    module = task.trainable()
    params = [q for q in module.parameters() if q.requires_grad]
    opt = torch.optim.AdamW(params, lr=p.train.lr, weight_decay=p.train.weight_decay)
    gen = torch.Generator().manual_seed(seed)
    module.train()

    def step(batch):
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
            loss, _ = task.loss(batch, gen, module)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(params, 1.0)
        opt.step()
        opt.zero_grad(set_to_none=True)

    step(batches[0])  # warm-up: allocator, first-call dispatch
    times, prof = [], None
    if profile:
        from torch.profiler import ProfilerActivity
        from torch.profiler import profile as torch_profile

        with torch_profile(activities=[ProfilerActivity.CPU]) as prof:
            for b in batches[1:]:
                step(b)
    else:
        for b in batches[1:]:
            t0 = time.perf_counter()
            step(b)
            times.append(time.perf_counter() - t0)
    return times, prof


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--params", default="params.yaml")
    ap.add_argument("--shards", type=Path, default=Path("data/shards"))
    ap.add_argument("--pred", type=Path, default=Path("data/intrinsics_pred"))
    ap.add_argument("--stage", choices=["intrinsics", "relight", "both"], default="both")
    ap.add_argument("--steps", type=int, default=6, help="timed steps per variant (after one warm-up)")
    ap.add_argument("--variants", nargs="*", default=["threads", "channels_last", "bf16", "no_physics"])
    ap.add_argument("--top", type=int, default=12, help="operators listed from the baseline's profile")
    args = ap.parse_args(argv)
    seed = load_section("base", args.params).seed
    cores = torch.get_num_threads()
    stages = ["intrinsics", "relight"] if args.stage == "both" else [args.stage]
    for stage in stages:
        task, p = make_task(stage, args.params, args.shards, args.pred)
        batches, load_s = read_batches(task, args.steps + 1)
        print(
            f"\n== {stage}: batch {p.train.batch_size}, {cores} threads; loader {1000 * load_s:.0f} ms/batch "
            f"(read + decode, outside the step)"
        )
        _, prof = time_steps(task, p, batches, seed=seed, profile=True)
        print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=args.top))
        rows = []
        for variant in ["baseline", *args.variants]:
            if variant == "no_physics" and stage != "relight":
                continue
            overrides = (
                {"lambda_ds": 0.0, "lambda_ps": 0.0, "lambda_rec": 0.0, "lambda_image": 0.0}
                if variant == "no_physics"
                else None
            )
            task, p = make_task(stage, args.params, args.shards, args.pred, overrides)
            if variant == "channels_last":
                task.trainable().to(memory_format=torch.channels_last)
            if variant == "threads":
                torch.set_num_threads(1)
            try:
                times, _ = time_steps(task, p, batches, seed=seed, bf16=variant == "bf16")
            finally:
                torch.set_num_threads(cores)
            rows.append((variant, 1000 * statistics.median(times), 1000 * min(times)))
        base_ms = rows[0][1]
        print(f"| {stage} variant | ms/step (median) | min | vs baseline |\n|---|---|---|---|")
        for name, med, lo in rows:
            print(f"| {name} | {med:.0f} | {lo:.0f} | {med / base_ms:.2f}x |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
