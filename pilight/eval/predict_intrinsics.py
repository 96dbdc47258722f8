"""What the infer_intrinsics stage writes to data/intrinsics_pred: every image of the requested splits
through the trained stage-1 model (all requested intrinsics of a batch in one sampling pass, from one
seeded generator per split), in the shard stage's schema and keys (pilight.data.predictions).

The sampling calls are timed, but the timings go to the stage's metrics file, never into the
predictions, which are byte-deterministic.

``task`` is anything with ``predict(image, domains, sampling, generator)`` (pilight.train.intrinsics's
IntrinsicsTask); eval never imports pilight.train.
"""

from __future__ import annotations

import time
from pathlib import Path

import torch
from tqdm import tqdm

from pilight.data.predictions import write_predictions
from pilight.data.shard_reader import intrinsics_dataset, make_loader


class Timing:
    """Seconds spent in the sampling calls (no data loading) and the images they predicted."""

    def __init__(self):
        self.images, self.seconds = 0, 0.0

    def per_image(self) -> float:
        return self.seconds / max(self.images, 1)


def predict_split(task, shards: Path, split: str, total: int, ip, seed: int, timing: Timing):
    """(key, {domain: H x W x C}, meta JSON) of every image of ``split`` (``total`` of them, for the
    progress bar), the ``ip.domains`` of ``ip``'s sampling."""
    gen = torch.Generator().manual_seed(seed)
    with tqdm(total=total, desc=f"infer {split}", unit="image") as bar:
        for batch in make_loader(intrinsics_dataset(shards, split, shuffle=False), ip.batch_size):
            t0 = time.perf_counter()
            pred = task.predict(batch["image"], ip.domains, ip, gen)
            timing.seconds += time.perf_counter() - t0
            timing.images += len(batch["key"])
            for i, key in enumerate(batch["key"]):
                yield key, {d: pred[d][i].cpu().numpy().transpose(1, 2, 0) for d in ip.domains}, batch["meta"][i]
            bar.update(len(batch["key"]))


def predict_intrinsics_splits(task, shards: Path, index: dict, out: Path, ip, seed: int, parts: dict) -> dict:
    """Predict every split of ``ip.splits`` that has shards (``index``: the shards' index.json) and
    write them to ``out``; its index records the domains, the sampling and the model's ``parts``.
    Returns the stage's metrics: seconds per image, images, samples per split written."""
    timing = Timing()
    splits = [s for s in ip.splits if index["splits"].get(s, {}).get("shards")]
    jobs = {s: predict_split(task, shards, s, index["splits"][s]["samples"], ip, seed, timing) for s in splits}
    info = {"domains": list(ip.domains), "sampling": ip.model_dump(mode="json"), "parts": parts}
    out_index = write_predictions(out, jobs, info)
    return {
        "seconds_per_image": timing.per_image(),
        "images": timing.images,
        "samples": {s: v["samples"] for s, v in out_index["splits"].items()},
    }
