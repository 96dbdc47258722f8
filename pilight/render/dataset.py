"""Render a whole dataset: scenes x views x lights, resumable and byte-deterministic (bpy only).

Per view, the first light's render also carries the view maps (AOVs + normal pass); later
lights render only what they need (beauty + diffuse passes). All main-scene renders of a view
run back to back, then all ball renders, so Cycles' persistent data is reused within each.
A view is complete when its `.done` marker holds the view's stamp: a hash of everything its files
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
"""

from __future__ import annotations

import hashlib
import json
import shutil
import tempfile
import time
from pathlib import Path

import bpy
import numpy as np
from tqdm import tqdm

from pilight import atomic
from pilight.data import layout
from pilight.data.colour import linear_to_srgb
from pilight.data.exr import read_render_passes, write_exr
from pilight.eval.grids import labelled_grid
from pilight.params import BaseParams, RenderParams
from pilight.render import passes as P
from pilight.render import scene as S
from pilight.render.blender_log import blender_output_to
from pilight.render.spec import SPLITS, scene_spec


def bundled_hdri_dir() -> Path:
    return Path(bpy.utils.system_resource("DATAFILES", path="studiolights/world"))


def write_json(path: Path, obj) -> None:
    atomic.write_text(path, json.dumps(obj, indent=1, sort_keys=True))  # no final newline: sidecar bytes as ever


def _srgb8_exact(x: np.ndarray) -> np.ndarray:
    # +0.5 and truncation, not srgb_preview's round-half-even: the bytes of every preview.png so far.
    return (linear_to_srgb(np.clip(x, 0.0, 1.0)) * 255.0 + 0.5).astype(np.uint8)


# A 16-bit lookup table: 4x faster than the power law per preview, within one code value of it.
_SRGB_LUT = _srgb8_exact(np.linspace(0.0, 1.0, 65536))


def _srgb8(x: np.ndarray) -> np.ndarray:
    return _SRGB_LUT[(np.clip(x, 0.0, 1.0) * 65535.0 + 0.5).astype(np.uint16)]


def write_preview(path: Path, tiles: list[np.ndarray]) -> None:
    """sRGB PNG strip for people (the only place sRGB is used in the render stage): the tiles side by
    side, no gaps; the ball, smaller, at the top of its column with black below."""
    strip = labelled_grid([[_srgb8(t) for t in tiles]], None, gap=0, tight=True)
    # compress_level 1: a quarter of the default's encode time for files about 7% larger.
    atomic.write_png(path, strip, compress_level=1)


def render_passes(scene, tmp_dir: Path) -> dict[str, np.ndarray]:
    """Render ``scene`` as it is set up now; its passes as {name: H x W x C float32} (a temporary EXR in tmp_dir)."""
    out = tmp_dir / f"{scene.name}.exr"
    scene.render.filepath = str(out)
    bpy.ops.render.render(write_still=True, scene=scene.name)
    passes = read_render_passes(out)
    out.unlink()
    return passes


def view_stamp(spec: dict, view: int, p: RenderParams) -> str:
    """sha256 of what one view's files are made from (module docstring); the `.done` marker's content."""
    # scenes: the counts decide which scenes exist, not how one looks; cluster: where it is rendered
    made_from = {
        "spec": spec,
        "view": view,
        "render": p.model_dump(mode="json", exclude={"scenes", "cluster"}),
        "blender": bpy.app.version_string,
    }
    return hashlib.sha256(json.dumps(made_from, sort_keys=True).encode()).hexdigest()


def _read_marker(done: Path) -> dict | None:
    """A view's `.done`: {"stamp", "sha256"} (JSON), {"stamp"} for a marker holding only the stamp (written
    before the hashes were recorded), None when missing or neither."""
    try:
        text = done.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError):
        return None
    if len(text) == 64 and all(c in "0123456789abcdef" for c in text):
        return {"stamp": text}
    try:
        marker = json.loads(text)
    except ValueError:
        return None
    ok = isinstance(marker, dict) and isinstance(marker.get("stamp"), str) and isinstance(marker.get("sha256"), dict)
    return marker if ok else None


