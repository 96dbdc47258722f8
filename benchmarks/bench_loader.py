"""Loader throughput: samples/s of the stage-1 and stage-2 readers over synthetic shards.

    python benchmarks/bench_loader.py [--samples 128] [--batch 8] [--passes 3]

Writes a synthetic render folder (layout.py) and its shards to a temporary directory at 64x64 and
256x256, then times full passes of the DataLoader with 0 and 2 workers (best of --passes; worker
start-up included, as each epoch pays it). Prints a markdown table. The rate a stage-1 training
step consumes samples is not measured here: that model does not exist yet.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pilight.data import layout  # noqa: E402
from pilight.data.exr import write_exr  # noqa: E402
from pilight.data.shard_params import ShardParams  # noqa: E402
from pilight.data.shard_reader import intrinsics_dataset, make_loader, relight_dataset
from pilight.data.shard_writer import write_shards  # noqa: E402

VIEWS, LIGHTS = 4, 4


def fake_renders(root: Path, n_samples: int, size: int) -> None:
    """Random valid maps (image = albedo * diffuse + specular), all scenes in train."""
    rng = np.random.default_rng(0)
    scenes = max(1, n_samples // (VIEWS * LIGHTS))
    manifest = {"blender_version": "synthetic", "scenes": []}
    for i in range(scenes):
        sid = f"train_{i:04d}"
        manifest["scenes"].append({"id": sid, "kind": "object", "split": "train", "views": VIEWS, "lights": LIGHTS})
        (root / sid).mkdir(parents=True)
        (root / sid / "scene.json").write_text(
            json.dumps(
                {"cameras": [{"view": v} for v in range(VIEWS)], "lights": [{"light": li} for li in range(LIGHTS)]}
            )
        )
        for v in range(VIEWS):
            n = rng.normal(size=(size, size, 3))
            a = rng.random((size, size, 3), dtype=np.float32)
            for name, arr in {
                "albedo": a,
                "normal": n / np.linalg.norm(n, axis=-1, keepdims=True),
                "roughness": rng.random((size, size, 1)),
                "metallic": rng.random((size, size, 1)),
                "mask": np.ones((size, size, 1)),
            }.items():
                write_exr(layout.map_path(root, sid, v, name), arr, half=name != "albedo")
            for li in range(LIGHTS):
                d, s = rng.random((size, size, 3), dtype=np.float32) * 4, rng.random((size, size, 3), dtype=np.float32)
                for name, arr in {
                    "image": a * d + s,
                    "diffuse": d,
                    "specular": s,
                    "ball": rng.random((64, 64, 3)),
                }.items():
                    write_exr(layout.map_path(root, sid, v, name, li), arr, half=name == "ball")
            (layout.view_dir(root, sid, v) / layout.DONE_MARKER).touch()
    (root / "manifest.json").write_text(json.dumps(manifest))


def rate(dataset, batch: int, workers: int, passes: int) -> float:
    best = 0.0
    for _ in range(passes):
        t0, n = time.perf_counter(), 0
        for b in make_loader(dataset, batch_size=batch, num_workers=workers):
            n += len(b["key"])
        best = max(best, n / (time.perf_counter() - t0))
    return best


def train_rate(shards: Path, steps: int = 4) -> float:
    """Samples/s a stage-1 training step (forward + backward + AdamW) consumes with the default params."""
    import torch

    from pilight.params import load_section
    from pilight.train.intrinsics import IntrinsicsTask

    p = load_section("intrinsics", Path(__file__).resolve().parents[1] / "params.yaml")
    task = IntrinsicsTask(p, shards, seed=0)
    opt = torch.optim.AdamW(task.trainable().parameters(), lr=1e-4)
    gen = torch.Generator().manual_seed(0)
    batches = iter(task.batches(0))
    batch = next(batches)
    task.loss(batch, gen)[0].backward()  # warm-up
    t0 = time.perf_counter()
    for _ in range(steps):
        opt.zero_grad()
        task.loss(batch, gen)[0].backward()
        opt.step()
    return steps * p.train.batch_size / (time.perf_counter() - t0)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--samples", type=int, default=128)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--passes", type=int, default=3)
    args = ap.parse_args()
    rows, consumption = [], {}
    with tempfile.TemporaryDirectory() as tmp:
        for size in (64, 256):
            renders, shards = Path(tmp) / f"r{size}", Path(tmp) / f"s{size}"
            fake_renders(renders, args.samples, size)
            # 4 shards, so 2 workers split by shard (the usual case).
            write_shards(renders, shards, ShardParams(maxcount=max(1, args.samples // 4)), seed=0)
            for task, make in (("intrinsics", intrinsics_dataset), ("relight (pairs)", relight_dataset)):
                for workers in (0, 2):
                    rows.append(
                        (task, size, workers, rate(make(shards, "train", seed=0), args.batch, workers, args.passes))
                    )
            consumption[size] = train_rate(shards)
    print(
        f"`python benchmarks/bench_loader.py --samples {args.samples} --batch {args.batch} --passes {args.passes}`"
        f" on {platform.machine()}, {os.cpu_count()} CPU cores\n"
    )
    print("| loader | size | workers | samples/s | x stage-1 training's consumption |\n|---|---|---|---|---|")
    for task, size, workers, r in rows:
        print(f"| {task} | {size}x{size} | {workers} | {r:.0f} | {r / consumption[size]:.0f}x |")
    print(
        "\nStage-1 training (params.yaml `intrinsics`, CPU) consumes "
        + ", ".join(f"{c:.1f} samples/s at {s}x{s}" for s, c in consumption.items())
        + "; target: loader >= 10x."
    )


if __name__ == "__main__":
    main()
