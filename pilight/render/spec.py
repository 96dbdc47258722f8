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
Variety beyond the paper, for the base model, each off by default and then drawing nothing, so the
default's specs keep every draw (tests/render/test_variety_spec.py pins them): per-axis stretch of
objects (render.scene.stretch), material classes (render.scene.material_model, material_classes.py)
and the procedural sky in place of the point light and HDRI (render.light.sky_probability).
Close-up scenes (render.scene.closeup_fraction, off by default: the share is cut from the object
scenes' without a new draw) frame one subject like a portrait: it fills half to nine tenths of the
picture's half-height, the camera at eye level (within 10 degrees of the horizon), a wall behind it or
nothing, never a floor. Object and room scenes always show the ground under their objects, which
taught stage 1 that the bottom of a picture faces up: on a portrait it read the sitter as a floor.
"""

from __future__ import annotations

import math
import zlib

import numpy as np

from pilight.params import EXTRA_SHAPES, RenderParams
from pilight.render.material_classes import PATTERN_EDGE, class_material, pattern_material

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
    if p.scene.material_model == "classes":
        return class_material(rng, p.scene.material_classes.model_dump(), p.scene.textures)
    if p.scene.material_pattern == "shared":
        return _shared_pattern_material(rng, p)
    metal = 1.0 if rng.uniform() < p.scene.metallic_probability else 0.0
    return {
        "type": "principled",
        "base_color": _channel(rng, p, _colour(rng), 0, 1, colour=True),
        "roughness": _channel(rng, p, round(float(rng.uniform(0.1, 0.9)), 4), 0.05, 1.0, colour=False),
        "metallic": _channel(rng, p, metal, 0.0, 1.0, colour=False),
    }


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
        "edge": PATTERN_EDGE,  # material_classes.py
    }
    return pattern_material(first, second, pattern)


def half_height(obj: dict) -> float:
    """Half the world-z extent of an object, read as its bounding sphere (radius ``scale``, as the
    ground and room placement always have): stretched and rotated, x = R S u with |u| <= scale
    reaches z = scale * |S R^T e_z|, where R^T e_z is the last row of Blender's XYZ Euler matrix."""
    if "stretch" not in obj:
        return obj["scale"]
    rx, ry, _ = np.radians(obj["rotation_deg"])
    last_row = np.array([-math.sin(ry), math.cos(ry) * math.sin(rx), math.cos(ry) * math.cos(rx)])
    return float(obj["scale"] * np.linalg.norm(np.asarray(obj["stretch"]) * last_row))


def _object(rng, p: RenderParams, location, size: float, on_floor: bool = False) -> dict:
    shape = str(rng.choice(p.scene.shapes))
    modifiers = []
    # The holed shapes keep their crisp rims: their faces, split at every crease, would come apart under
    # subdivision or displacement (pilight/render/holed_shapes.py).
    if rng.uniform() < p.scene.modifier_probability and shape not in EXTRA_SHAPES:
        modifiers.append(
            {"cube": "bevel", "cylinder": "bevel", "cone": "bevel"}.get(
                shape, "displace" if rng.uniform() < 0.5 else "subdivision"
            )
        )
    obj = {
        "shape": shape,
        "location": np.round(location, 4).tolist(),
        "rotation_deg": rng.uniform(0, 360, 3).round(3).tolist(),
        "scale": round(float(size), 4),
        "modifiers": modifiers,
        "material": _material(rng, p),
    }
    stretch = p.scene.stretch
    if stretch.probability > 0 and rng.uniform() < stretch.probability:  # at 0 no draw: older scenes keep theirs
        obj["stretch"] = rng.uniform(stretch.lo, stretch.hi, 3).round(4).tolist()  # per local axis
        if on_floor:  # rests on the floor as an unstretched object does: its centre one half-height up
            obj["location"][2] = round(half_height(obj), 4)
    return obj


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


SENSOR_HALF_MM = 18.0  # Blender's default sensor: 36 mm wide, fitted to the longer side (square renders)


def _closeup(rng, p: RenderParams) -> tuple[list[dict], dict | None, list[dict]]:
    """A subject at the origin filling a fraction f of the picture's half-height, seen at eye level from
    one side (every view within 25 degrees of azimuth of it), a second, smaller object beside or behind it
    in half the scenes, and in 60% of them a wall behind both, facing the camera side; no floor."""
    size = float(rng.uniform(0.6, 1.0))
    objects = [_object(rng, p, [0.0, 0.0, 0.0], size)]
    side = rng.uniform(0, 2 * math.pi)  # the azimuth the cameras look from
    toward = _direction(side, 0.0)  # from the subject toward the cameras, level
    across = np.array([-toward[1], toward[0], 0.0])
    if rng.uniform() < 0.5:
        second = float(rng.uniform(0.3, 0.6))
        at = rng.uniform(-1.5, 1.5) * across - rng.uniform(0.0, 1.2) * toward + [0.0, 0.0, rng.uniform(-0.8, 0.8)]
        objects.append(_object(rng, p, at, second))
    backdrop = None
    if rng.uniform() < 0.6:
        at = -(size + rng.uniform(0.8, 2.5)) * toward  # behind the subject (and the second object)
        # Blender's plane faces +z; rotated (90, 0, phi) degrees it faces (sin phi, -cos phi, 0) = toward
        phi = side + math.pi / 2
        backdrop = {
            "type": "wall",
            "material": _material(rng, p),
            "location": np.round(at, 4).tolist(),
            "rotation_deg": [90.0, 0.0, round(math.degrees(phi) % 360, 3)],
        }
    views = []
    for _ in range(p.views_per_scene):
        fill = rng.uniform(0.5, 0.9)  # the subject's radius over the picture's half-height
        lens = float(rng.uniform(35.0, 85.0))
        distance = size / (fill * SENSOR_HALF_MM / lens)
        az = side + math.radians(rng.uniform(-25.0, 25.0))
        el = math.radians(rng.uniform(-10.0, 10.0))
        look = rng.uniform(-0.3, 0.3, 2) * size  # off centre, across and up
        target = look[0] * across + [0.0, 0.0, look[1]]
        eye = target + distance * _direction(az, el)
        views.append(_look_view(eye, target, lens_mm=round(lens, 3)))
    return objects, backdrop, views


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


# Blender's procedural sky (ShaderNodeTexSky, Blender 5.0: SINGLE_SCATTERING, MULTIPLE_SCATTERING,
# PREETHAM, HOSEK_WILKIE). Multiple scattering (new in 5.0) is the physical one: its sky is also lit by
# light scattered more than once, as Earth's is.
SKY_MODEL = "MULTIPLE_SCATTERING"
# The sky's irradiance on a surface facing its sun at Background strength 1 (sun disc + sky, Earth's
# atmosphere, mean of R, G, B): 121-145 for suns 20-75 degrees up, integrated from equirectangular
# renders of the world. A sky light of strength e / SKY_IRRADIANCE thus gives about the irradiance e
# that the point light would have given. Exposure, measured on 16 scenes of the committed params
# (128 px, view 0, the same light draws point-lit and sky-lit): sky-lit images have 0.975 times the
# mean radiance on the mask (geometric mean; 0.6-2.1 per scene), the Lambertian ball 1.14 times (the
# sky's dome also lights the side the sun does not).
SKY_IRRADIANCE = 140.0


def _sky(rng, lp, sun_direction: np.ndarray, irradiance: float) -> dict:
    """An outdoor light: the sky with its sun along ``sun_direction`` (z up, at least 5 degrees up)."""
    return {
        "model": SKY_MODEL,
        "sun_direction": np.round(sun_direction, 6).tolist(),
        "strength": round(irradiance / SKY_IRRADIANCE, 6),
        "air": round(float(rng.uniform(lp.sky_air.lo, lp.sky_air.hi)), 4),
        "aerosol": round(float(rng.uniform(lp.sky_aerosol.lo, lp.sky_aerosol.hi)), 4),
        "sun_intensity": round(float(rng.uniform(lp.sky_sun_intensity.lo, lp.sky_sun_intensity.hi)), 4),
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
        sky = None
        if lp.sky_probability > 0 and rng.uniform() < lp.sky_probability:  # at 0 no draw: older scenes keep theirs
            # The sky replaces the point light and the HDRI: its sun is the key light, from where the
            # point light would have been (a second sun or a second environment would be no real place).
            sky = _sky(rng, lp, _direction(az, el), strength * lp.irradiance_scale)
        hdri = None
        if sky is None and hdris and rng.uniform() < lp.hdri_probability:
            strength *= lp.point_scale_with_hdri
            hdri = {
                "name": str(rng.choice(hdris)),
                "strength": round(float(rng.uniform(lp.hdri_strength.lo, lp.hdri_strength.hi)), 4),
                "rotation_deg": round(float(rng.uniform(0, 360)), 3),
            }
        e = strength * lp.irradiance_scale
        key = _point(np.asarray(target) + lp.distance * _direction(az, el), e, lp.distance, lp.radius)
        points = [] if sky else [key]
        # The appendix's extra light behind the camera, within +-30 degrees; kept under the sky too: it
        # lights the side of a room that the camera sees (without it, most sky-lit rooms measured 0.3 to
        # 0.65 times as bright as point-lit ones).
        if kind == "room":
            eye = np.asarray(view["location"])
            back = eye - np.asarray(view["target"])
            back /= np.linalg.norm(back)
            yaw = math.radians(rng.uniform(-lp.room_back_light_deg, lp.room_back_light_deg))
            c, s = math.cos(yaw), math.sin(yaw)
            back = np.array([c * back[0] - s * back[1], s * back[0] + c * back[1], back[2]])
            location = eye + 1.5 * back
            # Half the main light's irradiance at the scene centre.
            points.append(_point(location, 0.5 * e, float(np.linalg.norm(location - np.asarray(target))), lp.radius))
        light = {"points": points, "hdri": hdri, "ambient": round(float(rng.uniform(lp.ambient.lo, lp.ambient.hi)), 5)}
        if sky is not None:
            light["sky"] = sky
        out.append(light)
    return out


def scene_spec(p: RenderParams, seed: int, split: str, index: int) -> dict:
    """The full, deterministic description of scene `index` of `split`."""
    if split not in SPLITS:
        raise ValueError(f"unknown split {split!r}; allowed: {SPLITS}")
    rng = scene_rng(seed, split, index)
    u = rng.uniform()  # one draw picks the kind whatever the shares: a share of 0 changes no later draw
    kind = "room" if u < p.scene.room_fraction else "object"
    if kind == "object" and u < p.scene.room_fraction + p.scene.closeup_fraction:
        kind = "closeup"
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
    elif kind == "closeup":
        objects, backdrop, views = _closeup(rng, p)
        target = [0.0, 0.0, 0.0]  # the lights aim at the subject, the cameras a little off it
    else:
        n = int(rng.integers(p.scene.objects_room_scene.lo, p.scene.objects_room_scene.hi + 1))
        for _ in range(n):
            size = rng.uniform(0.25, 0.6)
            objects.append(_object(rng, p, [*rng.uniform([-1.6, -1.0], [1.6, 1.5]), size], size, on_floor=True))
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