def view_is_complete(root: Path, spec: dict, view: int, p: RenderParams) -> bool:
    """The view's marker holds its stamp (its bytes are checked once per run, by ``verify_renders``)."""
    marker = _read_marker(layout.view_dir(root, spec["id"], view) / layout.DONE_MARKER)
    return marker is not None and marker["stamp"] == view_stamp(spec, view, p)


def _view_files(vdir: Path) -> dict[str, str]:
    """sha256 of every file of a view folder but its marker, by path relative to the folder."""
    return {
        f.relative_to(vdir).as_posix(): atomic.sha256_file(f)
        for f in sorted(vdir.rglob("*"))
        if f.is_file() and f.name != layout.DONE_MARKER
    }


def write_view_marker(vdir: Path, stamp: str) -> None:
    """The view's `.done`: its stamp and the sha256 of each of its files, written last."""
    atomic.write_text(
        vdir / layout.DONE_MARKER, json.dumps({"stamp": stamp, "sha256": _view_files(vdir)}, sort_keys=True)
    )


def _expected_files(spec: dict, view: int, p: RenderParams) -> list[str]:
    names = [f"{m}.exr" for m in layout.VIEW_MAPS]
    light_maps = layout.LIGHT_MAPS + (("ball_lambertian",) if p.lambertian_ball else ())
    for li in range(len(spec["lights"][view])):
        names += [f"l{li:02d}/{m}.exr" for m in light_maps] + [f"l{li:02d}/preview.png"]
    return names


def _legacy_view_problem(vdir: Path, spec: dict, view: int, p: RenderParams) -> str | None:
    """What is wrong with a view marked before hashes were recorded: a file missing, or an EXR that does not
    decode whole (a truncation); None when it can be trusted once and its hashes recorded."""
    from pilight.data.exr import ExrError, read_exr

    for name in _expected_files(spec, view, p):
        f = vdir / name
        if not f.is_file():
            return f"{f}: missing"
        if name.endswith(".exr"):
            try:
                read_exr(f)
            except ExrError as exc:
                return str(exc)
    return None


def scene_marker(root: Path, sid: str) -> Path:
    return Path(root) / sid / layout.DONE_MARKER


def write_scene_marker(root: Path, sid: str) -> None:
    """The scene's `.done`: the sha256 of its scene.json (what shard reads beside the views)."""
    sidecar = Path(root) / sid / "scene.json"
    atomic.write_text(scene_marker(root, sid), json.dumps({"sha256": {"scene.json": atomic.sha256_file(sidecar)}}))


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
            marker = _read_marker(vdir / layout.DONE_MARKER)
            if marker is None or marker["stamp"] != view_stamp(spec, v, p):
                continue  # not complete (or made with other params): rendered again anyway
            counts["views"] += 1
            if "sha256" not in marker:
                problem = _legacy_view_problem(vdir, spec, v, p)
                if problem is None:
                    write_view_marker(vdir, marker["stamp"])
                    counts["upgraded"] += 1
                    continue
            else:
                found, recorded = _view_files(vdir), marker["sha256"]
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
        try:
            recorded = (
                json.loads(smark.read_text(encoding="utf-8"))["sha256"]["scene.json"] if smark.is_file() else None
            )
        except (OSError, ValueError, KeyError, TypeError):
            recorded = ""
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


TMP_PREFIX = ".render_tmp_"  # a render's scratch folder inside the output root (same filesystem: renames are atomic)


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


