"""The ceiling of a cast-shadow input for stage 2, measured before any model is changed.

    python benchmarks/visibility_oracle.py --params params.yaml --renders data/renders --out /tmp/vis --json /tmp/vis.json

Stage 2's diffuse branch predicts a gain g_D on D_calc_b, the target ball's Lambertian lookup at each normal
(pilight.relight.physics_first). A per-pixel lookup cannot know cast shadows, and the network explains about
a quarter of the true gains (docs: stage 2). Would a visibility map, marched in screen space over a depth
buffer, explain them? This answers with ground-truth geometry, so it bounds what a predicted depth could give.

1. ``positions``: for each view of the split's scenes one more Cycles render, of the Position pass alone
   (world space of the first hit; 1 sample and a 0.01 px filter, so no pixel blends two surfaces), cached
   as ``<out>/<scene>_v<view>.npy``. Only this needs ``bpy``.
2. ``visibility``: each mask pixel marches toward each point light of the render's light condition in
   screen space (``march_visibility``): a sample is hidden where the surface seen at its pixel is nearer the
   camera than the sample by more than a bias and by less than ``--thickness`` metres. Points are weighted
   by their unshadowed irradiance at the pixel. ``--light point`` marches to the light's location (a known
   light); ``direction`` marches along the direction the ball at the scene's target sees (what a fitted
   ball gives, with no distance).
3. The D branch's target, g = gain_of(D_target, D_calc_b, eps_b) on the mask, with D_target = (I_b - S_b) / A_x:
   the true D_b with the true albedo (``--albedo true``), or what the stage's ratio form needs (``effective``:
   A_x explains input a under its rendered ball, so a level lights a and b share cancels). What each fit explains (share of sum g^2, 0 = the anchor): a constant per image (the light's level); one
   global law g = alpha + beta vis (what a network given vis could learn without knowing the image); each
   image's level plus one global beta vis (what visibility adds to knowing the level); the law per image.
4. change_r2 on the mask, the evaluation's figure (relative to input a's image): I = A_x D + S_b with the true
   specular S_b and D from the anchor, from each fit, and the truth. Tone-mapped as the evaluation is; the light
   b is the rendered ball (the absolute tier), the maps the ground truth.

The pairs are the split's cross-light pairs (light a -> light b of one view). Deterministic; no model.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pilight.data import layout  # noqa: E402
from pilight.data.exr import read_exr  # noqa: E402

MARCH_SAMPLES = 64
START_OFFSET = 0.02  # metres along the normal: a sample must not hit its own surface
DEPTH_BIAS = 0.01  # relative: a surface hides a sample only when nearer by more than 1 % of its depth


def project(points: np.ndarray, K: np.ndarray, world_from_camera: np.ndarray) -> tuple[np.ndarray, ...]:
    """World points (..., 3) -> pixel column u, row v (pixel centres at +0.5) and depth along the view
    (Blender camera: -z forward, y up)."""
    R, C = world_from_camera[:3, :3], world_from_camera[:3, 3]
    cam = (points - C) @ R
    z = -cam[..., 2]
    safe = np.where(z > 1e-6, z, 1e-6)
    u = K[0, 0] * cam[..., 0] / safe + K[0, 2]
    v = K[1, 2] - K[1, 1] * cam[..., 1] / safe
    return u, v, z


def march_visibility(
    position: np.ndarray,
    normal_world: np.ndarray,
    pixels: np.ndarray,
    targets: np.ndarray,
    K: np.ndarray,
    world_from_camera: np.ndarray,
    *,
    thickness: float,
    directional: bool,
    max_distance: float = 8.0,
) -> np.ndarray:
    """(P,) visibility in {0, 1} of ``targets`` (P, 3: points, or unit directions when ``directional``) from
    the surface points ``position[pixels]``, marched over the depth buffer that ``position`` (H, W, 3) gives."""
    H, W, _ = position.shape
    _, _, depth = project(position, K, world_from_camera)
    has_surface = np.abs(position).sum(-1) > 0  # the Position pass is 0 where a camera ray hits nothing
    depth = np.where(has_surface, depth, np.inf)
    x0 = position[pixels[:, 0], pixels[:, 1]] + START_OFFSET * normal_world
    if directional:
        step_dir, length = targets, np.full(len(x0), max_distance)
    else:
        delta = targets - x0
        length = np.minimum(np.linalg.norm(delta, axis=-1), max_distance)
        step_dir = delta / np.maximum(np.linalg.norm(delta, axis=-1, keepdims=True), 1e-9)
    # denser near the start, where contact shadows are decided
    t = ((np.arange(1, MARCH_SAMPLES + 1) / MARCH_SAMPLES) ** 2)[None, :] * length[:, None]
    q = x0[:, None, :] + t[..., None] * step_dir[:, None, :]
    u, v, zq = project(q, K, world_from_camera)
    col, row = np.floor(u).astype(int), np.floor(v).astype(int)
    inside = (col >= 0) & (col < W) & (row >= 0) & (row < H) & (zq > 1e-3)
    z_seen = np.where(inside, depth[row.clip(0, H - 1), col.clip(0, W - 1)], np.inf)
    gap = zq - z_seen
    hidden = inside & (gap > DEPTH_BIAS * zq) & (gap < thickness)
    return (~hidden.any(axis=1)).astype(np.float32)


def render_positions(params: Path, split: str, out: Path) -> float:
    """Step 1 (module docstring): the Position pass of every view of ``split``; seconds taken."""
    import bpy

    from pilight.data.exr import read_render_passes
    from pilight.params import load_section
    from pilight.render import scene as S
    from pilight.render.blender_log import blender_output_to
    from pilight.render.dataset import all_specs
    from pilight.render.views import bundled_hdri_dir

    p, base = load_section("render", params), load_section("base", params)
    hdri_dir = Path(p.hdri.dir) if p.hdri.dir else bundled_hdri_dir()
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    with blender_output_to(out / "blender.log"):
        for spec in (s for s in all_specs(p, base) if s["split"] == split):
            _render_scene_positions(bpy, S, read_render_passes, spec, p, hdri_dir, out)
    return time.perf_counter() - t0


def _render_scene_positions(bpy, S, read_render_passes, spec: dict, p, hdri_dir: Path, out: Path) -> None:
    """The Position pass of each view of one scene that is not cached yet (write, then rename)."""
    todo = [v for v in range(len(spec["views"])) if not (out / f"{spec['id']}_v{v:02d}.npy").is_file()]
    if not todo:
        return
    handles = S.build(spec, p, hdri_dir)
    scene = handles["scene"]
    scene.cycles.samples, scene.cycles.use_adaptive_sampling = 1, False
    scene.cycles.filter_width = 0.01
    layer = scene.view_layers[0]
    for name in ("normal", "diffuse_direct", "diffuse_indirect", "diffuse_color"):
        setattr(layer, f"use_pass_{name}", False)
    layer.use_pass_position = True
    for v in todo:
        S.set_view(handles, spec["views"][v])
        S.set_lights(spec["lights"][v][0])
        S.set_world(handles["world"], spec["lights"][v][0])
        exr = out / f"_render_{spec['id']}_v{v:02d}.exr"
        scene.render.filepath = str(exr)
        bpy.ops.render.render(write_still=True, scene=scene.name)
        pos = read_render_passes(exr)["Position"][..., :3]
        exr.unlink()
        tmp = out / f"{spec['id']}_v{v:02d}.tmp.npy"
        np.save(tmp, pos.astype(np.float32))
        tmp.rename(out / f"{spec['id']}_v{v:02d}.npy")


def point_irradiance(points: list[dict], x: np.ndarray, n: np.ndarray) -> np.ndarray:
    """(P, k): each point light's unshadowed irradiance (power cos / 4 pi r^2) at surface points x, normals n."""
    cols = []
    for pt in points:
        d = np.asarray(pt["location"], dtype=np.float64) - x
        r2 = (d**2).sum(-1)
        cos = np.clip((d * n).sum(-1) / np.sqrt(np.maximum(r2, 1e-12)), 0.0, None)
        cols.append(pt["power"] * cos / (4 * np.pi * np.maximum(r2, 1e-6)))
    return np.stack(cols, -1) if cols else np.zeros((len(x), 0))


