"""Scene specifications drawn deterministically from (base seed, split, scene index).

Pure numpy, no bpy: a spec is a JSON-able dict that fully determines one scene (objects,
materials, cameras, lights), so it can be tested without Blender and is written verbatim into
the scene's sidecar. Distributions follow the paper's appendix (Dataset Construction):
- object scenes: 4 views from front, back, left and right at the paper's "70 degrees", then
  random views (we read 70 degrees as the polar angle from the up axis, i.e. 20 degrees above
  the horizon: 70 degrees above the horizon would show mostly the tops of objects);
- room scenes: lateral camera shifts in [-0.5, 0.5] m, forward/backward in [-0.2, 0.5] m and at
  most 5 degrees of elevation change; an extra point light behind the camera within +-30 degrees;
- lights: azimuth U[0, 360], elevation N(60, 40) clipped to [20, 160] degrees, strength U[5, 20]
  with jitter, lowered when an HDRI is on; a small ambient term; 80% point light alone, 20% point
  light plus an environment map.
"""

from __future__ import annotations

import math
import zlib

import numpy as np

from pilight.params import RenderParams

SPLITS = ("train", "val", "test")


def scene_rng(seed: int, split: str, index: int) -> np.random.Generator:
    # crc32 rather than hash(): Python salts str hashes per process.
    return np.random.default_rng([seed, zlib.crc32(split.encode()), index])


def _unit(v) -> list[float]:
    v = np.asarray(v, dtype=np.float64)
    return (v / np.linalg.norm(v)).tolist()


def _colour(rng: np.random.Generator) -> list[float]:
    # Linear base colours in [0.03, 0.9]: no physical dielectric is perfectly black or white,
    # and D = diffuse radiance / albedo needs albedo away from 0.
    hsv_s, hsv_v = rng.uniform(0.0, 0.9), rng.uniform(0.15, 0.95)
    h = rng.uniform(0.0, 1.0)
    k = (np.array([5.0, 3.0, 1.0]) + h * 6.0) % 6.0
    rgb = hsv_v - hsv_v * hsv_s * np.clip(np.minimum(k, 4.0 - k), 0.0, 1.0)
    return np.clip(rgb**2.2, 0.03, 0.9).round(4).tolist()


def _channel(rng, p: RenderParams, const: float | list[float], lo: float, hi: float, colour: bool) -> dict:
    """One Principled input: a constant or a procedural texture between two values."""
    if p.scene.textures and rng.uniform() < p.scene.textured_probability:
        a, b = (_colour(rng), _colour(rng)) if colour else sorted(rng.uniform(lo, hi, 2).round(4).tolist())
        return {
            "texture": str(rng.choice(p.scene.textures)),
            "scale": round(float(rng.uniform(2.0, 8.0)), 3),
            "values": [a, b],
        }
    return {"const": const}


def _material(rng: np.random.Generator, p: RenderParams) -> dict:
    if rng.uniform() < p.scene.non_principled_probability:
        if rng.uniform() < 0.5:
            return {
                "type": "glass",
                "color": _colour(rng),
                "roughness": round(float(rng.uniform(0, 0.2)), 4),
                "ior": 1.45,
            }
        return {"type": "emission", "color": _colour(rng), "strength": round(float(rng.uniform(1.0, 4.0)), 3)}
    if p.scene.material_pattern == "shared":
        return _shared_pattern_material(rng, p)
    metal = 1.0 if rng.uniform() < p.scene.metallic_probability else 0.0
    return {
        "type": "principled",
        "base_color": _channel(rng, p, _colour(rng), 0, 1, colour=True),
        "roughness": _channel(rng, p, round(float(rng.uniform(0.1, 0.9)), 4), 0.05, 1.0, colour=False),
        "metallic": _channel(rng, p, metal, 0.0, 1.0, colour=False),
    }


# Half-width of the Fac band that a shared pattern's mask ramps across: narrow, so the two
# sub-materials meet along a soft edge (anti-aliased, as in a baked material mask) instead of
# blending over the whole of a noise texture, whose Fac stays mostly between 0.3 and 0.7.
PATTERN_EDGE = 0.05


def _shared_pattern_material(rng: np.random.Generator, p: RenderParams) -> dict:
    """Two sub-materials (colour, roughness, metal 0 or 1) meeting along one procedural mask.

    Why: in real PBR assets (the paper's Objaverse data) a material mask drives base colour,
    roughness and metalness together, so where the albedo changes, the others may too, and
    metalness is 0 or 1 away from edges. Independent textures per map make roughness and
    metallic patterns that no image shows; "independent" keeps that older distribution."""

    def sub() -> tuple[list[float], float, float]:
        return (
            _colour(rng),
            round(float(rng.uniform(0.1, 0.9)), 4),
            1.0 if rng.uniform() < p.scene.metallic_probability else 0.0,
        )

    first = sub()
    if not (p.scene.textures and rng.uniform() < p.scene.textured_probability):
        return {
            "type": "principled",
            **{k: {"const": v} for k, v in zip(("base_color", "roughness", "metallic"), first)},
        }
    second = sub()
    pattern = {
        "texture": str(rng.choice(p.scene.textures)),
        "scale": round(float(rng.uniform(2.0, 8.0)), 3),
        "edge": PATTERN_EDGE,
    }
    channels = {
        k: {"const": a} if a == b else {"values": [a, b]}
        for k, a, b in zip(("base_color", "roughness", "metallic"), first, second)
    }
    return {"type": "principled", "pattern": pattern, **channels}


