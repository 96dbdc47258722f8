"""The render stage on a Dask cluster (`render.cluster.executor: dask`).

Why Dask and not Ray: rendering here is a bag of independent, coarse tasks whose outputs are files
on a shared filesystem, which is what `dask.distributed` does with the least machinery. It is pure
Python (one pip install, no object store or raylet), a local cluster of 2 processes starts in about a
second on 2 cores, and the schedulers people already run (SLURM, PBS, Kubernetes) start Dask workers
through Dask's own tools (dask-jobqueue, dask-kubernetes).

The scenes are cut into partitions of `render.cluster.scenes_per_task` scenes, in the order of
`pilight.render.dataset.all_specs`. One partition is one task. A worker process imports bpy once,
with its first task, and keeps it for every later one. The work inside a partition is the in-process
render (`views.render_scene`), with the same per-view stamps, so the bytes do not depend on the
executor, on which worker rendered what, or on how often a task was retried. A partition is complete
when its marker `<root>/.partitions/<first>--<last>.done` holds the hash of its views' stamps. A
rerun submits only the partitions without such a marker, and inside them renders only the views
without a stamp.

Failures:
- A worker that dies (killed, out of memory) loses its task. Dask's scheduler resubmits the task to
  another worker, up to its `allowed-failures` setting. The views the dead worker finished stay done.
- A partition whose task raises is retried `render.cluster.retries` times. If it still fails, every
  other partition is still finished, and then the stage fails, naming the failed scenes and the error.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

# No bpy at import time: workers unpickle this module's functions before render_partition has cleaned
# their sys.path (_blender_paths_out).
MARKERS = ".partitions"


def _blender_paths_out() -> None:
    """A local cluster's workers are spawned with the driver's sys.path, which holds the script folders
    that importing bpy added there (.../bpy/5.0/scripts/modules). With those first, `import bpy` finds
    Blender's inner package, not the bpy module ("No module named '_bpy'"). Drop them before bpy loads."""
    if "bpy" not in sys.modules:
        sys.path[:] = [e for e in sys.path if not (f"{os.sep}bpy{os.sep}" in e and f"{os.sep}scripts" in e)]


def partitions(specs: list[dict], size: int) -> list[list[dict]]:
    return [specs[i : i + size] for i in range(0, len(specs), size)]


def _marker(root: Path, part: list[dict]) -> Path:
    return Path(root) / MARKERS / f"{part[0]['id']}--{part[-1]['id']}.done"


def _stamp(part: list[dict], p) -> str:
    from pilight.render.views import view_stamp

    views = [view_stamp(spec, v, p) for spec in part for v in range(len(spec["views"]))]
    return hashlib.sha256("\n".join(views).encode()).hexdigest()


def partition_is_complete(root: Path, part: list[dict], p) -> bool:
    m = _marker(root, part)
    return m.is_file() and m.read_text() == _stamp(part, p)


def render_partition(part: list[dict], params_json: dict, root: str, hdri_dir: str, log: str | None) -> dict:
    """One task, run inside a worker process: render the partition's scenes, then write its marker."""
    _blender_paths_out()
    from pilight.params import RenderParams
    from pilight.render import views  # imports bpy, once per worker process
    from pilight.render.blender_log import blender_output_to
    from pilight.render.scene import RenderError

    p = RenderParams.model_validate(params_json, context={"check_paths": False})
    root_path, t0 = Path(root), time.perf_counter()
    bundles, failure = 0, None
    with blender_output_to(Path(log) if log else None):
        tmp = Path(tempfile.mkdtemp(prefix=views.TMP_PREFIX, dir=root_path))
        try:
            for spec in part:
                try:
                    bundles += views.render_scene(spec, p, root_path, Path(hdri_dir), tmp)
                except Exception as exc:  # noqa: BLE001 - named, then raised below as a plain message
                    failure = f"scene {spec['id']}: {type(exc).__name__}: {exc}"
                    break
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
    if failure is not None:
        # Raised outside the handler, without a cause: the scheduler pickles what a task raises with its
        # traceback, and frames holding Blender's objects do not travel (the task hung, never failed).
        raise RenderError(failure)
    marker = _marker(root_path, part)
    marker.parent.mkdir(parents=True, exist_ok=True)
    marker.write_text(_stamp(part, p))
    return {"bundles": bundles, "seconds": time.perf_counter() - t0, "pid": os.getpid()}


def render_on_dask(
    specs: list[dict], p, root: Path, hdri_dir: Path, on_bundles: Callable[[int], object], blender_log: Path | None
) -> list[dict]:
    """Submit every incomplete partition, wait for all of them; RenderError naming the failed scenes."""
    from pilight.render import views
    from pilight.render.scene import RenderError

    try:
        from dask.distributed import Client, LocalCluster, as_completed
    except ImportError:
        raise RenderError(
            "render.cluster.executor is 'dask' but dask.distributed is not installed: pip install -e '.[cluster]'"
        ) from None
    c = p.cluster
    parts = partitions(specs, c.scenes_per_task)
    todo = []
    for part in parts:
        if partition_is_complete(root, part, p):
            on_bundles(views.bundles_of(part))
        else:
            todo.append(part)
    if not todo:
        return []
    params_json = p.model_dump(mode="json")
    log = str(Path(blender_log).resolve()) if blender_log else None
    cluster = (
        None
        if c.address
        else LocalCluster(n_workers=c.workers, threads_per_worker=1, processes=True, dashboard_address=None)
    )
    client = Client(c.address or cluster)
    results, failed = [], []
    try:
        futures = {
            client.submit(
                render_partition,
                part,
                params_json,
                str(Path(root).resolve()),
                str(hdri_dir),
                log,
                key=f"render-{part[0]['id']}--{part[-1]['id']}",
                pure=False,
                retries=c.retries,
            ): part
            for part in todo
        }
        for future in as_completed(futures):
            part = futures[future]
            try:
                results.append(future.result())
            except Exception as exc:  # noqa: BLE001 - collected: the other partitions still finish
                failed.append(f"{part[0]['id']}..{part[-1]['id']}: {exc}")
                continue
            on_bundles(views.bundles_of(part))
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
    if failed:
        raise RenderError(
            f"{len(failed)} of {len(todo)} render partition(s) failed (the others are complete and "
            "kept; fix the cause and rerun):\n  " + "\n  ".join(failed)
        )
    return results