def view_pairs(renders: Path, positions: Path, split: str, light_mode: str, thickness: float):
    """Yield one dict per (view, light b): ground-truth maps, renders and vis (module docstring, step 2)."""
    manifest = json.loads((renders / "manifest.json").read_text())
    for entry in (s for s in manifest["scenes"] if s["split"] == split):
        sid = entry["id"]
        sidecar = json.loads((renders / sid / "scene.json").read_text())
        for v in range(entry["views"]):
            cam = sidecar["cameras"][v]
            K, wfc = np.asarray(cam["K"]), np.asarray(cam["world_from_camera"])
            position = np.load(positions / f"{sid}_v{v:02d}.npy").astype(np.float64)
            maps = {
                k: read_exr(layout.map_path(renders, sid, v, k))
                for k in ("albedo", "normal", "roughness", "metallic", "mask")
            }
            pix = np.argwhere(maps["mask"][..., 0] > 0.5)
            n_world = maps["normal"][pix[:, 0], pix[:, 1]].astype(np.float64) @ wfc[:3, :3].T
            x = position[pix[:, 0], pix[:, 1]]
            target = np.asarray(sidecar["spec"]["target"], dtype=np.float64)
            lit = {}
            for li in range(entry["lights"]):
                got = {
                    k: read_exr(layout.map_path(renders, sid, v, k, li))
                    for k in ("image", "diffuse", "specular", "ball")
                }
                points = sidecar["lights"][v][li]["points"]
                irr = point_irradiance(points, x, n_world)
                vis = np.ones((len(pix), len(points)), dtype=np.float32)
                for k, pt in enumerate(points):
                    loc = np.asarray(pt["location"], dtype=np.float64)
                    if light_mode == "point":
                        tgt, directional = np.broadcast_to(loc, x.shape), False
                    else:
                        d = (loc - target) / np.linalg.norm(loc - target)
                        tgt, directional = np.broadcast_to(d, x.shape), True
                    vis[:, k] = march_visibility(
                        position, n_world, pix, tgt, K, wfc, thickness=thickness, directional=directional
                    )
                total = irr.sum(-1)
                v_map = np.ones(maps["mask"].shape[:2], dtype=np.float32)
                v_map[pix[:, 0], pix[:, 1]] = np.where(total > 0, (irr * vis).sum(-1) / np.maximum(total, 1e-12), 1.0)
                lit[li] = {**got, "vis": v_map}
            yield {"id": f"{sid}_v{v:02d}", "maps": maps, "lit": lit}


