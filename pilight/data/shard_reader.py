"""The PyTorch readers of the shards (pilight.data.shard_writer writes them) for training and
evaluation, and index.json's checks.

index.json records, per split, every shard's sample count and sha256 (``shard_checks``), and every
reader verifies them when it is created (:func:`verify_shards`).  A tar cut at a member boundary
is still a valid tar with fewer samples: it trained on 2 of 4 samples with exit 0.  Cut inside a
member, it lost a sample's members and failed with a raw ``KeyError: 'meta.json'``.  Both now fail
naming the shard.
"""

from __future__ import annotations

import json
import random
import tarfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
import webdataset as wds
from torch.utils.data import DataLoader, IterableDataset

from pilight.atomic import sha256_file
from pilight.data.exr import read_exr_bytes
from pilight.data.layout import VIEW_MAPS
from pilight.data.pairs import read_pairs
from pilight.data.schema import (
    DataError,
    sample_key,
)


def exr_decoder(key: str, data: bytes):
    """webdataset decode handler: `wds.WebDataset(urls, ...).decode(exr_decoder)` turns `*.exr`
    members into H x W x C float32 arrays (webdataset has no EXR decoder of its own)."""
    return read_exr_bytes(data, key) if key.endswith(".exr") else None


def read_index(shard_dir: Path) -> dict[str, Any]:
    path = Path(shard_dir) / "index.json"
    if not path.is_file():
        raise DataError(f"{path}: not found; run the shard stage first")
    try:
        index = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise DataError(f"{path}: unreadable ({exc}); rerun the shard stage") from None
    if not isinstance(index, dict) or not isinstance(index.get("splits"), dict):
        raise DataError(f"{path}: want an object with 'splits'; rerun the shard stage")
    return index


# Shards already verified in this process, by (path, size, mtime, inode, recorded sha256): the
# training tasks build a dataset per epoch, and hashing the data again each time costs a full read.
_VERIFIED: set[tuple] = set()


def verify_shards(folder: Path, split: str, entry: dict[str, Any], index_path: Path) -> None:
    """DataError naming the shard unless every shard of ``entry`` (one split of index.json) exists
    and matches its recorded sample count and sha256.  An index written before the checks were
    recorded has none (``shard_checks`` absent): its shards are read unverified, as before."""
    checks = entry.get("shard_checks")
    if checks is None:
        return
    if not isinstance(checks, dict) or sorted(checks) != sorted(entry["shards"]):
        raise DataError(
            f"{index_path}: split {split!r}: 'shard_checks' does not list exactly its shards; rerun the shard stage"
        )
    recorded = sum(c["samples"] for c in checks.values())
    if "samples" in entry and recorded != entry["samples"]:
        raise DataError(
            f"{index_path}: split {split!r}: its shards hold {recorded} samples but it says "
            f"{entry['samples']}; rerun the shard stage"
        )
    for name in entry["shards"]:
        path = Path(folder) / name
        want = checks[name]
        try:
            st = path.stat()
        except FileNotFoundError:
            raise DataError(
                f"{path}: shard missing ({index_path} lists it with {want['samples']} samples); rerun the shard stage"
            ) from None
        key = (str(path.resolve()), st.st_size, st.st_mtime_ns, st.st_ino, want["sha256"])
        if key in _VERIFIED:
            continue
        if sha256_file(path) != want["sha256"]:
            found = count_samples(path)
            raise DataError(
                f"{path}: damaged shard: sha256 differs from {index_path}; {found} of its "
                f"{want['samples']} samples readable; rerun the shard stage"
            )
        _VERIFIED.add(key)


def count_samples(path: Path) -> str:
    """How many complete-looking samples (distinct keys) a tar holds, for messages; 'none' if it is unreadable."""
    keys: set[str] = set()
    try:
        with tarfile.open(path) as tf:
            for member in tf:
                if member.isfile():
                    keys.add(member.name.split(".", 1)[0])
    except (tarfile.TarError, OSError, EOFError):
        pass
    return str(len(keys)) if keys else "none"


