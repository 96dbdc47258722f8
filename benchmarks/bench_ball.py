"""What the light ball's resolution and samples cost, and what they buy downstream.

    python benchmarks/bench_ball.py                    # 6 train scenes, 2 views x 4 lights each
    python benchmarks/bench_ball.py --scenes 12 --configs 32x32x4 32x16x4 64x32x16

Every light condition's gray ball is rendered at each `RESxSPPxMIN` config (resolution, samples,
adaptive minimum; adaptive threshold as the scene's) and at a converged reference (64^2, 1024 spp,
no adaptive sampling). The figure of merit is what stage 2 computes from the ball: D_calculated,
the Lambertian lookup of the unfolded ball on a sphere's normals, as PSNR against the reference's
(peak = the reference's maximum). Point-lit and HDRI-lit conditions are reported apart: the
HDRI-lit balls are the noisy ones.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from pilight.params import BaseParams, RenderParams
from pilight.physics.envmap import ball_normals, ball_to_envmap
from pilight.physics.shading import diffuse_shading
from pilight.render import passes, scene, views
from pilight.render.spec import scene_spec

REFERENCE = (64, 1024, 0)


def parse_config(text: str) -> tuple[int, int, int]:
    try:
        res, spp, floor = (int(x) for x in text.split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"config {text!r}: want RESxSAMPLESxMIN, e.g. 32x32x4") from None
    return res, spp, floor


def render_ball(handles: dict, config: tuple[int, int, int], threshold: float, tmp: Path) -> tuple[np.ndarray, float]:
    res, spp, floor = config
    ball_scene = handles["ball_scene"]
    ball_scene.render.resolution_x = ball_scene.render.resolution_y = res
    c = ball_scene.cycles
    c.samples, c.adaptive_min_samples = spp, floor
    c.use_adaptive_sampling = config != REFERENCE and threshold > 0
    c.adaptive_threshold = threshold
    t0 = time.perf_counter()
    ball = passes.ball_maps(views.render_passes(ball_scene, tmp), lambertian=False)["ball"]
    return ball, time.perf_counter() - t0


def d_calculated(ball: np.ndarray) -> torch.Tensor:
    normals, inside = ball_normals(64, 64)
    env = ball_to_envmap(torch.from_numpy(ball).permute(2, 0, 1)[None])[0]
    return diffuse_shading(env, normals, inside)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", type=int, default=6)
    ap.add_argument(
        "--configs",
        nargs="+",
        type=parse_config,
        default=[parse_config(c) for c in ("64x32x16", "32x32x4", "32x16x4", "32x1024x0")],
    )
    a = ap.parse_args()
    p = RenderParams(views_per_scene=2, lights_per_view=4)
    tmp = Path(tempfile.mkdtemp(prefix="bench_ball_"))
    psnr: dict[tuple, list[float]] = {}
    seconds: dict[tuple, list[float]] = {}
    for index in range(a.scenes):
        spec = scene_spec(p, BaseParams().seed, "train", index)
        handles = scene.build(spec, p, views.bundled_hdri_dir())
        passes.configure_ball(handles["ball_scene"].view_layers[0], lambertian=False)
        for v, view in enumerate(spec["views"]):
            scene.set_view(handles, view)
            for light in spec["lights"][v]:
                scene.set_lights(light)
                scene.set_world(handles["world"], light)
                kind = "hdri" if light["hdri"] else "point"
                ref = d_calculated(render_ball(handles, REFERENCE, 0.0, tmp)[0])
                for config in a.configs:
                    ball, dt = render_ball(handles, config, p.cycles.adaptive_threshold, tmp)
                    err = float(((d_calculated(ball) - ref) ** 2).mean())
                    psnr.setdefault((kind, config), []).append(10 * np.log10(float(ref.max()) ** 2 / max(err, 1e-20)))
                    seconds.setdefault((kind, config), []).append(dt)
    print(
        f"\nD_calculated PSNR against {REFERENCE[0]}^2 at {REFERENCE[1]} spp; {a.scenes} scenes, threshold "
        f"{p.cycles.adaptive_threshold}\n"
    )
    print("| light | ball res | spp | adaptive min | n | ms / ball (median) | PSNR mean (dB) | PSNR min (dB) |")
    print("|---|---|---|---|---|---|---|---|")
    for (kind, (res, spp, floor)), values in sorted(psnr.items()):
        ms = 1000 * statistics.median(seconds[(kind, (res, spp, floor))])
        print(
            f"| {kind} | {res} | {spp} | {floor} | {len(values)} | {ms:.1f} | {np.mean(values):.1f} | {np.min(values):.1f} |"
        )


if __name__ == "__main__":
    main()