def render_view(
    handles: dict,
    spec: dict,
    view: int,
    root: Path,
    tmp_dir: Path,
    *,
    lambertian: bool,
    verify: bool = False,
    on_bundle=None,
    stamp: str = "",
) -> dict:
    """Render every light of one view into an emptied view folder; return the raw passes when `verify`."""
    scene, ball_scene = handles["scene"], handles["ball_scene"]
    shutil.rmtree(layout.view_dir(root, spec["id"], view), ignore_errors=True)  # nothing of an older view survives
    S.set_view(handles, spec["views"][view])
    rot = np.array(S.camera_rotation(handles))
    sid, raw = spec["id"], {}
    maps, lit = None, {}
    for li, light in enumerate(spec["lights"][view]):
        S.set_lights(light)
        S.set_world(handles["world"], light)
        P.configure(scene.view_layers[0], diffuse=True, view_maps=li == 0, verify=verify)
        passes = render_passes(scene, tmp_dir)
        if li == 0:
            maps = P.view_maps(passes, rot)
            for name, arr in maps.items():
                write_exr(layout.map_path(root, sid, view, name), arr, half=name not in layout.FLOAT32_MAPS)
        out = P.decompose(passes, maps["albedo"], where=f"{sid} view {view} light {li}")
        for name, arr in out.items():
            write_exr(layout.map_path(root, sid, view, name, li), arr, half=False)
        lit[li] = out
        if verify:
            raw[li] = passes
        if on_bundle:
            on_bundle()
    P.configure_ball(ball_scene.view_layers[0], lambertian=lambertian)
    for li, light in enumerate(spec["lights"][view]):
        S.set_lights(light)
        S.set_world(handles["world"], light)
        balls = P.ball_maps(render_passes(ball_scene, tmp_dir), lambertian=lambertian)
        for name, arr in balls.items():
            write_exr(layout.map_path(root, sid, view, name, li), arr, half=True)
        tiles = [lit[li]["image"], maps["albedo"], lit[li]["diffuse"], lit[li]["specular"], balls["ball"]]
        write_preview(layout.light_dir(root, sid, view, li) / "preview.png", tiles)
    write_view_marker(layout.view_dir(root, sid, view), stamp)
    return raw


def scene_sidecar(spec: dict, handles: dict, p: RenderParams) -> dict:
    cams = []
    for v, view in enumerate(spec["views"]):
        S.set_view(handles, view)
        cams.append({"view": v, **S.camera_json(handles["camera"], handles["scene"])})
    return {
        "id": spec["id"],
        "split": spec["split"],
        "kind": spec["kind"],
        "seed": spec["seed"],
        "blender_version": bpy.app.version_string,
        "resolution": p.resolution,
        "spec": spec,
        "materials": handles["materials"],
        "cameras": cams,
        "lights": [[{"light": li, **l} for li, l in enumerate(view_lights)] for view_lights in spec["lights"]],
    }


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


def bundles_of(specs: list[dict]) -> int:
    """(view, light) bundles of these scenes: the unit of the render's progress."""
    return sum(len(v) for s in specs for v in s["lights"])


def render_scene(spec: dict, p: RenderParams, root: Path, hdri_dir: Path, tmp_dir: Path, on_bundles=None) -> int:
    """Render the views of one scene that are not complete, and its scene.json; returns the bundles
    rendered. ``on_bundles(n)`` is called as bundles finish (or are found complete)."""
    tick = on_bundles or (lambda n: None)
    sid = spec["id"]
    pending = [v for v in range(len(spec["views"])) if not view_is_complete(root, spec, v, p)]
    if not pending and (root / sid / "scene.json").is_file():
        tick(bundles_of([spec]))
        return 0
    handles = S.build(spec, p, hdri_dir)
    rendered = 0
    for v in range(len(spec["views"])):
        if v in pending:
            render_view(
                handles,
                spec,
                v,
                root,
                tmp_dir,
                lambertian=p.lambertian_ball,
                on_bundle=lambda: tick(1),
                stamp=view_stamp(spec, v, p),
            )
            rendered += len(spec["lights"][v])
        else:
            tick(len(spec["lights"][v]))
    write_json(root / sid / "scene.json", scene_sidecar(spec, handles, p))
    write_scene_marker(root, sid)
    return rendered


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
