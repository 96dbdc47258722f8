"""Render folder -> webdataset shards (the shard stage); the readers are pilight.data.shard_reader.

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
reader verifies them when it is created (pilight.data.shard_reader.verify_shards).  A tar cut at a member boundary
is still a valid tar with fewer samples: it trained on 2 of 4 samples with exit 0.  Cut inside a
member, it lost a sample's members and failed with a raw ``KeyError: 'meta.json'``.  Both now fail
naming the shard.
"""

from __future__ import annotations

import json
import os
import shutil
import sys
import tempfile
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import webdataset as wds
from tqdm import tqdm

from pilight import atomic
from pilight.atomic import sha256_file
from pilight.data import layout
from pilight.data.exr import ExrError, read_exr, write_exr
from pilight.data.pairs import make_pairs, write_pairs
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
