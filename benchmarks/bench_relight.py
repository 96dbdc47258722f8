"""Stage-2 training speed with and without the physics terms, and peak memory of decode-with-gradients.

    python benchmarks/bench_relight.py [--steps 4] [--size 128] [--threads 2]

Training: the default `relight` params of params.yaml (pixel codec, UNet [64, 128, 128], batch 2
pairs x 3 branches) at --size^2 on a synthetic shard folder (tests.data.test_shards renders),
conditions: gt; optimizer steps per minute (AdamW; both cases in one process, interleaved step by
step on the same batches, median after 2 warm-up steps). "without" = lambda_ds = lambda_ps =
lambda_rec = 0 (no decode at all).

Decode memory: z (6 items = 2 pairs x 3 branches) -> codec.decode(z, checkpoint) -> sum of squares
-> backward, for the pixel codec and for a small random-init AutoencoderKL (block_out_channels
(32, 64, 64, 64), saved to a temp dir and loaded through VaeCodec). Each case runs in a fresh
spawned process; "held" = current RSS after the forward minus before it (what the graph keeps
until backward: what checkpointing saves while the UNet's activations are also alive); peak =
ru_maxrss after backward minus ru_maxrss once model and inputs exist (a high-water mark; with
checkpointing the recomputation happens inside backward, so the isolated peak does not drop).
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import resource
import sys
import tempfile
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def _rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # Linux: KiB


def _current_rss_mib() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def _train_case(steps: int, size: int, threads: int, q) -> None:
    """Both cases in one process, interleaved step by step (the machine is shared and noisy: a
    ratio measured side by side means more than two separate runs); median s/step after 2 warm-ups."""
    import statistics

    import torch

    torch.set_num_threads(threads)
    from pathlib import Path

    from fixtures.fake_renders import write_fake_renders
    from pilight.data.shard_params import ShardParams
    from pilight.data.shard_writer import write_shards
    from pilight.params import load_section
    from pilight.train.relight import RelightTask

    tmp = Path(tempfile.mkdtemp())
    write_shards(write_fake_renders(tmp / "r", size=size, ball=64), tmp / "s", ShardParams(), seed=0)
    p = load_section("relight", "params.yaml").model_copy(update={"conditions": "gt"})
    cases = {"with": p, "without": p.model_copy(update={"lambda_ds": 0.0, "lambda_ps": 0.0, "lambda_rec": 0.0})}
    task = RelightTask(p, tmp / "s", seed=0)
    opt = torch.optim.AdamW(task.trainable().parameters(), lr=1e-4)
    batches = [b for _, b in zip(range(steps + 2), _cycle(task))]
    gen = torch.Generator().manual_seed(0)
    times: dict[str, list[float]] = {k: [] for k in cases}
    for i, b in enumerate(batches):
        for name, params in cases.items():
            task.p = params  # same weights, same batch: only the loss differs
            t0 = time.perf_counter()
            loss, _ = task.loss(b, gen)
            loss.backward()
            opt.step()
            opt.zero_grad(set_to_none=True)
            if i >= 2:
                times[name].append(time.perf_counter() - t0)
    q.put(
        {k: {"s_per_step": statistics.median(v), "steps_per_min": 60 / statistics.median(v)} for k, v in times.items()}
    )


def _cycle(task):
    epoch = 0
    while True:
        yield from task.batches(epoch)
        epoch += 1


def _decode_case(codec_kind: str, checkpoint: bool, size: int, threads: int, q) -> None:
    import torch

    torch.set_num_threads(threads)
    from pilight.diffusion.codec import PixelCodec, VaeCodec

    if codec_kind == "pixel":
        codec = PixelCodec(4)
    else:
        from diffusers import AutoencoderKL

        tmp = tempfile.mkdtemp()
        torch.manual_seed(0)
        AutoencoderKL(
            block_out_channels=(32, 64, 64, 64),
            down_block_types=("DownEncoderBlock2D",) * 4,
            up_block_types=("UpDecoderBlock2D",) * 4,
            latent_channels=4,
            norm_num_groups=32,
        ).save_pretrained(tmp)
        codec = VaeCodec(tmp)
    h = size // codec.factor
    z = torch.randn(6, codec.latent_channels, h, h, requires_grad=True)
    base, base_now = _rss_mib(), _current_rss_mib()
    t0 = time.perf_counter()
    y = codec.decode(z * 1.0, checkpoint=checkpoint)  # z * 1.0: a non-leaf, as x0 = v_to_x0(...) is
    loss = y.square().mean()
    held = _current_rss_mib() - base_now  # what the graph keeps between forward and backward
    loss.backward()
    q.put(
        {
            "peak_mib": _rss_mib() - base,
            "held_mib": held,
            "seconds": time.perf_counter() - t0,
            "finite": bool(torch.isfinite(z.grad).all()),
        }
    )


def _spawn(fn, *args):
    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    proc = ctx.Process(target=fn, args=(*args, q))
    proc.start()
    out = q.get()
    proc.join()
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=int, default=6)
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    import torch

    print(
        f"command: python benchmarks/bench_relight.py --steps {args.steps} --size {args.size} --threads {args.threads}"
    )
    print(f"machine: CPU, torch {torch.__version__}, {args.threads} threads, {os.cpu_count()} logical cores (shared)\n")
    r = _spawn(_train_case, args.steps, args.size, args.threads)
    print(
        f"| case (default relight params, pixel codec, 2 pairs x 3 branches, {args.size}^2; median of "
        f"{args.steps} interleaved steps) | steps/min | s/step |"
    )
    print("|---|---|---|")
    for name in ("with", "without"):
        print(f"| train step, {name} physics terms | {r[name]['steps_per_min']:.1f} | {r[name]['s_per_step']:.2f} |")
    print(
        f"\nphysics terms: {r['with']['s_per_step'] / r['without']['s_per_step']:.2f}x the time of a step without them\n"
    )
    print(
        f"| decode with gradients, 6 items at {args.size}^2 | checkpoint | held between fwd and bwd (MiB) | "
        "peak RSS over baseline (MiB) | s (fwd+bwd) | grad finite |"
    )
    print("|---|---|---|---|---|---|")
    for kind in ("pixel", "vae"):
        for ck in (False, True):
            d = _spawn(_decode_case, kind, ck, args.size, args.threads)
            name = "pixel codec (factor 4)" if kind == "pixel" else "AutoencoderKL (32, 64, 64, 64), random init"
            print(
                f"| {name} | {'on' if ck else 'off'} | {d['held_mib']:.0f} | {d['peak_mib']:.0f} | {d['seconds']:.2f} | {d['finite']} |"
            )
    print(json.dumps({"train": r}))


if __name__ == "__main__":
    main()
