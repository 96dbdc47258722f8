"""Render a whole dataset: scenes x views x lights, resumable and byte-deterministic (bpy only).

One scene's views are rendered by pilight.render.views, here or on a Dask worker
(pilight.render.cluster); this module decides which scenes exist, checks what is already on disk, and
writes the manifest last. A view is complete when its `.done` marker holds the view's stamp: a hash of everything its files
are made from (the scene spec, the view index, the render params but the scene counts, Blender's
version). A rerun skips complete views and redoes the rest from an empty folder, so an interrupted
render ends with the same files as an uninterrupted one, and a rerun with other params never keeps
a view made with the old ones. Scene folders the params no longer ask for are removed. That is what
lets `dvc repro` resume a killed render: the stage's output is `persist: true` (dvc.yaml).

Verified by their bytes too (issue 36): the marker is JSON, the stamp and the sha256 of every file of the
view; a scene's `.done` holds the sha256 of its scene.json. Before any view is rendered, every marked
view is checked against its files (``verify_renders``): a view whose files no longer match (a flipped
byte, a truncated EXR, a file missing or added) is rendered again, and the stage says which and why. A
marker written before the hashes were recorded (only the stamp) is accepted once its files are all there
and every EXR decodes whole, and its hashes are recorded then. Before, the stamps hashed only the inputs:
a damaged EXR was skipped over and `dvc repro` recorded it in dvc.lock as the new truth.

The manifest is written only once every scene's `.done` matches its scene.json and every view is marked:
a Dask task retried after its worker died between a scene's sidecar and its marker once skipped that
scene, and the folder went to the shard stage without the marker (CI, 2026-12-07).
"""

from __future__ import annotations

import json
import shutil
import tempfile
import time
from pathlib import Path

import bpy
from tqdm import tqdm

from pilight import atomic
from pilight.data import layout
from pilight.params import BaseParams, RenderParams
from pilight.render.blender_log import blender_output_to
from pilight.render.scene import RenderError
from pilight.render.spec import SPLITS, scene_spec
from pilight.render.views import (
    TMP_PREFIX,
    bundled_hdri_dir,
    bundles_of,
    legacy_view_problem,
    read_view_marker,
    recorded_scene_hash,
    render_scene,
    scene_is_complete,
    scene_marker,
    view_files,
    view_is_complete,
    view_stamp,
    write_json,
    write_scene_marker,
    write_view_marker,
)


def verify_renders(root: Path, specs: list[dict], p: RenderParams, say=print) -> dict[str, int]:
    """Check every marked view (and scene.json) of ``specs`` against its bytes (module docstring): a view
    that no longer matches loses its marker, so it is rendered again, and ``say`` tells which file and why;
    a stamp-only marker is upgraded once its files are whole. Returns the counts, and the scenes touched
    under "scenes" (a Dask partition marker of theirs must go too)."""
    counts = {"views": 0, "damaged": 0, "upgraded": 0}
    touched: set[str] = set()
    for spec in specs:
        sid = spec["id"]
        for v in range(len(spec["views"])):
            vdir = layout.view_dir(root, sid, v)
            marker = read_view_marker(vdir / layout.DONE_MARKER)
            if marker is None or marker["stamp"] != view_stamp(spec, v, p):
                continue  # not complete (or made with other params): rendered again anyway
            counts["views"] += 1
            if "sha256" not in marker:
                problem = legacy_view_problem(vdir, spec, v, p)
                if problem is None:
                    write_view_marker(vdir, marker["stamp"])
                    counts["upgraded"] += 1
                    continue
            else:
                found, recorded = view_files(vdir), marker["sha256"]
                problem = next(
                    (
                        f"{vdir / n}: "
                        + (
                            "missing"
                            if n not in found
                            else "not written by the render"
                            if n not in recorded
                            else "its bytes differ from the sha256 in its .done marker"
                        )
                        for n in sorted(set(found) | set(recorded))
                        if found.get(n) != recorded.get(n)
                    ),
                    None,
                )
                if problem is None:
                    continue
            say(f"render: {problem}: view {sid} v{v:02d} is rendered again")
            (vdir / layout.DONE_MARKER).unlink()
            counts["damaged"] += 1
            touched.add(sid)
        sidecar, smark = root / sid / "scene.json", scene_marker(root, sid)
        if not sidecar.is_file():
            continue
        recorded = recorded_scene_hash(root, sid)
        if recorded is None:  # written before its hash was recorded: trusted once if it reads as this scene's
            try:
                ok = json.loads(sidecar.read_text(encoding="utf-8")).get("id") == sid
            except (OSError, ValueError, AttributeError):
                ok = False
            if ok:
                write_scene_marker(root, sid)
                continue
        elif recorded == atomic.sha256_file(sidecar):
            continue
        say(f"render: {sidecar}: its bytes differ from what the render wrote: written again")
        sidecar.unlink()
        smark.unlink(missing_ok=True)
        touched.add(sid)
    counts["scenes"] = len(touched)
    counts["touched"] = touched
    return counts


