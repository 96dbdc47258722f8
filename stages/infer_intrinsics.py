"""DVC stage `infer_intrinsics`: DDIM or single-step sampling with CFG; all requested intrinsics
of an image in one batched pass; writes predictions in the shard stage's schema and keys.

    python stages/infer_intrinsics.py

Reads params `base`, `intrinsics` (the model) and `infer_intrinsics` (steps, cfg_scale,
timestep_spacing, ensemble, domains, splits); models/intrinsics + data/shards -> data/intrinsics_pred.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

from pilight import atomic
from pilight.stage_cli import fails_on, run_stage


def options(ap) -> None:
    ap.add_argument("--shards", type=Path, default=Path("data/shards"))
    ap.add_argument("--model", type=Path, default=Path("models/intrinsics"))
    ap.add_argument("--out", type=Path, default=Path("data/intrinsics_pred"))
    ap.add_argument("--metrics", type=Path, default=Path("metrics/infer_intrinsics.json"))


def body(args, base, p, ip) -> int:
    import torch
    from tqdm import tqdm

    from pilight.data.predictions import write_predictions
    from pilight.data.shards import intrinsics_dataset, make_loader, read_index
    from pilight.train.build import ModelError, load_model
    from pilight.train.intrinsics import IntrinsicsTask

    with fails_on(ModelError, FileNotFoundError, ValueError):
        index = read_index(args.shards)
        task = IntrinsicsTask(p, args.shards, seed=base.seed)
        load_model(task.stack, args.model)
    task.stack.model.eval()
    timing = {"images": 0, "seconds": 0.0}

    def predictions(split: str):
        gen = torch.Generator().manual_seed(base.seed)
        with tqdm(total=index["splits"][split]["samples"], desc=f"infer {split}", unit="image") as bar:
            for batch in make_loader(intrinsics_dataset(args.shards, split, shuffle=False), ip.batch_size):
                t0 = time.perf_counter()
                pred = task.predict(batch["image"], ip.domains, ip, gen)
                timing["seconds"] += time.perf_counter() - t0
                timing["images"] += len(batch["key"])
                for i, key in enumerate(batch["key"]):
                    yield key, {d: pred[d][i].cpu().numpy().transpose(1, 2, 0) for d in ip.domains}, batch["meta"][i]
                bar.update(len(batch["key"]))

    splits = [s for s in ip.splits if index["splits"].get(s, {}).get("shards")]
    info = {"domains": list(ip.domains), "sampling": ip.model_dump(mode="json"), "parts": task.stack.describe()}
    with fails_on(ValueError, OSError):  # shards are read (and verified) while predicting; or a full disk
        out_index = write_predictions(args.out, {s: predictions(s) for s in splits}, info)
        per_image = timing["seconds"] / max(timing["images"], 1)
        # Timings vary run to run: they go to a metrics file, never into the (deterministic) output.
        atomic.write_json(
            args.metrics,
            {
                "seconds_per_image": per_image,
                "images": timing["images"],
                "samples": {s: v["samples"] for s, v in out_index["splits"].items()},
            },
        )
    print(
        f"infer_intrinsics: {timing['images']} images, {per_image:.3f} s/image ({ip.mode}, {ip.steps} steps, "
        f"cfg {ip.cfg_scale}, ensemble {ip.ensemble}, domains {list(ip.domains)}) -> {args.out}"
    )
    return 0


def main(argv: list[str] | None = None) -> int:
    return run_stage("infer_intrinsics", __doc__, argv, ["base", "intrinsics", "infer_intrinsics"], options, body)


if __name__ == "__main__":
    sys.exit(main())