def _object(rng, p: RenderParams, location, size: float) -> dict:
    shape = str(rng.choice(p.scene.shapes))
    modifiers = []
    if rng.uniform() < p.scene.modifier_probability:
        modifiers.append(
            {"cube": "bevel", "cylinder": "bevel", "cone": "bevel"}.get(
                shape, "displace" if rng.uniform() < 0.5 else "subdivision"
            )
        )
    return {
        "shape": shape,
        "location": np.round(location, 4).tolist(),
        "rotation_deg": rng.uniform(0, 360, 3).round(3).tolist(),
        "scale": round(float(size), 4),
        "modifiers": modifiers,
        "material": _material(rng, p),
    }


def _look_view(location, target, lens_mm: float = 50.0) -> dict:
    return {"location": np.round(location, 5).tolist(), "target": np.round(target, 5).tolist(), "lens_mm": lens_mm}


def _object_views(rng, p: RenderParams, radius: float) -> list[dict]:
    views, dist = [], 3.2 * radius + 2.0
    for v in range(p.views_per_scene):
        if v < 4:  # front, back, left, right at the paper's 70 degrees (polar)
            azimuth, polar = math.radians(-90 + 90 * (0, 2, 3, 1)[v]), math.radians(70.0)
        else:
            azimuth, polar = rng.uniform(0, 2 * math.pi), math.radians(rng.uniform(45.0, 85.0))
        eye = dist * np.array(
            [math.sin(polar) * math.cos(azimuth), math.sin(polar) * math.sin(azimuth), math.cos(polar)]
        )
        views.append(_look_view(eye + [0, 0, 0.3 * radius], [0.0, 0.0, 0.3 * radius]))
    return views


def _room_views(rng, p: RenderParams) -> list[dict]:
    base_eye, target = np.array([0.0, -4.5, 1.4]), np.array([0.0, 0.0, 0.6])
    forward = (target - base_eye) / np.linalg.norm(target - base_eye)
    right = np.cross(forward, [0, 0, 1.0])
    right /= np.linalg.norm(right)
    views = []
    for _ in range(p.views_per_scene):
        shift = rng.uniform(-0.5, 0.5) * right + rng.uniform(-0.2, 0.5) * forward
        d_el = math.radians(rng.uniform(-5.0, 5.0))  # at most 5 degrees of elevation change
        eye = base_eye + shift
        look = target + shift + np.array([0, 0, math.tan(d_el) * np.linalg.norm(target - base_eye)])
        views.append(_look_view(eye, look, lens_mm=35.0))
    return views


def _direction(azimuth: float, elevation: float) -> np.ndarray:
    # Elevation above 90 degrees continues over the zenith to the other side.
    return np.array(
        [math.cos(elevation) * math.cos(azimuth), math.cos(elevation) * math.sin(azimuth), math.sin(elevation)]
    )


def _point(location, irradiance: float, distance: float, radius: float) -> dict:
    # Blender point power P [W] gives irradiance ~ P / (4 pi d^2) at distance d.
    return {
        "location": np.round(location, 5).tolist(),
        "power": round(4 * math.pi * distance**2 * irradiance, 4),
        "radius": radius,
    }


def _lights(rng, p: RenderParams, kind: str, view: dict, target, hdris: tuple[str, ...]) -> list[dict]:
    lp, out = p.light, []
    for _ in range(p.lights_per_view):
        az = math.radians(rng.uniform(lp.azimuth_deg.lo, lp.azimuth_deg.hi))
        el = math.radians(
            float(
                np.clip(
                    rng.normal(lp.elevation_mean_deg, lp.elevation_std_deg),
                    lp.elevation_clip_deg.lo,
                    lp.elevation_clip_deg.hi,
                )
            )
        )
        strength = rng.uniform(lp.strength.lo, lp.strength.hi) * (1 + rng.uniform(-lp.jitter, lp.jitter))
        hdri = None
        if hdris and rng.uniform() < lp.hdri_probability:
            strength *= lp.point_scale_with_hdri
            hdri = {
                "name": str(rng.choice(hdris)),
                "strength": round(float(rng.uniform(lp.hdri_strength.lo, lp.hdri_strength.hi)), 4),
                "rotation_deg": round(float(rng.uniform(0, 360)), 3),
            }
        e = strength * lp.irradiance_scale
        points = [_point(np.asarray(target) + lp.distance * _direction(az, el), e, lp.distance, lp.radius)]
        if kind == "room":  # the appendix's extra light behind the camera, within +-30 degrees
            eye = np.asarray(view["location"])
            back = eye - np.asarray(view["target"])
            back /= np.linalg.norm(back)
            yaw = math.radians(rng.uniform(-lp.room_back_light_deg, lp.room_back_light_deg))
            c, s = math.cos(yaw), math.sin(yaw)
            back = np.array([c * back[0] - s * back[1], s * back[0] + c * back[1], back[2]])
            location = eye + 1.5 * back
            # Half the main light's irradiance at the scene centre.
            points.append(_point(location, 0.5 * e, float(np.linalg.norm(location - np.asarray(target))), lp.radius))
        out.append(
            {"points": points, "hdri": hdri, "ambient": round(float(rng.uniform(lp.ambient.lo, lp.ambient.hi)), 5)}
        )
    return out