def remove_stale_scratch(root: Path) -> None:
    """Scratch folders of renders that died without cleaning up: a killed process or Dask worker cannot
    run its ``finally``, and what it left (partial EXRs) must not reach the dataset or its DVC hash."""
    for d in sorted(root.glob(f"{TMP_PREFIX}*")):
        shutil.rmtree(d, ignore_errors=True)


def remove_unasked(root: Path, specs: list[dict]) -> None:
    """Scene folders, and views within them, that the current params do not ask for (fewer scenes or
    views than the last run): a folder the params would not make must not reach the shards."""
    asked = {s["id"]: len(s["views"]) for s in specs}
    for d in sorted(root.iterdir()):
        if not d.is_dir() or d.name.startswith("."):
            continue
        if d.name not in asked:
            shutil.rmtree(d)
            continue
        for v in sorted(d.iterdir()):
            if v.is_dir() and v.name.startswith("v") and v.name[1:].isdigit() and int(v.name[1:]) >= asked[d.name]:
                shutil.rmtree(v)


def all_specs(p: RenderParams, base: BaseParams) -> list[dict]:
    counts = p.scenes.model_dump()
    return [scene_spec(p, base.seed, split, i) for split in SPLITS for i in range(counts[split])]


def render_dataset(
    p: RenderParams, base: BaseParams, root: Path, *, progress: bool = True, blender_log: Path | None = None
) -> dict:
    """Render all scenes into `root`; returns timing figures. Blender's own lines go to `blender_log`
    (appended; None = the terminal), the progress bar stays on the terminal."""
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    with blender_output_to(blender_log) as terminal:
        return _render_all(p, base, root, progress=progress, terminal=terminal, blender_log=blender_log)


def manifest_entry(spec: dict) -> dict:
    return {
        "id": spec["id"],
        "kind": spec["kind"],
        "split": spec["split"],
        "views": len(spec["views"]),
        "lights": len(spec["lights"][0]),
        "hdris": sorted({l["hdri"]["name"] for v in spec["lights"] for l in v if l["hdri"]}),
    }


def _render_all(
    p: RenderParams, base: BaseParams, root: Path, *, progress: bool, terminal, blender_log: Path | None = None
) -> dict:
    hdri_dir = Path(p.hdri.dir) if p.hdri.dir else bundled_hdri_dir()
    specs = all_specs(p, base)
    total = bundles_of(specs)
    bar = tqdm(total=total, desc="render (view, light) bundles", unit="bundle", disable=not progress, file=terminal)
    t0 = time.perf_counter()
    (root / "manifest.json").unlink(missing_ok=True)  # written last: its presence means the folder is complete
    remove_unasked(root, specs)
    checked = verify_renders(root, specs, p, say=lambda line: print(line, file=terminal, flush=True))
    if checked["upgraded"]:
        print(
            f"render: {checked['upgraded']} view(s) marked before file hashes were recorded: every file there, every "
            "EXR decoded whole; their hashes are recorded now",
            file=terminal,
        )
    if checked["touched"] and p.cluster.executor == "dask":  # a partition marker would skip the damaged views
        from pilight.render import cluster

        for part in cluster.partitions(specs, p.cluster.scenes_per_task):
            if any(s["id"] in checked["touched"] for s in part):
                cluster._marker(root, part).unlink(missing_ok=True)
    try:
        if p.cluster.executor == "dask":
            from pilight.render.cluster import render_on_dask

            render_on_dask(specs, p, root, hdri_dir, bar.update, blender_log)
        else:
            tmp_dir = Path(tempfile.mkdtemp(prefix=TMP_PREFIX, dir=root))
            try:
                for spec in specs:
                    render_scene(spec, p, root, hdri_dir, tmp_dir, bar.update)
            finally:
                shutil.rmtree(tmp_dir, ignore_errors=True)
    finally:
        bar.close()
    # The manifest says the folder is complete, so it is written only when every scene is: an executor
    # that skipped something (a retried task that trusted a half-written scene) fails loudly here.
    unfinished = [
        s["id"]
        for s in specs
        if not scene_is_complete(root, s["id"])
        or not all(view_is_complete(root, s, v, p) for v in range(len(s["views"])))
    ]
    if unfinished:
        raise RenderError(
            f"{len(unfinished)} scene(s) have no complete .done markers after the render ({', '.join(unfinished[:5])}"
            f"{', ...' if len(unfinished) > 5 else ''}); no manifest written: rerun the stage to finish them"
        )
    # before the manifest: left by a killed earlier run, or by Dask workers killed mid-task (their
    # partitions were rerun elsewhere)
    remove_stale_scratch(root)
    write_json(
        root / "manifest.json",
        {
            "blender_version": bpy.app.version_string,
            "resolution": p.resolution,
            "scenes": [manifest_entry(s) for s in specs],
        },
    )
    seconds = time.perf_counter() - t0
    return {"bundles": total, "seconds": seconds}
