"""Seconds per (view, light) bundle: everything the render stage writes vs the beauty render alone.

    python benchmarks/bench_render.py                  # 128^2, 64 spp, adaptive sampling on
    python benchmarks/bench_render.py --resolution 256 --views 2 --lights 4

Each (scene kind, mode) runs in its own child process so peak memory (max RSS) is its own.
"beauty" renders only the Combined pass of the main scene; "bundle" is the whole stage output:
view maps (AOVs + normal, amortised over the view's lights), image/diffuse/specular, the gray
and Lambertian balls, EXR + PNG writing. Both modes render the same views and lights in the
same run, so their ratio is meaningful on a noisy shared machine; each repeats all views x lights
`--repeats` times and reports the median pass (the first pass includes building the BVH).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def child(kind: str, mode: str, resolution: int, views: int, lights: int, repeats: int) -> dict:
    from pilight.params import BaseParams, RenderParams
    from pilight.render import passes, scene, views
    from pilight.render.spec import scene_spec

    p = RenderParams(resolution=resolution, views_per_scene=views, lights_per_view=lights)
    spec = next(s for i in range(100) if (s := scene_spec(p, BaseParams().seed, "train", i))["kind"] == kind)
    handles = scene.build(spec, p, views.bundled_hdri_dir())
    out = Path(tempfile.mkdtemp(prefix="bench_render_"))
    per_bundle = []
    for _ in range(repeats):  # every pass renders all views x lights again; the median is reported
        t0, n = time.perf_counter(), 0
        for v in range(views):
            if mode == "bundle":
                views.render_view(handles, spec, v, out, out, lambertian=True)
                n += lights
            else:
                scene.set_view(handles, spec["views"][v])
                for light in spec["lights"][v]:
                    scene.set_lights(light)
                    scene.set_world(handles["world"], light)
                    passes.configure(handles["scene"].view_layers[0], diffuse=False, view_maps=False)
                    views.render_passes(handles["scene"], out)
                    n += 1
        per_bundle.append((time.perf_counter() - t0) / n)
    return {
        "kind": kind,
        "mode": mode,
        "bundles": n * repeats,
        "s_per_bundle": statistics.median(per_bundle),
        "objects": len(spec["objects"]),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--resolution", type=int, default=128)
    ap.add_argument("--views", type=int, default=2)
    ap.add_argument("--lights", type=int, default=4)
    ap.add_argument("--repeats", type=int, default=5, help="passes over all views x lights; the median pass counts")
    ap.add_argument("--child", nargs=2, metavar=("KIND", "MODE"), help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.child:
        print("RESULT " + json.dumps(child(*a.child, a.resolution, a.views, a.lights, a.repeats)))
        return
    rows = []
    for kind in ("object", "room"):
        for mode in ("beauty", "bundle"):
            proc = subprocess.Popen(
                [
                    sys.executable,
                    __file__,
                    "--child",
                    kind,
                    mode,
                    "--resolution",
                    str(a.resolution),
                    "--views",
                    str(a.views),
                    "--lights",
                    str(a.lights),
                    "--repeats",
                    str(a.repeats),
                ],
                stdout=subprocess.PIPE,
                stderr=subprocess.DEVNULL,
                text=True,
            )
            stdout = proc.stdout.read()
            _, status, usage = os.wait4(proc.pid, 0)
            if status:
                raise SystemExit(f"benchmark child {kind}/{mode} failed")
            r = json.loads(next(l for l in stdout.splitlines() if l.startswith("RESULT "))[7:])
            r["peak_mb"] = usage.ru_maxrss / 1024  # Linux reports KiB
            rows.append(r)
    print(
        f"\n{a.resolution}x{a.resolution}, 64 spp, adaptive threshold 0.02, {a.views} views x {a.lights} lights, "
        f"{os.cpu_count()} cores, median of {a.repeats} passes\n"
    )
    print("| scene | mode | objects | s / bundle | bundles / min | peak RSS (MB) | bundle / beauty |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        beauty = next(b for b in rows if b["kind"] == r["kind"] and b["mode"] == "beauty")
        per = r["s_per_bundle"]
        ratio = per / beauty["s_per_bundle"]
        print(
            f"| {r['kind']} | {r['mode']} | {r['objects']} | {per:.3f} | {60 / per:.1f} | {r['peak_mb']:.0f} | {ratio:.2f}x |"
        )


if __name__ == "__main__":
    main()
