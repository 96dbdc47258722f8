"""The render side of the speed/accuracy trade: the beauty pass at several samples per pixel (bpy only).

For the first object scene and the first room scene of the test split (else val, else train; view 0,
light 0, the render params' resolution and bounces), the beauty pass is rendered once at
`evaluate.trade.render_reference_spp` (the reference, seed base.seed), then at each
`evaluate.trade.render_spp` with adaptive sampling OFF (so spp means spp) and once at the pipeline's
own setting (`render.cycles.samples` with its adaptive threshold), both with seed base.seed + 1 so
their noise is not the reference's. Seconds are wall-clock per render. pilight.eval.render_trade
scores the renders against the reference and draws the plot.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

from tqdm import tqdm

from pilight.params import BaseParams, RenderParams, TradeParams
from pilight.render import passes, scene, views
from pilight.render.blender_log import blender_output_to
from pilight.render.spec import scene_spec


def first_of(p: RenderParams, seed: int, kind: str) -> dict | None:
    """The first scene spec of ``kind`` ("object" | "room"), test split first."""
    for split in ("test", "val", "train"):
        for i in range(getattr(p.scenes, split)):
            spec = scene_spec(p, seed, split, i)
            if spec["kind"] == kind:
                return spec
    return None


def render_spp_sweep(p: RenderParams, base: BaseParams, tp: TradeParams, blender_log: Path | None = None) -> list[dict]:
    """Per scene, the reference and then every point: {"spec", "what" ("reference" | "spp" | "pipeline"), "spp",
    "adaptive_threshold", "image" (the Combined pass, H x W x 4 float32 linear), "seconds"}. Blender's own
    output goes to ``blender_log`` (None: the terminal); raises scene.RenderError."""
    points = [("reference", tp.render_reference_spp, 0.0, base.seed)]
    points += [("spp", n, 0.0, base.seed + 1) for n in tp.render_spp]
    points.append(("pipeline", p.cycles.samples, p.cycles.adaptive_threshold, base.seed + 1))
    specs = [s for s in (first_of(p, base.seed, "object"), first_of(p, base.seed, "room")) if s is not None]
    out = []
    with (
        blender_output_to(blender_log) as terminal,
        tempfile.TemporaryDirectory(prefix="render_trade_") as tmp,
        tqdm(total=len(specs) * len(points), desc="render_trade", unit="render", file=terminal) as bar,
    ):
        for spec in specs:
            handles = scene.build(spec, p, views.bundled_hdri_dir())
            scn = handles["scene"]
            scene.set_view(handles, spec["views"][0])
            light = spec["lights"][0][0]
            scene.set_lights(light)
            scene.set_world(handles["world"], light)
            passes.configure(scn.view_layers[0], diffuse=False, view_maps=False)
            for what, spp, threshold, seed in points:
                c = scn.cycles
                c.samples, c.use_adaptive_sampling, c.adaptive_threshold, c.seed = spp, threshold > 0, threshold, seed
                t0 = time.perf_counter()
                image = views.render_passes(scn, Path(tmp))["Combined"]
                bar.update(1)
                out.append(
                    {
                        "spec": spec,
                        "what": what,
                        "spp": spp,
                        "adaptive_threshold": threshold,
                        "image": image,
                        "seconds": time.perf_counter() - t0,
                    }
                )
    return out