class ShardDataset(IterableDataset):
    """Stream one split. task="intrinsics": one item per sample (image, four intrinsics, mask);
    task="relight": one item per pair listed in pairs/<split>.tsv.

    Shards are split across nodes (webdataset split_by_node) and DataLoader workers
    (split_by_worker). With fewer shards than readers (nodes x workers), every reader streams
    all shards and keeps every n-th sample (relight: view), so no reader idles or hangs and each
    item still comes exactly once per pass. shuffle: shard order from (seed, epoch), identical
    on every reader, then a buffer shuffle. repeat: endless passes, epoch + 1 each, for
    iteration-based multi-GPU training where ranks must never run dry at different times.
    Call set_epoch(e) before each epoch when not repeating (like DistributedSampler).
    """

    def __init__(
        self,
        shard_dir: Path,
        split: str,
        task: Literal["intrinsics", "relight"],
        *,
        shuffle: bool = False,
        repeat: bool = False,
        seed: int = 0,
        buffer: int = 256,
        cross_only: bool = False,
    ):
        if task not in ("intrinsics", "relight"):
            raise ValueError(f"task must be 'intrinsics' or 'relight', got {task!r}")
        entry = read_index(shard_dir)["splits"].get(split)
        if not entry or not entry["shards"]:
            raise DataError(f"{shard_dir}: split {split!r} has no shards")
        verify_shards(Path(shard_dir) / split, split, entry, Path(shard_dir) / "index.json")
        self.urls = [str(Path(shard_dir) / split / name) for name in entry["shards"]]
        self.num_samples = entry["samples"]
        self.task, self.shuffle, self.repeat, self.seed, self.buffer = task, shuffle, repeat, seed, buffer
        self.epoch = 0
        self.pairs: dict[tuple[str, int], list[tuple[int, int]]] = {}
        if task == "relight":
            for p in read_pairs(Path(shard_dir) / "pairs" / f"{split}.tsv"):
                if cross_only and p.a == p.b:  # an identity pair (a -> a)
                    continue
                self.pairs.setdefault((p.scene, p.view), []).append((p.a, p.b))

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def __iter__(self) -> Iterator[dict[str, Any]]:
        epoch = self.epoch
        while True:
            n = 0
            for item in self._one_pass(epoch):
                n += 1
                yield item
            if not self.repeat:
                return
            if n == 0:  # repeating an empty stream would spin forever
                raise DataError(f"{self.urls[0]}...: this reader got no {self.task} items; fewer units than readers")
            epoch += 1

    def _one_pass(self, epoch: int) -> Iterator[dict[str, Any]]:
        rank, world, worker, workers = wds.utils.pytorch_worker_info()
        readers, reader = world * workers, rank * workers + worker
        urls = list(self.urls)
        if self.shuffle:
            random.Random(f"{self.seed}:{epoch}").shuffle(urls)  # same order on every reader
        if len(urls) >= readers:
            units = self._units(list(wds.split_by_worker(wds.split_by_node(urls))))
        else:
            units = (u for i, u in enumerate(self._units(urls)) if i % readers == reader)
        items = (it for u in units for it in self._items(u))
        if self.shuffle:
            items = _buffer_shuffle(items, self.buffer, random.Random(f"{self.seed}:{epoch}:{reader}"))
        for item in items:
            yield self._decode(item)

    def _units(self, urls: list[str]) -> Iterator[Any]:
        samples = _checked_samples(urls, self.task)
        if self.task == "intrinsics":
            yield from samples
            return
        group: list[dict] = []
        for s in samples:  # all lights of a view are consecutive in one shard (writer's rule)
            if group and _view_of(s) != _view_of(group[0]):
                yield group
                group = []
            group.append(s)
        if group:
            yield group

    def _items(self, unit: Any) -> Iterator[Any]:
        if self.task == "intrinsics":
            yield unit
            return
        scene, view = _view_of(unit[0])
        by_light = {_meta(s)["light"]: s for s in unit}
        for a, b in self.pairs.get((scene, view), []):
            if a not in by_light or b not in by_light:
                raise DataError(
                    f"{unit[0]['__url__']}: pairs list {scene} view {view} light {a}->{b}, "
                    f"but the shard has lights {sorted(by_light)}; shards and pairs out of date?"
                )
            yield by_light[a], by_light[b]

    def _decode(self, item: Any) -> dict[str, Any]:
        if self.task == "intrinsics":
            out = {"key": item["__key__"], "meta": item["meta.json"].decode()}
            out.update({k: _tensor(item, k) for k in ("image", *VIEW_MAPS)})
            return out
        sa, sb = item
        ma, mb = _meta(sa), _meta(sb)
        out = {
            "key": f"{sample_key(ma['scene'], ma['view'], ma['light'])}_to_l{mb['light']:02d}",
            "meta_a": sa["meta.json"].decode(),
            "meta_b": sb["meta.json"].decode(),
            "image_a": _tensor(sa, "image"),
            "ball_a": _tensor(sa, "ball"),
        }
        out.update({f"{k}_b": _tensor(sb, k) for k in ("image", "ball", "diffuse", "specular")})
        if "ball_lambertian.exr" in sb:  # present when the render stage wrote it (render.lambertian_ball)
            out["ball_lambertian_b"] = _tensor(sb, "ball_lambertian")
        if "ball_lambertian.exr" in sa:
            out["ball_lambertian_a"] = _tensor(sa, "ball_lambertian")
        out.update({k: _tensor(sb, k) for k in VIEW_MAPS})
        return out


