"""DVC stage `infer_intrinsics`: DDIM or single-step sampling with CFG; all requested intrinsics
of an image in one batched pass; writes predictions in the shard stage's schema and keys.

    python stages/infer_intrinsics.py

Reads params `base`, `intrinsics` (the model) and `infer_intrinsics` (steps, cfg_scale,
timestep_spacing, ensemble, domains, splits); models/intrinsics + data/shards -> data/intrinsics_pred.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pilight import atomic  # noqa: E402
from pilight.params import ParamsError, load_section  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--params", default="params.yaml")
    ap.add_argument("--shards", type=Path, default=Path("data/shards"))
    ap.add_argument("--model", type=Path, default=Path("models/intrinsics"))
    ap.add_argument("--out", type=Path, default=Path("data/intrinsics_pred"))
    ap.add_argument("--metrics", type=Path, default=Path("metrics/infer_intrinsics.json"))
    args = ap.parse_args(argv)
    try:
        base = load_section("base", args.params)
        p, ip = load_section("intrinsics", args.params), load_section("infer_intrinsics", args.params)
    except ParamsError as exc:
        print(f"infer_intrinsics: {exc}", file=sys.stderr)
        return 2
    import torch
    from tqdm import tqdm

    from pilight.data.predictions import write_predictions
    from pilight.data.schema import DataError
    from pilight.data.shards import intrinsics_dataset, make_loader, read_index
    from pilight.train.build import ModelError, load_model
    from pilight.train.intrinsics import IntrinsicsTask

    try:
        index = read_index(args.shards)
        task = IntrinsicsTask(p, args.shards, seed=base.seed)
        load_model(task.stack, args.model)
    except (DataError, ModelError, FileNotFoundError, ValueError) as exc:
        print(f"infer_intrinsics: {exc}", file=sys.stderr)
        return 1
    task.stack.model.eval()
    timing = {"images": 0, "seconds": 0.0}

    def predictions(split: str):
        loader = make_loader(intrinsics_dataset(args.shards, split, shuffle=False), ip.batch_size)
        total = index["splits"][split]["samples"]
        gen = torch.Generator().manual_seed(base.seed)
        with tqdm(total=total, desc=f"infer {split}", unit="image") as bar:
            for batch in loader:
                t0 = time.perf_counter()
                pred = task.predict(batch["image"], ip.domains, ip, gen)
                timing["seconds"] += time.perf_counter() - t0
                timing["images"] += len(batch["key"])
                for i, key in enumerate(batch["key"]):
                    maps = {d: pred[d][i].cpu().numpy().transpose(1, 2, 0) for d in ip.domains}
                    yield key, maps, batch["meta"][i]
                bar.update(len(batch["key"]))

    splits = [s for s in ip.splits if index["splits"].get(s, {}).get("shards")]
    info = {"domains": list(ip.domains), "sampling": ip.model_dump(mode="json"), "parts": task.stack.describe()}
    try:  # shards are read (and verified) while predicting: damage there, or a full disk, is a message
        out_index = write_predictions(args.out, {s: predictions(s) for s in splits}, info)
        per_image = timing["seconds"] / max(timing["images"], 1)
        # Timings vary run to run: they go to a metrics file, never into the (deterministic) output.
        atomic.write_json(args.metrics, {"seconds_per_image": per_image, "images": timing["images"],
                                         "samples": {s: v["samples"] for s, v in out_index["splits"].items()}})
    except (DataError, ValueError, OSError) as exc:
        print(f"infer_intrinsics: error: {exc}", file=sys.stderr)
        return 1
    print(f"infer_intrinsics: {timing['images']} images, {per_image:.3f} s/image ({ip.mode}, {ip.steps} steps, "
          f"cfg {ip.cfg_scale}, ensemble {ip.ensemble}, domains {list(ip.domains)}) -> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
