"""The render stage as users run it: determinism, resume after a kill, bad input, user assets."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from fixtures.render_stage import ROOT, run_stage, stage_args, tree_digest, write_params
from fixtures.stage_scripts import stage_env

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    d = tmp_path_factory.mktemp("reference")
    params = write_params(d / "params.yaml")
    r = run_stage(params, d / "renders")
    assert r.returncode == 0, r.stderr
    return params, d / "renders"


def test_same_seed_same_bytes(reference, tmp_path):
    params, first = reference
    r = run_stage(params, tmp_path / "again")
    assert r.returncode == 0, r.stderr
    a, b = tree_digest(first), tree_digest(tmp_path / "again")
    assert a == b
    assert any(k.endswith("image.exr") for k in a) and "manifest.json" in a


def test_held_out_hdris_only_in_test(reference):
    import json

    manifest = json.loads((reference[1] / "manifest.json").read_text())
    holdout = {"courtyard", "sunset"}
    for scene in manifest["scenes"]:
        if scene["split"] != "test":
            assert not holdout & set(scene["hdris"]), scene


def test_killed_render_resumes_to_identical_files(reference, tmp_path):
    params, first = reference
    out = tmp_path / "renders"
    proc = subprocess.Popen(
        stage_args(params, out),
        cwd=ROOT,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
        env=stage_env(),
    )
    deadline = time.time() + 300
    while time.time() < deadline and not list(out.rglob(".done")):
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    assert not (out / "manifest.json").exists(), "killed before the end: no manifest"
    assert list(out.glob(".render_tmp_*")), "the killed render left its scratch folder (what the rerun must clear)"
    r = run_stage(params, out)
    assert r.returncode == 0, r.stderr
    assert tree_digest(out) == tree_digest(first)
    assert not list(out.glob(".render_tmp_*")), "a dead run's scratch folder would reach the dataset's hash"


def _specs_and_params(params_file: Path):
    from pilight.params import BaseParams, RenderParams, read_params
    from pilight.render.dataset import all_specs

    raw = read_params(params_file)
    p, base = RenderParams.model_validate(raw["render"]), BaseParams.model_validate(raw["base"])
    return all_specs(p, base), p


def test_scene_whose_marker_was_not_written_is_finished_not_skipped(reference, tmp_path):
    """A worker killed between a scene's scene.json and its .done (CI saw it: a Dask task retried on a
    restarted worker): every view is complete and the sidecar is there, yet the scene is not. Its rerun
    writes the marker, and the folder equals the uninterrupted render."""
    import shutil

    pytest.importorskip("bpy")
    from pilight.render import views

    params, first = reference
    specs, p = _specs_and_params(params)
    out = tmp_path / "renders"
    shutil.copytree(first, out)
    (out / "manifest.json").unlink()
    (out / "train_0000" / ".done").unlink()
    spec = next(s for s in specs if s["id"] == "train_0000")
    assert not views.scene_is_complete(out, "train_0000")
    rendered = views.render_scene(spec, p, out, views.bundled_hdri_dir(), tmp_path)
    assert rendered == 0, "its views were complete: nothing is rendered again"
    assert views.scene_is_complete(out, "train_0000")
    expected = {k: v for k, v in tree_digest(first).items() if k != "manifest.json"}
    assert tree_digest(out) == expected


def test_no_manifest_while_a_scene_is_unfinished(reference, tmp_path, monkeypatch):
    """The manifest means the folder is complete: if the executor leaves a view unmarked, the stage fails
    naming the scene and writes no manifest."""
    import shutil

    pytest.importorskip("bpy")
    from pilight.params import BaseParams, RenderParams, read_params
    from pilight.render import dataset
    from pilight.render.scene import RenderError

    params, first = reference
    raw = read_params(params)
    out = tmp_path / "renders"
    shutil.copytree(first, out)
    (out / "test_0000" / "v00" / ".done").unlink()
    monkeypatch.setattr(dataset, "render_scene", lambda *a, **k: 0)  # an executor that renders nothing
    with pytest.raises(RenderError, match=r"1 scene\(s\) have no complete \.done markers.*test_0000"):
        dataset.render_dataset(
            RenderParams.model_validate(raw["render"]), BaseParams.model_validate(raw["base"]), out, progress=False
        )
    assert not (out / "manifest.json").exists()


def test_rerun_with_other_params_keeps_no_view_of_the_old_ones(reference, tmp_path):
    """Into last run's folder (as `dvc repro` with persist leaves it), with fewer scenes and other
    samples: the result is byte-identical to a clean render with the new params, and the rendering
    of views whose params did not change is skipped."""
    import shutil

    params, first = reference
    out = tmp_path / "renders"
    shutil.copytree(first, out)
    new = write_params(
        tmp_path / "new.yaml",
        scenes={"train": 1, "val": 0, "test": 1},
        cycles={"samples": 4, "adaptive_min_samples": 2},
    )
    assert run_stage(new, out).returncode == 0
    clean = tmp_path / "clean"
    assert run_stage(new, clean).returncode == 0
    assert tree_digest(out) == tree_digest(clean)
    assert not (out / "train_0001").exists()
    log = tmp_path / "renders.blender.log"
    saved = log.read_text().count("Saved:")
    again = run_stage(new, out)  # nothing changed: every view is skipped, Blender saves nothing
    assert again.returncode == 0 and tree_digest(out) == tree_digest(clean)
    assert log.read_text().count("Saved:") == saved


@pytest.mark.parametrize(
    "override, needle",
    [
        ({"resolution": 100}, "render.resolution = 100"),
        ({"scenes": {"train": -1, "val": 0, "test": 1}}, "render.scenes.train = -1"),
        ({"hdri": {"names": ["forest", "mars"], "test_holdout": ["forest"]}}, "mars"),
        ({"light": {"hdri_probability": 1.5}}, "render.light.hdri_probability = 1.5"),
        ({"assets": ["/nonexistent/chair.glb"]}, "/nonexistent/chair.glb"),
        ({"assets": [str(ROOT / "pyproject.toml")]}, "unsupported type"),
    ],
)
def test_bad_params_fail_before_blender(tmp_path, override, needle):
    r = run_stage(write_params(tmp_path / "p.yaml", **override), tmp_path / "out")
    assert r.returncode == 2
    assert needle in r.stderr, r.stderr
    assert not (tmp_path / "out").exists(), "nothing written for bad params"


def test_asset_without_mesh_is_an_error(tmp_path):
    empty = tmp_path / "empty.obj"
    empty.write_text("# an OBJ with no geometry\n")
    r = run_stage(write_params(tmp_path / "p.yaml", assets=[str(empty)], assets_only=True), tmp_path / "out")
    assert r.returncode == 1 and "contains no mesh" in r.stderr and str(empty) in r.stderr, r.stderr
    assert not (tmp_path / "out" / "manifest.json").exists()


def test_unreadable_hdri_is_an_error(tmp_path):
    hdris = tmp_path / "hdris"
    hdris.mkdir()
    (hdris / "good.exr").write_bytes(b"not an exr at all" * 10)
    (hdris / "bad.exr").write_bytes(b"\x76\x2f\x31\x01 truncated")
    r = run_stage(
        write_params(
            tmp_path / "p.yaml",
            hdri={"dir": str(hdris), "names": ["good", "bad"], "test_holdout": ["bad"]},
            light={"hdri_probability": 1.0},
        ),
        tmp_path / "out",
    )
    assert r.returncode == 1 and "unreadable" in r.stderr and str(hdris) in r.stderr, r.stderr


EXPORT_ASSET = """
import bpy, sys
bpy.ops.wm.read_factory_settings(use_empty=True)
bpy.ops.mesh.primitive_cube_add(size=1.0)
mat = bpy.data.materials.new("paint")
bsdf = next(n for n in mat.node_tree.nodes if n.type == "BSDF_PRINCIPLED")
bsdf.inputs["Base Color"].default_value = (0.2, 0.6, 0.1, 1.0)
bsdf.inputs["Roughness"].default_value = 0.3
bpy.context.object.data.materials.append(mat)
out = sys.argv[-1]
if out.endswith(".glb"):
    bpy.ops.export_scene.gltf(filepath=out, export_format="GLB")
