"""Predicted intrinsics as webdataset shards, in the shard stage's schema and keys.

```
<pred_dir>/index.json              domains, sampling settings, per split: shards and counts
<pred_dir>/<split>/<split>-000000.tar   <key>.{albedo,normal,roughness,metallic}.exr (float16) + <key>.meta.json
```
Keys are the ground-truth shards' keys (`<scene>_vNN_lNN`), so stage 2 and evaluation join the
two by key. Written like the shards: fixed tar metadata, a temporary folder renamed into place,
and index.json records each tar's sample count and sha256 (``shard_checks``), which
:func:`read_predictions` verifies: a missing, cut or damaged tar is a DataError naming it.
"""

from __future__ import annotations

import json
import os
import shutil
import tarfile
import tempfile
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
import webdataset as wds

from pilight import atomic
from pilight.atomic import sha256_file
from pilight.data.exr import ExrError, read_exr_bytes, write_exr
from pilight.data.schema import DataError
from pilight.data.shard_reader import count_samples
from pilight.data.shard_writer import TAR_MTIME, TAR_OWNER


def _exr_bytes(arr: np.ndarray, scratch: Path) -> bytes:
    path = scratch / "map.exr"
    write_exr(path, arr, half=True)
    return path.read_bytes()


def write_predictions(
    out: Path, splits: dict[str, Iterable[tuple[str, dict[str, np.ndarray], str]]], info: dict[str, Any]
) -> dict[str, Any]:
    """splits: split -> iterable of (key, {domain: H x W x C array}, meta json). Returns index.json."""
    out = Path(out)
    index: dict[str, Any] = {**info, "splits": {}}
    tmp = None
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp-", dir=out.parent))
        with tempfile.TemporaryDirectory() as scratch:
            for split, items in splits.items():
                (tmp / split).mkdir()
                shards: list[str] = []
                checks: dict[str, dict[str, Any]] = {}

                def finished(f: str) -> None:  # called as each tar closes, while w.count is its count
                    shards.append(Path(f).name)  # noqa: B023 (called within this iteration)
                    checks[Path(f).name] = {"samples": w.count, "sha256": sha256_file(Path(f))}  # noqa: B023 (called within this iteration)

                count = 0
                with wds.ShardWriter(
                    str(tmp / split / f"{split}-%06d.tar"),
                    maxcount=10**9,
                    verbose=0,
                    encoder=False,
                    post=finished,
                    mtime=TAR_MTIME,
                    user=TAR_OWNER,
                    group=TAR_OWNER,
                    mode=0o444,
                ) as w:
                    for key, maps, meta in items:
                        sample = {"__key__": key, "meta.json": meta.encode()}
                        for d, a in sorted(maps.items()):
                            try:
                                sample[f"{d}.exr"] = _exr_bytes(a, Path(scratch))
                            except ExrError as exc:  # the scratch file's name would tell the user nothing
                                raise DataError(
                                    f"prediction {split}/{key} {d!r}: {str(exc).split(': ', 1)[-1]}"
                                ) from None
                        w.write(sample)
                        count += 1
                index["splits"][split] = {"samples": count, "shards": shards, "shard_checks": checks}
        (tmp / "index.json").write_text(json.dumps(index, indent=1, sort_keys=True) + "\n")
        os.chmod(tmp, atomic.dir_mode())  # mkdtemp makes it 0700 whatever the umask
        if out.exists():
            shutil.rmtree(out)
        os.replace(tmp, out)
    except BaseException as exc:
        atomic.abandon_folder(exc, tmp, out)
    return index


def read_predictions(pred_dir: Path, split: str) -> dict[str, dict[str, np.ndarray]]:
    """key -> {domain: H x W x C float32}; small enough to hold in memory at our scales.

    Every way the folder can be short is a DataError naming the file: a missing index or tar, a tar
    whose sha256 or sample count differs from index.json, an unreadable tar."""
    pred_dir = Path(pred_dir)
    index_path = pred_dir / "index.json"
    if not index_path.is_file():
        raise DataError(f"{index_path}: not found; run infer_intrinsics first")
    try:
        index = json.loads(index_path.read_text())
        entry = index["splits"].get(split)
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
        raise DataError(f"{index_path}: unreadable ({type(exc).__name__}: {exc}); rerun infer_intrinsics") from None
    if entry is None:
        raise DataError(f"{pred_dir}: no predictions for split {split!r} (infer_intrinsics.splits)")
    checks = entry.get("shard_checks")  # absent in folders written before the checks were recorded
    out: dict[str, dict[str, np.ndarray]] = {}
    for name in entry["shards"]:
        path = pred_dir / split / name
        if not path.is_file():
            raise DataError(f"{path}: prediction tar missing ({index_path} lists it); rerun infer_intrinsics")
        if checks is not None:
            want = checks.get(name)
            if want is None:
                raise DataError(f"{index_path}: no check recorded for {name}; rerun infer_intrinsics")
            if sha256_file(path) != want["sha256"]:
                raise DataError(
                    f"{path}: damaged prediction tar: sha256 differs from {index_path}; "
                    f"{count_samples(path)} of its {want['samples']} samples readable; rerun infer_intrinsics"
                )
        try:
            for s in wds.tarfile_samples([{"url": str(path)}]):
                out[s["__key__"]] = {
                    k[:-4]: read_exr_bytes(v, f"{name}:{s['__key__']}.{k}") for k, v in s.items() if k.endswith(".exr")
                }
        except (tarfile.TarError, OSError, EOFError) as exc:
            raise DataError(
                f"{path}: unreadable prediction tar ({type(exc).__name__}: {exc}); rerun infer_intrinsics"
            ) from None
    if "samples" in entry and len(out) != entry["samples"]:
        raise DataError(
            f"{pred_dir / split}: {len(out)} predictions read but {index_path} says {entry['samples']}; "
            "rerun infer_intrinsics"
        )
    return out
