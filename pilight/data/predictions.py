"""Predicted intrinsics as webdataset shards, in the shard stage's schema and keys.

```
<pred_dir>/index.json              domains, sampling settings, per split: shards and counts
<pred_dir>/<split>/<split>-000000.tar   <key>.{albedo,normal,roughness,metallic}.exr (float16) + <key>.meta.json
```
Keys are the ground-truth shards' keys (`<scene>_vNN_lNN`), so stage 2 and evaluation join the
two by key. Written like the shards: fixed tar metadata, a temporary folder renamed into place.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any, Iterable

import numpy as np
import webdataset as wds

from pilight.data.exr import read_exr_bytes, write_exr
from pilight.data.schema import DataError
from pilight.data.shards import TAR_MTIME, TAR_OWNER


def _exr_bytes(arr: np.ndarray, scratch: Path) -> bytes:
    path = scratch / "map.exr"
    write_exr(path, arr, half=True)
    return path.read_bytes()


def write_predictions(out: Path, splits: dict[str, Iterable[tuple[str, dict[str, np.ndarray], str]]],
                      info: dict[str, Any]) -> dict[str, Any]:
    """splits: split -> iterable of (key, {domain: H x W x C array}, meta json). Returns index.json."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp-", dir=out.parent))
    index: dict[str, Any] = {**info, "splits": {}}
    try:
        with tempfile.TemporaryDirectory() as scratch:
            for split, items in splits.items():
                (tmp / split).mkdir()
                shards: list[str] = []
                count = 0
                with wds.ShardWriter(str(tmp / split / f"{split}-%06d.tar"), maxcount=10**9, verbose=0, encoder=False,
                                     post=lambda f: shards.append(Path(f).name), mtime=TAR_MTIME,
                                     user=TAR_OWNER, group=TAR_OWNER, mode=0o444) as w:
                    for key, maps, meta in items:
                        sample = {"__key__": key, "meta.json": meta.encode()}
                        sample.update({f"{d}.exr": _exr_bytes(a, Path(scratch)) for d, a in sorted(maps.items())})
                        w.write(sample)
                        count += 1
                index["splits"][split] = {"samples": count, "shards": shards}
        (tmp / "index.json").write_text(json.dumps(index, indent=1, sort_keys=True) + "\n")
        os.chmod(tmp, 0o755)
        if out.exists():
            shutil.rmtree(out)
        os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return index


def read_predictions(pred_dir: Path, split: str) -> dict[str, dict[str, np.ndarray]]:
    """key -> {domain: H x W x C float32}; small enough to hold in memory at our scales."""
    pred_dir = Path(pred_dir)
    index_path = pred_dir / "index.json"
    if not index_path.is_file():
        raise DataError(f"{index_path}: not found; run infer_intrinsics first")
    entry = json.loads(index_path.read_text())["splits"].get(split)
    if entry is None:
        raise DataError(f"{pred_dir}: no predictions for split {split!r} (infer_intrinsics.splits)")
    out: dict[str, dict[str, np.ndarray]] = {}
    for name in entry["shards"]:
        for s in wds.tarfile_samples([{"url": str(pred_dir / split / name)}]):
            out[s["__key__"]] = {k[:-4]: read_exr_bytes(v, f"{name}:{s['__key__']}.{k}")
                                 for k, v in s.items() if k.endswith(".exr")}
    return out
