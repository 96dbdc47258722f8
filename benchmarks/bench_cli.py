"""Seconds per photo and peak memory of the photo API (what `pilight decompose` / `pilight relight` run).

    python benchmarks/bench_cli.py [--sizes 256 512] [--repeats 2] [--threads 2] [--models models]

Cases, each at --sizes^2 processing resolution (the photo: scikit-image's astronaut resized to
that size, so outputs are at that size too), each in a fresh spawned process:

* decompose                stage 1 (albedo, normal, roughness, metallic in one batched pass);
* relight, 1 light         stage 1 + stage 2;
* relight, 6 lights        one call: stage 1 once, stage 2 in batches of relight_infer.batch_size;
* 6 x relight, 1 light     six separate calls (what the 6-light call saves).

Models: --models DIR when it holds trained models, else the params.yaml UNets untrained (speed
and memory do not depend on the weights). Sampling: params.yaml's infer_intrinsics and
relight_infer. seconds = median over --repeats timed calls after one warm-up call; peak = the
process's ru_maxrss at the end minus its RSS once the models are loaded (a high-water mark of
what inference adds), beside the pipeline's own estimate (pilight.pipeline.estimate_memory, which
the memory guard checks).
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
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
REPO = Path(__file__).resolve().parents[1]
CASES = ("decompose", "relight, 1 light", "relight, 6 lights", "6 x relight, 1 light")


def _current_rss_mib() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def _case(models: str, size: int, case: str, repeats: int, threads: int, q) -> None:
    import numpy as np
    import torch
    from PIL import Image
    from skimage.data import astronaut

    torch.set_num_threads(threads)
    from pilight import lights
    from pilight.pipeline import PILightPipeline

    pipe = PILightPipeline.from_pretrained(
        models, device="cpu", params=REPO / "params.yaml", processing_resolution=size
    )
    photo = np.asarray(Image.fromarray(astronaut()).resize((size, size), Image.LANCZOS))
    six = [lights.directional(a, 30.0) for a in (-150, -90, -30, 30, 90, 150)]
    run = {
        "decompose": lambda: pipe.decompose(photo),
        "relight, 1 light": lambda: pipe.relight(photo, six[:1]),
        "relight, 6 lights": lambda: pipe.relight(photo, six),
        "6 x relight, 1 light": lambda: [pipe.relight(photo, [l]) for l in six],
    }[case]
    base = _current_rss_mib()
    run()  # warm-up (allocator, kernels)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        run()
        times.append(time.perf_counter() - t0)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024 - base
    k = 0 if case == "decompose" else (6 if "6 lights" in case else 1)
    est = pipe.estimate_memory(size, size, k)["host"] / 2**20
    q.put(
        {
            "seconds": statistics.median(times),
            "peak_mib": peak,
            "estimate_mib": est,
            "processing": pipe.processing_size(size, size),
        }
    )


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[256, 512])
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--models", type=Path, default=REPO / "models")
    ap.add_argument("--cases", nargs="+", default=list(CASES), choices=CASES)
    args = ap.parse_args()
    trained = (args.models / "intrinsics" / "model.safetensors").is_file() and (
        args.models / "relight" / "model.safetensors"
    ).is_file()
    tmp = None
    models = args.models
    if not trained:
        from fixtures.tiny_models import save_tiny_models

        tmp = tempfile.TemporaryDirectory()
        models = save_tiny_models(Path(tmp.name), unet=None)
    print(
        f"models: {'trained, ' + str(args.models) if trained else 'params.yaml UNets, untrained'}; "
        f"{args.threads} threads; median of {args.repeats} after a warm-up; astronaut resized to each size"
    )
    ctx = mp.get_context("spawn")
    rows = []
    for size in args.sizes:
        for case in args.cases:
            q = ctx.Queue()
            p = ctx.Process(target=_case, args=(str(models), size, case, args.repeats, args.threads, q))
            p.start()
            r = q.get()
            p.join()
            rows.append((size, case, r))
            print(f"  {size}^2 {case}: {r['seconds']:.2f} s, peak +{r['peak_mib']:.0f} MiB", flush=True)
    print("\n| size | case | seconds per photo | peak memory (MiB) | guard's estimate (MiB) |")
    print("|---|---|---|---|---|")
    for size, case, r in rows:
        print(f"| {size}² | {case} | {r['seconds']:.2f} | {r['peak_mib']:.0f} | {r['estimate_mib']:.0f} |")
    by = {(s, c): r["seconds"] for s, c, r in rows}
    for size in args.sizes:
        if (size, "relight, 6 lights") in by and (size, "6 x relight, 1 light") in by:
            print(
                f"{size}²: 6 lights in one call take {by[size, 'relight, 6 lights'] / by[size, '6 x relight, 1 light']:.2f}"
                " of six separate calls"
            )
    if tmp is not None:
        tmp.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())
