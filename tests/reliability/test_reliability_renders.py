"""Issue 36: renders are verified by their bytes, not only by the stamp of their inputs. A view whose files
no longer match what the render wrote is rendered again, and the stage says so; the dataset ends
byte-identical to an untouched one. Before, a flipped byte or a truncated EXR in data/renders was skipped
over by the render stage, and `dvc repro` recorded the damage in dvc.lock."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from fixtures.render_stage import run_stage, tree_digest, write_params

pytestmark = pytest.mark.slow  # two tiny Blender renders (8 and 4 bundles at 32^2)


def _flip_a_pixel_byte(exr: Path) -> None:
    raw = bytearray(exr.read_bytes())
    raw[-40] ^= 0x01  # inside the last scanline block's compressed pixels: the header still parses
    exr.write_bytes(bytes(raw))


def _stamp(done: Path) -> str:
    text = done.read_text()
    return json.loads(text)["stamp"] if text.startswith("{") else text  # JSON now; the stamp alone before


def test_damaged_views_are_rendered_again_and_said(tmp_path):
    params = write_params(tmp_path / "params.yaml", scenes={"train": 2, "val": 0, "test": 0}, views_per_scene=2)
    out = tmp_path / "renders"
    r = run_stage(params, out)
    assert r.returncode == 0, r.stderr
    reference = tree_digest(out)
    a, b = out / "train_0000", out / "train_0001"

    _flip_a_pixel_byte(a / "v00" / "l01" / "image.exr")  # a flipped byte under a current marker
    marker_stamp = _stamp(a / "v01" / ".done")
    (a / "v01" / ".done").write_text(marker_stamp)
    untouched = {p: p.stat().st_mtime_ns for p in (a / "v01").rglob("*.exr")}  # stamp-only marker, intact files
    legacy = b / "v00" / ".done"
    legacy.write_text(_stamp(legacy))  # stamp-only marker ...
    exr = b / "v00" / "l00" / "diffuse.exr"
    exr.write_bytes(exr.read_bytes()[: exr.stat().st_size // 2])  # ... over a truncated EXR
    sidecar = b / "scene.json"
    sidecar.write_text(sidecar.read_text().replace('"kind"', '"kind" ', 1))

    r = run_stage(params, out)
    assert r.returncode == 0, r.stderr
    said = r.stdout + r.stderr
    assert f"{a / 'v00' / 'l01' / 'image.exr'}: its bytes differ from the sha256 in its .done marker" in said, said
    assert "view train_0000 v00 is rendered again" in said
    assert f"{exr}: unreadable EXR" in said and "view train_0001 v00 is rendered again" in said, said
    assert f"{sidecar}: its bytes differ from what the render wrote: written again" in said
    assert "1 view(s) marked before file hashes were recorded" in said, said
    assert "train_0000 v01 is rendered again" not in said
    assert all(p.stat().st_mtime_ns == t for p, t in untouched.items()), "an intact view was rendered again"
    assert json.loads((a / "v01" / ".done").read_text())["stamp"] == marker_stamp  # upgraded in place
    assert tree_digest(out) == reference  # every byte back as rendered, the markers included


def test_a_file_added_to_or_removed_from_a_view_is_found(tmp_path):
    params = write_params(tmp_path / "params.yaml", scenes={"train": 1, "val": 0, "test": 0}, views_per_scene=1)
    out = tmp_path / "renders"
    assert run_stage(params, out).returncode == 0
    reference = tree_digest(out)
    view = out / "train_0000" / "v00"
    (view / "l00" / "ball.exr").unlink()
    (view / "notes.txt").write_text("not the render's")
    r = run_stage(params, out)
    assert r.returncode == 0, r.stderr
    assert f"{view / 'l00' / 'ball.exr'}: missing: view train_0000 v00 is rendered again" in r.stdout + r.stderr
    assert tree_digest(out) == reference
    # the marker lists every other file of the view
    files = {f.relative_to(view).as_posix() for f in view.rglob("*") if f.is_file() and f.name != ".done"}
    assert set(json.loads((view / ".done").read_text())["sha256"]) == files
