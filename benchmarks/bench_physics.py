"""Time and peak memory of the PI-Light physics losses at training resolution.

    python benchmarks/bench_physics.py [--device cuda] [--batch 8] [--size 768] [--repeats 3] [--no-vit-b]

Each case and mode (fwd, fwd+bwd) runs in a fresh (spawned) process so its peak memory is its own:
on CPU, peak = ru_maxrss after the case minus ru_maxrss once its inputs
exist (a high-water mark of the resident set, so it includes allocator slack
and the autograd graph); on CUDA, torch.cuda.max_memory_allocated minus the
allocation before the first call.  Times: median over --repeats after one warm-up.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import resource
import statistics
import sys
import tempfile
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

CASES = [
    "diffuse_shading",
    "L_DS",
    "L_PS",
    "L_rec pooled-rgb-8x8",
    "all (pooled-rgb) + 1/t",
    "L_rec dinov2 ViT-B/14 random @224",
]


def _inputs(torch, b, s, dev):
    g = torch.Generator().manual_seed(0)
    n = torch.randn(b, 3, s, s, generator=g)
    n = n / n.norm(dim=1, keepdim=True)
    t = lambda: torch.rand(b, 3, s, s, generator=g).to(dev)
    return dict(
        env=torch.rand(b, 3, 16, 32, generator=g).to(dev),
        normals=n.to(dev),
        mask=(torch.rand(b, 1, s, s, generator=g) > 0.2).float().to(dev),
        relit=t(),
        inp=t(),
        albedo=t(),
        d_pred=t(),
        s_pred=t(),
    )


def _vit_b(tmp, dev):
    from transformers import Dinov2Config, Dinov2Model

    from pilight.physics import Dinov2Features

    cfg = Dinov2Config(
        hidden_size=768,
        num_hidden_layers=12,
        num_attention_heads=12,
        intermediate_size=3072,
        patch_size=14,
        image_size=518,
    )
    Dinov2Model(cfg).save_pretrained(tmp)  # random init, dinov2-base shape; loaded like real weights
    return Dinov2Features(tmp, resolution=224).to(dev)


def _case(name, backward, args, q):
    import torch

    from pilight.physics import (
        PooledRGBFeatures,
        diffuse_shading,
        diffuse_shading_loss,
        physical_shading_loss,
        physics_loss,
        reconstruction_loss,
    )

    dev = torch.device(args.device)
    torch.manual_seed(0)
    x = _inputs(torch, args.batch, args.size, dev)
    ext = PooledRGBFeatures()
    tmp = tempfile.TemporaryDirectory()
    if "dinov2" in name:
        ext = _vit_b(tmp.name, dev)
    t_steps = torch.randint(0, 1000, (args.batch,), device=dev)

    def run(backward):
        need = lambda k: x[k].detach().requires_grad_(backward)
        if name == "diffuse_shading":
            env, n = need("env"), need("normals")
            out = diffuse_shading(env, n, x["mask"]).sum()
        elif name == "L_DS":
            with torch.no_grad():
                d_calc = diffuse_shading(x["env"], x["normals"], x["mask"])
            out = diffuse_shading_loss(d_calc, need("d_pred"), x["mask"])
        elif name == "L_PS":
            out = physical_shading_loss(need("relit"), x["albedo"], need("d_pred"), need("s_pred"), x["mask"])
        elif name.startswith("L_rec"):
            out = reconstruction_loss(need("relit"), x["inp"], ext)
        else:
            relit, d_pred, s_pred = need("relit"), need("d_pred"), need("s_pred")
            with torch.no_grad():
                d_calc = diffuse_shading(x["env"], x["normals"], x["mask"])
            r = "none"
            out = physics_loss(
                t_steps,
                diffuse_shading_loss(d_calc, d_pred, x["mask"], r),
                physical_shading_loss(relit, x["albedo"], d_pred, s_pred, x["mask"], r),
                reconstruction_loss(relit, x["inp"], ext, r),
                (1.0, 1.0, 1.0),
                1.0,
            )
        if backward:
            out.backward()
        return out

    sync = torch.cuda.synchronize if dev.type == "cuda" else (lambda: None)
    if dev.type == "cuda":
        torch.cuda.reset_peak_memory_stats()
        base = torch.cuda.memory_allocated()
    else:
        base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    with torch.set_grad_enabled(backward):
        run(backward)  # warm-up
        sync()
        times = []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            run(backward)
            sync()
            times.append(time.perf_counter() - t0)
    if dev.type == "cuda":
        peak = (torch.cuda.max_memory_allocated() - base) / 2**20
    else:  # ru_maxrss is in KiB on Linux
        peak = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - base) / 1024
    q.put((statistics.median(times), peak))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--size", type=int, default=768)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--no-vit-b", action="store_true", help="skip the ViT-B-sized DINOv2 case")
    args = ap.parse_args()
    import torch

    ctx = mp.get_context("spawn")
    rows = []
    for name in CASES:
        if "dinov2" in name and args.no_vit_b:
            continue
        res = {}
        for mode, backward in (("fwd", False), ("fwd+bwd", True)):
            q = ctx.Queue()
            p = ctx.Process(target=_case, args=(name, backward, args, q))
            p.start()
            res[mode] = q.get()
            p.join()
        rows.append((name, res))
        print(f"done: {name}", file=sys.stderr, flush=True)
    mem = "CUDA max_memory_allocated delta" if args.device.startswith("cuda") else "ru_maxrss delta"
    print(
        f"\nbatch {args.batch} x 3 x {args.size} x {args.size}, device {args.device}, "
        f"torch {torch.__version__}, threads {torch.get_num_threads()}, median of {args.repeats}\n"
    )
    print(f"| case | fwd ms | fwd+bwd ms | fwd peak MiB | fwd+bwd peak MiB ({mem}) |")
    print("|---|---:|---:|---:|---:|")
    for name, r in rows:
        print(
            f"| {name} | {r['fwd'][0] * 1e3:.1f} | {r['fwd+bwd'][0] * 1e3:.1f} "
            f"| {r['fwd'][1]:.0f} | {r['fwd+bwd'][1]:.0f} |"
        )


if __name__ == "__main__":
    main()
