"""Render folder -> webdataset shards, and the PyTorch readers for training and evaluation.

Output (one DVC out, written to a temporary sibling and renamed into place):
```
<shard_dir>/index.json                 schema version, render info, per split: shards, counts, sizes
<shard_dir>/<split>/<split>-000000.tar one sample per (scene, view, light); see pilight.data.schema
<shard_dir>/splits/<split>.txt         scene ids (pilight.data.splits)
<shard_dir>/pairs/<split>.tsv          relighting pairs (pilight.data.pairs)
```
Same renders + params + seed -> the same bytes: fixed tar mtime/owner/mode, sorted members,
samples in (scene, view, light) order, deterministic EXR and JSON encoders.

index.json records, per split, every shard's sample count and sha256 (``shard_checks``), and every
reader verifies them when it is created (:func:`verify_shards`).  A tar cut at a member boundary
is still a valid tar with fewer samples: it trained on 2 of 4 samples with exit 0.  Cut inside a
member, it lost a sample's members and failed with a raw ``KeyError: 'meta.json'``.  Both now fail
naming the shard.
"""

from __future__ import annotations

import json
import os
import random
import shutil
import sys
import tarfile
import tempfile
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
import webdataset as wds
from torch.utils.data import DataLoader, IterableDataset
from tqdm import tqdm

from pilight import atomic
from pilight.atomic import sha256_file
from pilight.data import layout
from pilight.data.exr import ExrError, read_exr, read_exr_bytes, write_exr
from pilight.data.pairs import make_pairs, read_pairs, write_pairs
from pilight.data.schema import (
    OPTIONAL_MAPS,
    SCHEMA_VERSION,
    SPECS,
    SPLITS,
    DataError,
    SampleError,
    sample_key,
    validate_sample,
)
from pilight.data.shard_params import ShardParams
from pilight.data.splits import check_hdri_holdout, check_splits, hdri_summary, write_splits

TAR_MTIME = 0  # fixed member metadata: the tar bytes depend on the samples only
TAR_OWNER = "pilight"
MANIFEST_ID_FIELDS = ("id", "kind", "split", "views", "lights")  # the rest is opaque, copied to meta
INTRINSICS = ("albedo", "normal", "roughness", "metallic", "mask")


class RenderFolderError(DataError):
    """The render folder is incomplete or its manifest / scene.json is malformed."""


# ---------------------------------------------------------------------------------- writer
def write_shards(
    renders: Path,
    out: Path,
    params: ShardParams,
    *,
    seed: int,
    heldout_hdris: Iterable[str] = (),
    progress: bool = False,
) -> dict[str, Any]:
    """Validate every sample under `renders` and write the shard folder `out`; returns index.json's
    content. `heldout_hdris` (render.hdri.test_holdout) must not light any train/val scene.
    On any error nothing is left under `out` (an earlier complete `out` is kept)."""
    renders, out = Path(renders), Path(out)
    manifest = _load_json(renders / "manifest.json")
    scenes = manifest.get("scenes")
    if not isinstance(scenes, list) or not all(isinstance(s, dict) for s in scenes):
        raise RenderFolderError(f"{renders / 'manifest.json'}: 'scenes' must be a list of objects")
    splits = check_splits(scenes, where=str(renders / "manifest.json"))
    check_hdri_holdout(scenes, heldout_hdris, where=str(renders / "manifest.json"))
    tmp = None
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp-", dir=out.parent))
        index = _write_all(renders, tmp, manifest, splits, params, seed, progress)
        write_splits(tmp, splits, hdri_summary(scenes))
        (tmp / "index.json").write_text(json.dumps(index, indent=1, sort_keys=True) + "\n")
        os.chmod(tmp, atomic.dir_mode())  # mkdtemp makes it 0700 whatever the umask
        _swap_into_place(tmp, out)
    except BaseException as exc:
        atomic.abandon_folder(exc, tmp, out)
    return index