# Members every sample of a task needs; one lost to a cut tar must be named, not a KeyError later.
_REQUIRED = {
    "intrinsics": ("meta.json", "image.exr", *(f"{k}.exr" for k in VIEW_MAPS)),
    "relight": ("meta.json", "image.exr", "ball.exr", "diffuse.exr", "specular.exr", *(f"{k}.exr" for k in VIEW_MAPS)),
}


def _checked_samples(urls: list[str], task: str) -> Iterator[dict]:
    """webdataset's samples of ``urls``, each with every member ``task`` reads (DataError otherwise,
    naming the shard and the sample), tar errors turned into DataErrors naming the shard."""
    url = urls[0] if urls else ""
    try:
        for s in wds.tarfile_samples({"url": u} for u in urls):
            url = s.get("__url__", url)
            missing = [m for m in _REQUIRED[task] if m not in s]
            if missing:
                raise DataError(
                    f"{url}: sample {s.get('__key__')!r} lacks {missing}: the shard is cut or "
                    "damaged; rerun the shard stage"
                )
            yield s
    except (tarfile.TarError, OSError, EOFError) as exc:
        raise DataError(f"{url}: unreadable shard ({type(exc).__name__}: {exc}); rerun the shard stage") from None


def _buffer_shuffle(items: Iterator[Any], size: int, rng: random.Random) -> Iterator[Any]:
    buf: list[Any] = []
    for it in items:
        buf.append(it)
        if len(buf) >= size:
            i = rng.randrange(len(buf))
            buf[i], buf[-1] = buf[-1], buf[i]
            yield buf.pop()
    rng.shuffle(buf)
    yield from buf


def _meta(sample: dict) -> dict:
    return json.loads(sample["meta.json"])


def _view_of(sample: dict) -> tuple[str, int]:
    m = _meta(sample)
    return m["scene"], m["view"]


def _tensor(sample: dict, name: str) -> torch.Tensor:
    member = f"{sample['__url__']}:{sample['__key__']}.{name}.exr"
    if f"{name}.exr" not in sample:
        raise DataError(f"{member}: missing from the shard")
    arr = read_exr_bytes(sample[f"{name}.exr"], member)
    return torch.from_numpy(np.ascontiguousarray(arr.transpose(2, 0, 1)))  # C x H x W


def intrinsics_dataset(
    shard_dir: Path,
    split: str = "train",
    *,
    shuffle: bool = True,
    repeat: bool = False,
    seed: int = 0,
    buffer: int = 256,
) -> ShardDataset:
    """Stage 1: {key, meta, image, albedo, normal, roughness, metallic, mask}, linear, C x H x W."""
    return ShardDataset(shard_dir, split, "intrinsics", shuffle=shuffle, repeat=repeat, seed=seed, buffer=buffer)


def relight_dataset(
    shard_dir: Path,
    split: str = "train",
    *,
    shuffle: bool = True,
    repeat: bool = False,
    seed: int = 0,
    buffer: int = 256,
    cross_only: bool = False,
) -> ShardDataset:
    """Stage 2: {key, meta_a, meta_b, image_a, ball_a, image_b, ball_b, diffuse_b, specular_b, albedo,
    normal, roughness, metallic, mask} (+ ball_lambertian_a/_b when rendered): input under light a
    (with the ball of that light), target under light b, same view. ``cross_only``: without the
    identity pairs (a -> a)."""
    return ShardDataset(
        shard_dir, split, "relight", shuffle=shuffle, repeat=repeat, seed=seed, buffer=buffer, cross_only=cross_only
    )


def eval_dataset(
    shard_dir: Path, split: str = "test", task: Literal["intrinsics", "relight"] = "relight"
) -> ShardDataset:
    """Evaluation: one pass, no shuffle, in shard order (with num_workers <= 1)."""
    return ShardDataset(shard_dir, split, task, shuffle=False, repeat=False)


def make_loader(dataset: ShardDataset, batch_size: int, num_workers: int = 0, drop_last: bool = False) -> DataLoader:
    """A DataLoader over a ShardDataset; batches are built inside each worker."""
    return DataLoader(
        dataset,
        batch_size=batch_size,
        num_workers=num_workers,
        drop_last=drop_last,
        pin_memory=torch.cuda.is_available(),
        persistent_workers=False,
    )