def scene_spec(p: RenderParams, seed: int, split: str, index: int) -> dict:
    """The full, deterministic description of scene `index` of `split`."""
    if split not in SPLITS:
        raise ValueError(f"unknown split {split!r}; allowed: {SPLITS}")
    rng = scene_rng(seed, split, index)
    kind = "room" if rng.uniform() < p.scene.room_fraction else "object"
    # Held-out HDRIs appear only in the test split.
    hdris = p.hdri.names if split == "test" else tuple(n for n in p.hdri.names if n not in p.hdri.test_holdout)
    if split == "test" and p.hdri.test_holdout:
        hdris = p.hdri.test_holdout
    objects, assets = [], list(p.assets)
    if kind == "object":
        n = int(rng.integers(p.scene.objects_object_scene.lo, p.scene.objects_object_scene.hi + 1))
        for i in range(n):
            loc = [0.0, 0.0, 0.0] if i == 0 else [*rng.uniform(-1.2, 1.2, 2), 0.0]
            objects.append(_object(rng, p, loc, rng.uniform(0.6, 1.0) if i == 0 else rng.uniform(0.3, 0.6)))
        backdrop = {"type": "ground", "material": _material(rng, p)} if rng.uniform() < 0.5 else None
        target = [0.0, 0.0, 0.0]
        views = _object_views(rng, p, radius=1.2 if n > 1 else 1.0)
    else:
        n = int(rng.integers(p.scene.objects_room_scene.lo, p.scene.objects_room_scene.hi + 1))
        for _ in range(n):
            size = rng.uniform(0.25, 0.6)
            objects.append(_object(rng, p, [*rng.uniform([-1.6, -1.0], [1.6, 1.5]), size], size))
        backdrop = {"type": "room", "material": _material(rng, p), "wall_material": _material(rng, p)}
        target = [0.0, 0.0, 0.6]
        views = _room_views(rng, p)
    if p.assets_only:
        objects = []
    placed_assets = [
        {
            "asset": a,
            "location": [float(x) for x in rng.uniform(-0.8, 0.8, 2).round(4)] + [0.0],
            "rotation_deg": [0.0, 0.0, round(float(rng.uniform(0, 360)), 3)],
            "size": 1.0,
        }
        for a in assets
    ]
    lights = [_lights(rng, p, kind, v, target, hdris) for v in views]
    return {
        "id": f"{split}_{index:04d}",
        "split": split,
        "index": index,
        "kind": kind,
        "seed": seed,
        "cycles_seed": int(rng.integers(0, 2**31 - 1)),
        "objects": objects,
        "assets": placed_assets,
        "backdrop": backdrop,
        "target": target,
        "views": views,
        "lights": lights,
    }


def one_object_spec(shape: str, lights: list[dict], scene_id: str = "train_0000") -> dict:
    """A scene spec of one `shape` at the origin, a gray (0.8) Principled dielectric of roughness 0.5,
    seen from 5 m along -y, under `lights` (the light specs of its one view): the controlled scene
    that the proofs against Blender render (tests/physics/test_physics_blender.py,
    benchmarks/blender_proof.py)."""
    material = {
        "type": "principled",
        "base_color": {"const": [0.8, 0.8, 0.8]},
        "roughness": {"const": 0.5},
        "metallic": {"const": 0.0},
    }
    obj = {
        "shape": shape,
        "location": [0.0, 0.0, 0.0],
        "rotation_deg": [0, 0, 0],
        "scale": 1.0,
        "modifiers": [],
        "material": material,
    }
    return {
        "id": scene_id,
        "split": scene_id.split("_")[0],
        "index": 0,
        "kind": "object",
        "seed": 0,
        "cycles_seed": 7,
        "objects": [obj],
        "assets": [],
        "backdrop": None,
        "target": [0.0, 0.0, 0.0],
        "views": [{"location": [0.0, -5.0, 0.0], "target": [0.0, 0.0, 0.0], "lens_mm": 50.0}],
        "lights": [lights],
    }