def _t(a: np.ndarray) -> torch.Tensor:
    """H x W x C numpy -> 1 x C x H x W float tensor."""
    return torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32)).permute(2, 0, 1)[None]


def study(renders: Path, positions: Path, split: str, light_mode: str, thickness: float, albedo: str = "true") -> dict:
    """Steps 3 and 4 (module docstring) over the split's cross-light pairs a -> b. ``albedo``: ``true`` forms
    I = A D + S with the true albedo, so g is the true D_b on the anchor; ``effective`` uses the stage's A_x
    (pilight.relight.physics_first: the albedo that explains input a under its rendered ball, GGX specular),
    whose ratio form cancels what lights a and b share, and g is the D branch's own target."""
    from pilight.data.colour import tonemap01
    from pilight.eval.light_following import ChangeR2
    from pilight.relight import physics_first as pf

    items = []  # per cross-light pair: g and vis on the mask, and what composing needs
    for view in view_pairs(renders, positions, split, light_mode, thickness):
        m = view["maps"]
        intr = {k: _t(m[k]) for k in ("albedo", "normal")} | {k: _t(m[k][..., :1]) for k in ("metallic", "roughness")}
        mask = _t(m["mask"][..., :1])
        sel = mask[0, 0] > 0.5
        for lb, got in view["lit"].items():
            for la in (la for la in view["lit"] if la != lb):
                ball_a, ball_b = _t(view["lit"][la]["ball"]), _t(got["ball"])
                anc = pf.anchors(
                    _t(view["lit"][la]["image"]), intr, mask, ball_b, None,
                    albedo_source="effective" if albedo == "effective" else "conditioning",
                    ball_a=ball_a, specular="ggx",
                )  # fmt: skip
                a_x = anc.albedo
                d_target = pf.diffuse_target(_t(got["image"]), _t(got["specular"]), a_x)
                g = pf.gain_of(d_target, anc.d_calc, anc.eps).mean(1, keepdim=True)  # one gain per pixel
                items.append(
                    {
                        "view": view, "a": la, "b": lb, "sel": sel, "d_calc": anc.d_calc, "eps": anc.eps,
                        "albedo": a_x, "d_target": d_target, "g": g[0, 0][sel].double(),
                        "vis": torch.from_numpy(got["vis"])[sel].double(),
                    }
                )  # fmt: skip
    g_all, v_all = torch.cat([it["g"] for it in items]), torch.cat([it["vis"] for it in items])
    X = torch.stack([torch.ones_like(v_all), v_all], 1)
    law = torch.linalg.lstsq(X, g_all[:, None]).solution[:, 0]  # one global (alpha, beta)
    # level + one global slope: each image's own level, and beta fitted on the within-image variation
    dev = [(it["g"] - it["g"].mean(), it["vis"] - it["vis"].mean()) for it in items]
    beta = float(sum((dg * dv).sum() for dg, dv in dev) / max(sum(float((dv**2).sum()) for _, dv in dev), 1e-12))
    fits = {"anchor": [], "level": [], "vis_law": [], "level_plus_vis": [], "vis_per_image": [], "truth": []}
    for it in items:
        g, vis = it["g"], it["vis"]
        Xi = torch.stack([torch.ones_like(vis), vis], 1)
        per = torch.linalg.lstsq(Xi, g[:, None]).solution[:, 0] if vis.std() > 1e-6 else torch.tensor([g.mean(), 0.0])
        fits["anchor"].append(torch.zeros_like(g))
        fits["level"].append(torch.full_like(g, float(g.mean())))
        fits["vis_law"].append(Xi @ law)
        fits["level_plus_vis"].append(g.mean() + beta * (vis - vis.mean()))
        fits["vis_per_image"].append(Xi @ per)
        fits["truth"].append(g)
    sse0 = float((g_all**2).sum())
    out = {
        "split": split,
        "light": light_mode,
        "albedo": albedo,
        "thickness_m": thickness,
        "pairs": len(items),
        "mask_pixels": int(len(g_all)),
        "shadowed_share": float((v_all < 0.5).double().mean()),
        "law_alpha_beta": [float(law[0]), float(law[1])],
        "level_plus_vis_beta": beta,
        "corr_g_vis": float(torch.corrcoef(torch.stack([g_all, v_all]))[0, 1]),
    }
    for name, preds in fits.items():
        out[f"gain_explained_{name}"] = 1 - float(((torch.cat(preds) - g_all) ** 2).sum()) / sse0
    # step 4: compose each fit's D with the true S on the mask and score each pair a -> b
    for name in fits:
        r2 = ChangeR2()
        for j, it in enumerate(items):
            view, lit_b = it["view"], it["view"]["lit"][it["b"]]
            g_map = torch.zeros_like(it["d_calc"][:, :1])
            g_map[0, 0][it["sel"]] = fits[name][j].float()
            d = it["d_target"] if name == "truth" else pf.apply_gain(g_map, it["d_calc"], it["eps"])
            mask, target = _t(view["maps"]["mask"][..., :1]), _t(lit_b["image"])
            formed = torch.where(mask > 0.5, it["albedo"] * d + _t(lit_b["specular"]), target)
            r2.update(tonemap01(formed), tonemap01(target), tonemap01(_t(view["lit"][it["a"]]["image"])), mask)
        c = r2.compute()
        out[f"change_r2_{name}"], out[f"change_r2_{name}_pair_median"] = c["mask"], c["mask_pair_median"]
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--params", type=Path, default=Path("params.yaml"), help="the params the renders were made with")
    ap.add_argument("--renders", type=Path, default=Path("data/renders"))
    ap.add_argument("--out", type=Path, required=True, help="where the Position passes are cached")
    ap.add_argument("--split", default="test")
    ap.add_argument("--light", choices=["point", "direction"], nargs="+", default=["point", "direction"])
    ap.add_argument(
        "--thickness", type=float, nargs="+", default=[0.5], help="metres a seen surface occludes behind it"
    )
    ap.add_argument("--albedo", choices=["true", "effective"], nargs="+", default=["true", "effective"])
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    if not (args.renders / "manifest.json").is_file():
        print(f"visibility_oracle: {args.renders}/manifest.json missing: not a finished render folder", file=sys.stderr)
        return 2
    seconds = render_positions(args.params, args.split, args.out)
    print(f"positions: {seconds:.1f} s -> {args.out}", flush=True)
    results = []
    for light in args.light:
        for thickness in args.thickness:
            for albedo in args.albedo:
                r = study(args.renders, args.out, args.split, light, thickness, albedo)
                results.append(r)
                print(json.dumps(r), flush=True)
    if args.json:
        tmp = args.json.with_suffix(".tmp")
        tmp.write_text(json.dumps(results, indent=1))
        tmp.rename(args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