def _write_all(renders, tmp, manifest, splits, params, seed, progress) -> dict[str, Any]:
    entries = {s["id"]: s for s in manifest["scenes"]}
    for e in entries.values():
        for f in ("views", "lights"):
            if not isinstance(e.get(f), int) or e[f] < 1:
                raise RenderFolderError(f"{renders / 'manifest.json'}: scene {e['id']!r}: {f!r} must be an int >= 1")
    render_info = {k: v for k, v in manifest.items() if k != "scenes"}
    total = sum(e["views"] * e["lights"] for e in entries.values())
    sizes: dict[str, tuple] = {}  # dataset-wide sizes, so batches collate
    index: dict[str, Any] = {"schema_version": SCHEMA_VERSION, "render": render_info, "splits": {}}
    with (
        tqdm(total=total, desc="shard", unit="sample", disable=not progress) as bar,
        tempfile.TemporaryDirectory() as scratch,
    ):
        for split in SPLITS:
            views = [(sid, v, entries[sid]["lights"]) for sid in splits[split] for v in range(entries[sid]["views"])]
            write_pairs(
                tmp / "pairs" / f"{split}.tsv",
                make_pairs(views, seed=seed, pairs_per_view=params.pairs_per_view, identity=params.identity_pairs),
            )
            shards: list[str] = []
            checks: dict[str, dict[str, Any]] = {}
            if views:
                (tmp / split).mkdir()

                def finished(f: str) -> None:  # called as each shard closes, while writer.count is its count
                    shards.append(Path(f).name)  # noqa: B023 (called within this iteration)
                    checks[Path(f).name] = {"samples": writer.count, "sha256": sha256_file(Path(f))}  # noqa: B023 (called within this iteration)

                writer = wds.ShardWriter(
                    str(tmp / split / f"{split}-%06d.tar"),
                    maxcount=sys.maxsize,
                    maxsize=float("inf"),
                    post=finished,
                    verbose=0,
                    encoder=False,
                    mtime=TAR_MTIME,
                    user=TAR_OWNER,
                    group=TAR_OWNER,
                    mode=0o444,
                )
                with writer:
                    for sid in splits[split]:
                        for group in _scene_groups(renders, entries[sid], render_info, sizes, Path(scratch)):
                            _write_view(writer, group, params)
                            bar.update(len(group))
            index["splits"][split] = {
                "scenes": len(splits[split]),
                "views": len(views),
                "samples": sum(n for _, _, n in views),
                "shards": shards,
                "shard_checks": checks,
            }
    index["sizes"] = {k: list(v) for k, v in sorted(sizes.items())}
    return index


def _write_view(writer: wds.ShardWriter, group: list[dict], params: ShardParams) -> None:
    # Roll over only between views: stage 2 pairs lights of one view while streaming a shard.
    nbytes = sum(len(v) for s in group for k, v in s.items() if k != "__key__")
    if writer.count and (writer.count + len(group) > params.maxcount or writer.size + nbytes > params.maxsize):
        writer.next_stream()
    for sample in group:
        writer.write(sample)


