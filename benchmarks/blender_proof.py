"""Proof against Blender: D_calculated from the rendered light ball vs Cycles' diffuse shading.

    python benchmarks/blender_proof.py [--resolution 128] [--ball-resolution 128] [--samples 512]
                                       [--ball-samples 512] [--world-map 1024] [--erode 2]

Scenes are built and rendered by the render stage (``scene.build`` + ``views.render_view``):
one object (sphere; Suzanne facing the camera), Principled base 0.8 / roughness 0.5 /
metallic 0, no backdrop, camera at 5 m (50 mm).  Lights (each + ambient 0.02):
HDRI ``forest`` (strength 1, rotated 30 deg), HDRI ``sunset`` (strength 1, not rotated), and
one point light (radius 0.1) in direction (4, -3, 2) from the centre (camera's right, above,
in front) at 100 m and at 20 m, power scaled by distance^2 to keep the irradiance of 1000 W
at |(4, -3, 2)| = 5.39 m.  One extra row renders forest with the render stage's default world
importance map (256) to show what it costs, and Suzanne is rendered once more with
``visible_shadow = False`` on the object (a diagnostic, not the render stage's setting): no
cast shadows or self-occlusion, which D_calculated does not model either.

D_calculated = diffuse_shading(ball_to_envmap(ball)[0], normal) with the ball ('ball': the
paper's Principled roughness-0.5 ball; 'ball_lambertian': 0.5 (Diffuse Direct + Indirect) of
the same render), the camera-space normal map and mask exactly as written to disk.
Reference: Cycles' raw light passes Diffuse Direct + Diffuse Indirect of the object.
Pixels: the written mask eroded by --erode pixels.  Over those pixels and RGB:
PSNR = 10 log10(max(ref)^2 / mean((calc - ref)^2)); mean rel err = mean(|calc - ref| / ref);
bias = mean(calc - ref) / mean(ref); "x-flip" = PSNR with the normal map's x negated.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from pilight.data import layout  # noqa: E402
from pilight.data.exr import read_exr  # noqa: E402
from pilight.params import RenderParams  # noqa: E402
from pilight.physics.envmap import ball_to_envmap  # noqa: E402
from pilight.physics.shading import diffuse_shading  # noqa: E402
from pilight.render.spec import one_object_spec  # noqa: E402

SID = "train_0000"
LIGHT_DIR = np.array([4.0, -3.0, 2.0])
AMBIENT = 0.02


def point(distance: float) -> dict:
    d = LIGHT_DIR / np.linalg.norm(LIGHT_DIR)
    power = 1000.0 * distance**2 / float(LIGHT_DIR @ LIGHT_DIR)
    return {
        "points": [{"location": list(d * distance), "power": power, "radius": 0.1}],
        "hdri": None,
        "ambient": AMBIENT,
    }


def hdri(name: str, rotation: float) -> dict:
    return {"points": [], "hdri": {"name": name, "strength": 1.0, "rotation_deg": rotation}, "ambient": AMBIENT}


LIGHTS = {
    "HDRI forest": hdri("forest", 30.0),
    "HDRI sunset": hdri("sunset", 0.0),
    "point 100 m": point(100.0),
    "point 20 m": point(20.0),
}
OBJECTS = {"sphere": "sphere", "Suzanne": "monkey"}


def erode(m: np.ndarray, r: int) -> np.ndarray:
    out = m.copy()
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            out &= np.roll(np.roll(m, dy, 0), dx, 1)
    return out


def d_calc(ball: np.ndarray, normal: np.ndarray, flip_x: bool = False) -> np.ndarray:
    env, _ = ball_to_envmap(torch.from_numpy(ball).permute(2, 0, 1)[None])
    n = torch.from_numpy(normal).permute(2, 0, 1)[None]
    if flip_x:
        n = n * torch.tensor([-1.0, 1.0, 1.0])[None, :, None, None]
    return diffuse_shading(env, n)[0].permute(1, 2, 0).numpy()


def metrics(calc: np.ndarray, ref: np.ndarray, inner: np.ndarray) -> dict:
    c, r = calc[inner].astype(np.float64), ref[inner].astype(np.float64)
    return {
        "psnr": 10 * np.log10(r.max() ** 2 / ((c - r) ** 2).mean()),
        "rel": float((np.abs(c - r) / np.maximum(r, 1e-6)).mean()),
        "bias": float((c - r).mean() / r.mean()),
    }


def render(shape: str, lights: dict, params: RenderParams, erode_px: int, cast_shadows: bool = True) -> list[dict]:
    from pilight.render import scene, views

    names = list(lights)
    spec = one_object_spec(shape, [lights[n] for n in names], SID)
    with tempfile.TemporaryDirectory(prefix="blender_proof_") as d:
        root = Path(d)
        (root / ".tmp").mkdir()
        handles = scene.build(spec, params, views.bundled_hdri_dir())
        if not cast_shadows:  # diagnostic: the object casts no shadow (on itself), D_calc's own assumption
            for obj in handles["scene"].objects:
                if obj.name.startswith("obj_"):
                    obj.visible_shadow = False
        raw = views.render_view(handles, spec, 0, root, root / ".tmp", lambertian=True, verify=True)
        normal = read_exr(layout.map_path(root, SID, 0, "normal"))
        inner = erode(read_exr(layout.map_path(root, SID, 0, "mask"))[..., 0] > 0.5, erode_px)
        rows = []
        for li, name in enumerate(names):
            dd, di = raw[li]["Diffuse Direct"], raw[li]["Diffuse Indirect"]
            ref = dd + di
            for kind in ("ball_lambertian", "ball"):
                ball = read_exr(layout.map_path(root, SID, 0, kind, li))
                m = metrics(d_calc(ball, normal), ref, inner)
                m["flip"] = metrics(d_calc(ball, normal, flip_x=True), ref, inner)["psnr"]
                m["dd_only"] = metrics(d_calc(ball, normal), dd, inner)["psnr"]
                rows.append(
                    {
                        "object": shape,
                        "light": name,
                        "ball": kind,
                        "pixels": int(inner.sum()),
                        "di_over_dd": float(di[inner].mean() / dd[inner].mean()),
                        **m,
                    }
                )
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--resolution", type=int, default=128)
    ap.add_argument("--ball-resolution", type=int, default=128)
    ap.add_argument("--samples", type=int, default=512)
    ap.add_argument("--ball-samples", type=int, default=512)
    ap.add_argument("--world-map", type=int, default=1024, help="world importance map resolution")
    ap.add_argument("--erode", type=int, default=2, help="mask erosion in pixels")
    args = ap.parse_args()

    def params(world_map: int) -> RenderParams:
        return RenderParams.model_validate(
            dict(
                resolution=args.resolution,
                scenes=dict(train=1, val=0, test=0),
                views_per_scene=1,
                lights_per_view=len(LIGHTS),
                ball_resolution=args.ball_resolution,
                ball_samples=args.ball_samples,
                cycles=dict(
                    samples=args.samples, adaptive_threshold=0.0, adaptive_min_samples=0, world_map_resolution=world_map
                ),
            )
        )

    t0 = time.perf_counter()
    rows = []
    for label, shape in OBJECTS.items():
        for r in render(shape, LIGHTS, params(args.world_map), args.erode):
            rows.append({**r, "object": label})
    no_shadow = {f"{n}, cast shadows off": LIGHTS[n] for n in ("HDRI forest", "point 100 m")}
    for r in render("monkey", no_shadow, params(args.world_map), args.erode, cast_shadows=False):
        rows.append({**r, "object": "Suzanne"})
    default_map = RenderParams().cycles.world_map_resolution
    if default_map != args.world_map:
        name = f"HDRI forest, world map {default_map} (render default)"
        for r in render("sphere", {name: LIGHTS["HDRI forest"]}, params(default_map), args.erode):
            rows.append({**r, "object": "sphere"})
    seconds = time.perf_counter() - t0

    cmd = "python benchmarks/blender_proof.py " + " ".join(sys.argv[1:])
    print(f"\nCommand: `{cmd.strip()}`  ")
    print(
        f"Image {args.resolution}^2 at {args.samples} spp, ball {args.ball_resolution}^2 at {args.ball_samples} spp "
        f"(adaptive sampling off), world importance map {args.world_map}, mask eroded by {args.erode} px; "
        f"Blender {_blender_version()}, {seconds:.0f} s.  Reference: Cycles Diffuse Direct + Indirect.\n"
    )
    print(
        "| object | light | ball | PSNR (dB) | mean rel err | bias | PSNR vs Direct only (dB) | Indirect/Direct | PSNR x-flipped normals (dB) |"
    )
    print("|---|---|---|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        ball = "Lambertian" if r["ball"] == "ball_lambertian" else "Principled r=0.5 (paper)"
        print(
            f"| {r['object']} | {r['light']} | {ball} | {r['psnr']:.2f} | {r['rel']:.3f} | {r['bias']:+.3f} "
            f"| {r['dd_only']:.2f} | {r['di_over_dd']:.3f} | {r['flip']:.2f} |"
        )


def _blender_version() -> str:
    import bpy

    return bpy.app.version_string


if __name__ == "__main__":
    main()
