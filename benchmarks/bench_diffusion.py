"""Speed of the PI-Light diffusion model: sampling seconds per image and training steps/min.

    python benchmarks/bench_diffusion.py                      # CPU, small scratch UNet, 32x32 latent
    python benchmarks/bench_diffusion.py --device cuda        # same, bf16 autocast
    python benchmarks/bench_diffusion.py --device cuda --paper  # SD2 UNet (random init), 32x32 and 96x96 latents

One image = all 4 intrinsics (albedo, normal, roughness, metallic) = one sample of 4 views
in one batch.  Scratch config: 128x128 image, pixel-unshuffle codec factor 4 -> 48 x 32 x 32
latent (+48 condition channels).  Paper config: SD2 UNet, 4 + 4 input channels, latents of a
256^2 and a 768^2 image.  Each case is timed with and without cross-batch attention; times
are the best of --repeats after one warm-up.  Training = forward + backward + AdamW step on
the Stage 1 v-loss at batch 2 samples x 4 domains.  CUDA also reports
torch.cuda.max_memory_allocated per case.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import torch  # noqa: E402

from pilight.diffusion import (  # noqa: E402
    PAPER_UNET_SPEC,
    DomainDiffusion,
    LearnedEmbedding,
    PixelCodec,
    UNetSpec,
    build_unet,
    make_train_scheduler,
    sample,
)

DOMAINS = 4
SAMPLING = [("single_step", 1), ("ddim", 1), ("ddim", 4), ("ddim", 10), ("ddim", 50)]


def _sync(device):
    if device.type == "cuda":
        torch.cuda.synchronize()


def _timed(fn, device, repeats):
    fn()  # warm-up
    _sync(device)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        _sync(device)
        times.append(time.perf_counter() - t0)
    # best of: the CPU machine is shared with other jobs, the minimum is the least contaminated
    return min(times)


def _model(spec, latent_ch, cond_ch, cross_batch, device):
    torch.manual_seed(0)
    unet = build_unet(spec, latent_ch + cond_ch, latent_ch, DOMAINS)
    return DomainDiffusion(
        unet,
        LearnedEmbedding(spec.cross_attention_dim),
        DOMAINS,
        cond_ch,
        items_per_sample=DOMAINS,
        cross_batch=cross_batch,
    ).to(device)


def _peak_mb(device):
    return f"{torch.cuda.max_memory_allocated(device) / 2**20:.0f}" if device.type == "cuda" else "n/a"


def bench_sampling(model, codec, size, latent_ch, mode, steps, device, amp, repeats):
    """Seconds for one image (4 domains): encode condition, sample, decode the 4 outputs."""
    g = torch.Generator().manual_seed(0)
    image = (torch.rand(1, 3, size, size, generator=g) * 2 - 1).to(device)
    ids = torch.arange(DOMAINS, device=device)

    def run():
        with amp():
            cond = codec.encode(image) if codec else torch.randn(1, latent_ch, size, size, device=device)
            cond = cond.repeat_interleave(DOMAINS, 0)
            ehs = model.embed(image).repeat_interleave(DOMAINS, 0)
            x0 = sample(
                model,
                cond,
                ids,
                ehs,
                items_per_sample=DOMAINS,
                steps=steps,
                mode=mode,
                generator=torch.Generator(device).manual_seed(1),
            )
            return codec.decode(x0) if codec else x0

    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    return _timed(run, device, repeats), _peak_mb(device)


def bench_training(model, latent_ch, cond_ch, hw, device, amp, repeats, samples=2):
    """Seconds per optimiser step at ``samples`` x 4 domains."""
    n = samples * DOMAINS
    g = torch.Generator().manual_seed(0)
    x0, cond = torch.randn(n, latent_ch, hw, hw, generator=g), torch.randn(n, cond_ch, hw, hw, generator=g)
    noise = torch.randn(n, latent_ch, hw, hw, generator=g)
    t = torch.randint(0, 1000, (n,), generator=g)
    x0, cond, noise, t = (a.to(device) for a in (x0, cond, noise, t))
    ids = torch.arange(DOMAINS, device=device).repeat(samples)
    sched = make_train_scheduler()
    ac = sched.alphas_cumprod.to(device)
    x_t = ac[t].sqrt().view(-1, 1, 1, 1) * x0 + (1 - ac[t]).sqrt().view(-1, 1, 1, 1) * noise
    target = sched.get_velocity(x0, noise, t)
    opt = torch.optim.AdamW([p for p in model.parameters() if p.requires_grad], lr=1e-5)
    model.train()

    def step():
        with amp():
            ehs = model.embed(x0[:, :3]).to(x0.dtype)  # learned embedding: image content unused
            loss = torch.nn.functional.mse_loss(model(x_t, cond, t, ids, ehs).float(), target)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    sec = _timed(step, device, repeats)
    model.eval()
    return sec, _peak_mb(device)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--paper", action="store_true", help="SD2 UNet (random init) at 32x32 and 96x96 latents")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--max-steps", type=int, default=50, help="skip DDIM cases with more steps (CPU time)")
    args = ap.parse_args()
    device = torch.device(args.device)
    if device.type == "cuda":
        amp = lambda: torch.autocast("cuda", dtype=torch.bfloat16)  # noqa: E731
        torch.backends.cuda.matmul.allow_tf32 = True
    else:
        amp = contextlib.nullcontext

    if args.paper:  # SD2 UNet on VAE-sized latents (no VAE here: random condition latents)
        configs = [
            (PAPER_UNET_SPEC, 4, 4, hw, None, f"SD2 UNet, latent 4x{hw}x{hw} ({hw * 8}^2 image)") for hw in (32, 96)
        ]
    else:
        codec = PixelCodec(4)
        configs = [
            (
                UNetSpec(),
                codec.latent_channels,
                codec.latent_channels,
                32,
                codec,
                "scratch UNet, 128^2 image, pixel-unshuffle-4 -> 48x32x32",
            )
        ]

    print(f"command: python {' '.join(sys.argv)}")
    print(
        f"device: {device} ({torch.cuda.get_device_name(device) if device.type == 'cuda' else f'{torch.get_num_threads()} CPU threads'}), "
        f"torch {torch.__version__}, bf16 autocast: {device.type == 'cuda'}, repeats: {args.repeats}\n"
    )
    for spec, latent_ch, cond_ch, hw, codec, title in configs:
        print(f"### {title}\n")
        print("| case | cross-batch attn | s / image (4 domains) | images / s | peak MiB |")
        print("|---|---|---|---|---|")
        for cross in (True, False):
            model = _model(spec, latent_ch, cond_ch, cross, device).eval()
            for mode, steps in SAMPLING:
                if steps > args.max_steps:
                    continue
                reps = args.repeats
                size = hw * codec.factor if codec else hw
                sec, peak = bench_sampling(model, codec, size, latent_ch, mode, steps, device, amp, reps)
                name = "single step" if mode == "single_step" else f"DDIM {steps}"
                print(f"| {name} | {'on' if cross else 'off'} | {sec:.3f} | {1 / sec:.2f} | {peak} |", flush=True)
            sec, peak = bench_training(model, latent_ch, cond_ch, hw, device, amp, args.repeats)
            print(
                f"| train step, batch 2x4 ({60 / sec:.1f} steps/min, {1 / sec:.2f} it/s) | {'on' if cross else 'off'} "
                f"| {sec:.3f} s/step | | {peak} |",
                flush=True,
            )
            del model
        print()


if __name__ == "__main__":
    main()