def _scene_groups(renders: Path, entry: dict, render_info: dict, sizes: dict, scratch: Path) -> Iterator[list[dict]]:
    """Per view: the encoded samples (one per light), after validating each."""
    sid = entry["id"]
    scene_json = renders / sid / "scene.json"
    info = _load_json(scene_json)
    extra = {k: v for k, v in entry.items() if k not in MANIFEST_ID_FIELDS}
    for view in range(entry["views"]):
        vdir = layout.view_dir(renders, sid, view)
        if not (vdir / layout.DONE_MARKER).is_file():
            raise RenderFolderError(
                f"sample {sample_key(sid, view, 0)}: {vdir / layout.DONE_MARKER} missing: "
                "view not completely rendered (rerun the render stage)"
            )
        camera = _entry_for(info.get("cameras"), "view", view, f"{scene_json}: 'cameras'")
        lights = info.get("lights")
        if isinstance(lights, list) and lights and isinstance(lights[0], list):
            lights = lights[view] if view < len(lights) else None  # lights sampled per view
        group = []
        for light in range(entry["lights"]):
            key = sample_key(sid, view, light)
            files = {
                name: layout.map_path(renders, sid, view, name, None if name in layout.VIEW_MAPS else light)
                for name in SPECS
            }
            files = {n: p for n, p in files.items() if n not in OPTIONAL_MAPS or p.is_file()}
            sample: dict[str, Any] = {"__key__": key}
            for name, path in files.items():
                try:
                    sample[name] = read_exr(path)
                except ExrError as exc:
                    raise SampleError(f"sample {key}: {name!r}: {exc}") from None
            sample["meta"] = {
                "scene": sid,
                "kind": entry.get("kind"),
                "split": entry["split"],
                "view": view,
                "light": light,
                "camera": camera,
                "light_params": _entry_for(lights, "light", light, f"{scene_json}: 'lights'"),
                "manifest_extra": extra,
                "render": render_info,
            }
            files["meta"] = scene_json
            validate_sample(sample, files)
            _check_sizes(sample, files, sizes)
            group.append(_encode(sample, scratch))
        yield group


def _check_sizes(sample: dict, files: dict, sizes: dict) -> None:
    for name in ("image", "ball", "ball_lambertian"):
        if name not in sample:
            continue
        hw = sample[name].shape[:2]
        ref = sizes.setdefault(name, hw)
        if hw != ref:
            raise SampleError(
                f"sample {sample['__key__']}: {name!r} ({files[name]}): size {hw} differs from "
                f"the first sample's {ref}; all samples must share one size"
            )


def _encode(sample: dict, scratch: Path) -> dict[str, Any]:
    enc: dict[str, Any] = {"__key__": sample["__key__"]}
    tmp = scratch / "map.exr"
    for name in SPECS:
        if name in sample:
            write_exr(tmp, sample[name], half=True)  # the EXR header has no time or host
            enc[f"{name}.exr"] = tmp.read_bytes()
    enc["meta.json"] = json.dumps(sample["meta"], sort_keys=True, separators=(",", ":"), allow_nan=False).encode()
    return enc


def _entry_for(items: Any, index_field: str, index: int, where: str) -> dict:
    """The one object in `items` whose `index_field` equals `index` (a camera or light entry)."""
    if not isinstance(items, list):
        raise RenderFolderError(f"{where}: want a list of objects with {index_field!r}")
    found = [it for it in items if isinstance(it, dict) and it.get(index_field) == index]
    if len(found) != 1:
        raise RenderFolderError(f"{where}: {len(found)} entries with {index_field} = {index}, want 1")
    return found[0]


def _load_json(path: Path) -> dict:
    try:
        data = json.loads(Path(path).read_text())
    except FileNotFoundError:
        raise RenderFolderError(f"{path}: file not found (has the render stage run?)") from None
    except (OSError, ValueError) as exc:
        raise RenderFolderError(f"{path}: unreadable JSON ({exc})") from None
    if not isinstance(data, dict):
        raise RenderFolderError(f"{path}: want a JSON object")
    return data


def _swap_into_place(tmp: Path, out: Path) -> None:
    if not out.exists():
        os.replace(tmp, out)
        return
    old = out.with_name(f".{out.name}.old-{os.getpid()}")
    os.replace(out, old)
    os.replace(tmp, out)
    shutil.rmtree(old)


# ---------------------------------------------------------------------------------- readers
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
            out.update({k: _tensor(item, k) for k in ("image", *INTRINSICS)})
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
        out.update({k: _tensor(sb, k) for k in INTRINSICS})
        return out


# Members every sample of a task needs; one lost to a cut tar must be named, not a KeyError later.
_REQUIRED = {
    "intrinsics": ("meta.json", "image.exr", *(f"{k}.exr" for k in INTRINSICS)),
    "relight": ("meta.json", "image.exr", "ball.exr", "diffuse.exr", "specular.exr", *(f"{k}.exr" for k in INTRINSICS)),
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
