"""One scene rendered: its views, each light of a view, the ball, the files and their markers (bpy only).

Per view, the first light's render also carries the view maps (AOVs + normal pass); later
lights render only what they need (beauty + diffuse passes). All main-scene renders of a view
run back to back, then all ball renders, so Cycles' persistent data is reused within each.
A view is complete when its `.done` marker holds the view's stamp: a hash of everything its files
are made from (the scene spec, the view index, the render params but the scene counts, Blender's
version), and the sha256 of every file of the view; a scene's `.done` holds the sha256 of its
scene.json. A view that is not complete is rendered again from an empty folder, so an interrupted
render ends with the same files as an uninterrupted one. The whole dataset, its resumption and its
byte checks are pilight.render.dataset's; a Dask worker renders scenes through here
(pilight.render.cluster), so neither of those imports the other's orchestration.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import bpy
import numpy as np

from pilight import atomic
from pilight.data import layout
from pilight.data.exr import read_render_passes, write_exr
from pilight.eval.grids import labelled_grid
from pilight.params import RenderParams
from pilight.pictures import srgb8_preview_lut
from pilight.render import passes as P
from pilight.render import scene as S


def bundled_hdri_dir() -> Path:
    return Path(bpy.utils.system_resource("DATAFILES", path="studiolights/world"))


def write_json(path: Path, obj) -> None:
    atomic.write_text(path, json.dumps(obj, indent=1, sort_keys=True))  # no final newline: sidecar bytes as ever


def write_preview(path: Path, tiles: list[np.ndarray]) -> None:
    """sRGB PNG strip for people (the only place sRGB is used in the render stage): the tiles side by
    side, no gaps; the ball, smaller, at the top of its column with black below."""
    strip = labelled_grid([[srgb8_preview_lut(t) for t in tiles]], None, gap=0, tight=True)
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


def read_view_marker(done: Path) -> dict | None:
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
    marker = read_view_marker(layout.view_dir(root, spec["id"], view) / layout.DONE_MARKER)
    return marker is not None and marker["stamp"] == view_stamp(spec, view, p)


def view_files(vdir: Path) -> dict[str, str]:
    """sha256 of every file of a view folder but its marker, by path relative to the folder."""
    return {
        f.relative_to(vdir).as_posix(): atomic.sha256_file(f)
        for f in sorted(vdir.rglob("*"))
        if f.is_file() and f.name != layout.DONE_MARKER
    }


def write_view_marker(vdir: Path, stamp: str) -> None:
    """The view's `.done`: its stamp and the sha256 of each of its files, written last."""
    atomic.write_text(
        vdir / layout.DONE_MARKER, json.dumps({"stamp": stamp, "sha256": view_files(vdir)}, sort_keys=True)
    )


def _expected_files(spec: dict, view: int, p: RenderParams) -> list[str]:
    names = [f"{m}.exr" for m in layout.VIEW_MAPS]
    light_maps = layout.LIGHT_MAPS + (("ball_lambertian",) if p.lambertian_ball else ())
    for li in range(len(spec["lights"][view])):
        names += [f"l{li:02d}/{m}.exr" for m in light_maps] + [f"l{li:02d}/preview.png"]
    return names


def legacy_view_problem(vdir: Path, spec: dict, view: int, p: RenderParams) -> str | None:
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


def recorded_scene_hash(root: Path, sid: str) -> str | None:
    """The sha256 of scene.json that the scene's `.done` records: None without a marker, "" when the
    marker cannot be read."""
    marker = scene_marker(root, sid)
    if not marker.is_file():
        return None
    try:
        return json.loads(marker.read_text(encoding="utf-8"))["sha256"]["scene.json"]
    except (OSError, ValueError, KeyError, TypeError):
        return ""


def scene_is_complete(root: Path, sid: str) -> bool:
    """The scene's marker holds the sha256 of the scene.json beside it. A worker killed between the two
    writes leaves the sidecar without its marker: that scene is not complete, whatever its views say."""
    sidecar, recorded = Path(root) / sid / "scene.json", recorded_scene_hash(root, sid)
    return bool(recorded) and sidecar.is_file() and recorded == atomic.sha256_file(sidecar)


def write_scene_marker(root: Path, sid: str) -> None:
    """The scene's `.done`: the sha256 of its scene.json (what shard reads beside the views)."""
    sidecar = Path(root) / sid / "scene.json"
    atomic.write_text(scene_marker(root, sid), json.dumps({"sha256": {"scene.json": atomic.sha256_file(sidecar)}}))


TMP_PREFIX = ".render_tmp_"  # a render's scratch folder inside the output root (same filesystem: renames are atomic)


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


def bundles_of(specs: list[dict]) -> int:
    """(view, light) bundles of these scenes: the unit of the render's progress."""
    return sum(len(v) for s in specs for v in s["lights"])


def render_scene(spec: dict, p: RenderParams, root: Path, hdri_dir: Path, tmp_dir: Path, on_bundles=None) -> int:
    """Render the views of one scene that are not complete, and its scene.json; returns the bundles
    rendered. ``on_bundles(n)`` is called as bundles finish (or are found complete)."""
    tick = on_bundles or (lambda n: None)
    sid = spec["id"]
    pending = [v for v in range(len(spec["views"])) if not view_is_complete(root, spec, v, p)]
    if not pending and scene_is_complete(root, sid):
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