else:
    # A registered text block would run on file open if auto-execution were on.
    txt = bpy.data.texts.new("evil.py")
    txt.write("open(%r, 'w').write('ran')" % (out + ".ran",))
    txt.use_module = True
    bpy.ops.wm.save_as_mainfile(filepath=out)
"""


@pytest.mark.parametrize("suffix", [".glb", ".blend"])
def test_user_asset_is_rendered_with_its_material(tmp_path, suffix):
    import json

    import numpy as np

    from pilight.data.exr import read_exr

    asset = tmp_path / f"cube{suffix}"
    r = subprocess.run([sys.executable, "-c", EXPORT_ASSET, str(asset)], capture_output=True, text=True, timeout=300)
    assert asset.is_file(), r.stderr
    r = run_stage(
        write_params(
            tmp_path / "p.yaml",
            assets=[str(asset)],
            assets_only=True,
            scenes={"train": 1, "val": 0, "test": 0},
            resolution=48,
        ),
        tmp_path / "out",
    )
    assert r.returncode == 0, r.stderr
    assert not Path(str(asset) + ".ran").exists(), "the .blend's script must not run"
    view = tmp_path / "out" / "train_0000" / "v00"
    mask = read_exr(view / "mask.exr")[..., 0] > 0.5
    # The scene may also have a Principled ground plane: count the pixels carrying the cube's values.
    albedo, rough = read_exr(view / "albedo.exr")[mask], read_exr(view / "roughness.exr")[mask][:, 0]
    cube = np.abs(albedo - [0.2, 0.6, 0.1]).max(axis=1) < 2e-3
    assert cube.sum() > 20, "the asset is visible, Principled, with its own base colour"
    np.testing.assert_allclose(rough[cube], 0.3, atol=2e-3)
    assert json.loads((view.parent / "scene.json").read_text())["spec"]["assets"][0]["asset"] == str(asset)


# --- render.cluster.executor: dask (pilight/render/cluster.py) -------------------------------------------
def rendered_files(root: Path) -> dict[str, str]:
    """The rendered dataset, without the Dask partition markers (bookkeeping of the executor)."""
    return {k: v for k, v in tree_digest(root).items() if not k.startswith(".partitions/")}


@pytest.fixture(scope="module")
def dask_cluster():
    pytest.importorskip("distributed", reason="dask.distributed (the test extra) is not installed")
    from dask.distributed import Client, LocalCluster

    cluster = LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None)
    client = Client(cluster)
    yield cluster.scheduler_address, client
    client.close()
    cluster.close()


def test_dask_render_survives_killed_workers_with_the_in_process_bytes(reference, tmp_path, dask_cluster):
    """2 workers of a running cluster (render.cluster.address); both are SIGKILLed once the first view is
    done. Dask restarts them and resubmits their partitions; the dataset equals the in-process render."""
    _, first = reference
    address, client = dask_cluster
    params = write_params(
        tmp_path / "params.yaml", cluster={"executor": "dask", "address": address, "scenes_per_task": 1}
    )
    out = tmp_path / "renders"
    proc = subprocess.Popen(
        stage_args(params, out), cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=stage_env()
    )
    deadline = time.time() + 300
    while time.time() < deadline and not list(out.rglob(".done")) and proc.poll() is None:
        time.sleep(0.05)
    killed = list(client.run(os.getpid).values())
    for pid in killed:
        os.kill(pid, signal.SIGKILL)
    _, err = proc.communicate(timeout=600)
    assert proc.returncode == 0, err[-3000:]
    assert not list(out.glob(".render_tmp_*")), "a killed worker's scratch folder was left in the dataset"
    assert rendered_files(out) == rendered_files(first)
    assert len(list((out / ".partitions").glob("*.done"))) == 3  # one marker per partition of 1 scene
    client.wait_for_workers(2, timeout=60)
    assert not set(client.run(os.getpid).values()) & set(killed), "the workers were not restarted: nothing was killed"


def test_dask_render_names_a_failing_scene_and_keeps_the_other_partitions(reference, tmp_path):
    """A local cluster started by the stage (address: null). One scene cannot be written (its folder
    is a file): the stage fails naming it, writes no manifest, and keeps every other partition; the
    rerun after the fix renders only that scene and ends byte-identical to the in-process render."""
    _, first = reference
    params = write_params(tmp_path / "params.yaml", cluster={"executor": "dask", "workers": 2, "scenes_per_task": 1})
    out = tmp_path / "renders"
    out.mkdir()
    (out / "train_0001").write_text("not a folder")
    r = run_stage(params, out)
    assert r.returncode == 1
    assert "1 of 3 render partition(s) failed" in r.stderr and "scene train_0001" in r.stderr, r.stderr[-3000:]
    assert not (out / "manifest.json").exists()
    kept = {p: p.stat().st_mtime_ns for p in out.rglob("*") if p.is_file() and "train_0001" not in str(p)}
    assert (
        any(p.name == ".done" for p in kept) and len({p.parts[len(out.parts)] for p in kept if p.name == ".done"}) == 2
    )
    (out / "train_0001").unlink()
    r = run_stage(params, out)
    assert r.returncode == 0, r.stderr[-3000:]
    assert rendered_files(out) == rendered_files(first)
    assert all(p.stat().st_mtime_ns == t for p, t in kept.items() if p.exists()), "a finished partition was redone"
