"""Scene variety for the base model (stretch, gradient/gabor, material classes, sky): its params and
the specs it draws (pure Python: no Blender). At their defaults the keys change no draw at all."""

from __future__ import annotations

import colorsys
import hashlib
import json
import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from fixtures.render_scenes import euler_xyz
from pilight.params import ParamsError, RenderParams, load_section
from pilight.render.material_classes import ALBEDO_RANGE, METAL_F0
from pilight.render.spec import SKY_IRRADIANCE, half_height, scene_spec

ROOT = Path(__file__).resolve().parents[2]


def _hash(specs) -> str:
    return hashlib.sha256(json.dumps(specs, sort_keys=True).encode()).hexdigest()


# sha256 of the specs' JSON, computed with the code of 7e9c46e, before the variety keys existed. The
# committed params.yaml differs from the class defaults only in keys that no draw reads differently
# (scene counts, camera_backdrop) and in views_per_scene = lights_per_view = 2.
PINNED_COMMITTED = {
    ("train", 0): "78352e4eab02cda83566296807b5c9f54d8c12b3fef00007359b74f82b6cf417",
    ("train", 7): "ef74d5268884f80388d566d2d2788149b1114afb7537ded7f11fe81b053c9704",
    ("val", 1): "27d86ddc0c45e232497775be64bb3f9ea86f0b29d3d075ab638693b056af4c3c",
    ("test", 5): "75dae295c2478291aeb4ab817124b1c8020da0fb59af1e63569e06a9e62ea746",
}
PINNED_CLASS_DEFAULTS = {  # 40 train scenes each
    "shared": "2cbd6187870135ac9e7063dfc1c3525538902a95ae6c65e3e1725d493243d631",
    "independent": "33d4d83741b5c54df5a44e49009f91c0a87b9dbcd65d731b29d9ab7b48f0f79d",
}


@pytest.mark.parametrize(
    "source",
    [
        "frozen",  # today's committed render params, written out: independent of later edits of params.yaml
        "params.yaml",  # the live file: fails if someone changes its render draws (update the hashes on purpose)
    ],
)
def test_committed_params_draw_the_same_specs_as_before_the_variety_keys(source):
    if source == "frozen":
        p = RenderParams(views_per_scene=2, lights_per_view=2, camera_backdrop=0.05)
    else:
        p = load_section("render", ROOT / "params.yaml")
    for (split, index), digest in PINNED_COMMITTED.items():
        assert _hash(scene_spec(p, 42, split, index)) == digest, (
            f"{split} {index}: the spec changed; the variety keys' defaults must leave every draw as it was"
        )


@pytest.mark.parametrize("pattern", sorted(PINNED_CLASS_DEFAULTS))
def test_class_defaults_draw_the_same_specs_as_before_the_variety_keys(pattern):
    p = RenderParams(scene={"material_pattern": pattern})
    assert _hash([scene_spec(p, 42, "train", i) for i in range(40)]) == PINNED_CLASS_DEFAULTS[pattern]


def _load(tmp_path, render: dict):
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump({"base": {"seed": 1}, "render": render}))
    return load_section("render", path)


@pytest.mark.parametrize(
    "render, needle",
    [
        ({"scene": {"stretch": {"probability": 0.5, "lo": 0.0, "hi": 1.0}}}, "render.scene.stretch.lo = 0.0"),
        ({"scene": {"stretch": {"probability": 0.5, "lo": 1.5, "hi": 1.0}}}, "lo (1.5) must not exceed hi (1.0)"),
        ({"scene": {"stretch": {"probability": 1.2}}}, "render.scene.stretch.probability = 1.2"),
        ({"scene": {"textures": ["gabor", "perlin"]}}, "unknown texture(s) ['perlin']"),
        ({"scene": {"material_model": "pbr"}}, "render.scene.material_model = 'pbr'"),
        ({"scene": {"material_classes": {"glass": 1.0}}}, "render.scene.material_classes.glass"),
        ({"scene": {"material_classes": {"metal": -1.0}}}, "render.scene.material_classes.metal = -1.0"),
        (
            {
                "scene": {
                    "material_classes": dict.fromkeys(("metal", "plastic", "rubber", "wood", "stone", "ceramic"), 0)
                }
            },
            "at least one class needs a positive weight",
        ),
        ({"light": {"sky_probability": -0.1}}, "render.light.sky_probability = -0.1"),
        ({"light": {"sky_aerosol": {"lo": -1.0, "hi": 2.0}}}, "render.light.sky_aerosol.lo = -1.0"),
        ({"light": {"sky_air": {"lo": 2.0, "hi": 1.0}}}, "lo (2.0) must not exceed hi (1.0)"),
        (
            {"light": {"sky_probability": 0.5, "elevation_clip_deg": {"lo": -10, "hi": 160}}},
            "sky_probability > 0 needs elevation_clip_deg within [5, 175]",
        ),
    ],
)
def test_bad_variety_params_name_key_value_and_rule(tmp_path, render, needle):
    with pytest.raises(ParamsError) as err:
        _load(tmp_path, render)
    assert needle in str(err.value)


def test_committed_params_document_every_variety_key():
    raw = yaml.safe_load((ROOT / "params.yaml").read_text())["render"]
    for key in ("stretch", "material_model", "material_classes", "closeup_fraction"):
        assert key in raw["scene"], key
    for key in ("sky_probability", "sky_air", "sky_aerosol", "sky_sun_intensity"):
        assert key in raw["light"], key


def _objects(specs):
    return [(s, o) for s in specs for o in s["objects"]]


def test_stretch_scales_a_share_of_objects_per_axis_and_room_objects_still_rest_on_the_floor():
    p = RenderParams(scene={"stretch": {"probability": 0.5, "lo": 0.6, "hi": 1.6}})
    pairs = _objects([scene_spec(p, 42, "train", i) for i in range(60)])
    stretched = [o for _, o in pairs if "stretch" in o]
    assert 0.4 < len(stretched) / len(pairs) < 0.6
    s = np.array([o["stretch"] for o in stretched])
    assert s.min() >= 0.6 and s.max() <= 1.6 and s.std(axis=1).mean() > 0.1, "per axis, not one factor"
    u = np.random.default_rng(0).normal(size=(20000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    for spec, o in pairs:
        if "stretch" in o:  # half_height: the stretched, rotated bounding sphere's reach along z
            z = (u * o["scale"] * np.asarray(o["stretch"])) @ euler_xyz(o["rotation_deg"])[2]
            assert abs(half_height(o) - z.max()) < 2e-3 * o["scale"]
        if spec["kind"] == "room":
            assert o["location"][2] == pytest.approx(half_height(o), abs=1e-4), "on the floor (z = 0)"


def _principled(specs):
    mats = [o["material"] for _, o in _objects(specs)]
    mats += [
        s["backdrop"][k] for s in specs if s["backdrop"] for k in ("material", "wall_material") if k in s["backdrop"]
    ]
    return [m for m in mats if m["type"] == "principled"]


def _values(channel) -> list:
    return channel["values"] if "values" in channel else [channel["const"]]


def _classes(**weights):
    textures = ["noise", "voronoi", "checker", "wave", "brick", "magic", "gradient", "gabor"]
    p = RenderParams(scene={"material_model": "classes", "material_classes": weights, "textures": textures})
    return _principled([scene_spec(p, 42, "train", i) for i in range(80)])


def test_material_classes_follow_their_weights_and_record_the_class():
    mats = _classes(metal=1.0, plastic=1.0, rubber=0.0, wood=2.0, stone=0.0, ceramic=0.0)
    share = {c: np.mean([m["class"] == c for m in mats]) for c in ("metal", "plastic", "wood")}
    assert len(mats) > 200 and set(m["class"] for m in mats) == {"metal", "plastic", "wood"}
    assert abs(share["wood"] - 0.5) < 0.08 and abs(share["metal"] - 0.25) < 0.08


def test_every_class_keeps_albedo_in_range_and_its_real_world_correlations():
    mats = _classes()
    assert {m["class"] for m in mats} == {"metal", "plastic", "rubber", "wood", "stone", "ceramic"}
    for m in mats:
        for colour in _values(m["base_color"]):
            assert ALBEDO_RANGE[0] <= min(colour) and max(colour) <= ALBEDO_RANGE[1], m
        metal, rough = _values(m["metallic"]), _values(m["roughness"])
        first_colour, first_rough = _values(m["base_color"])[0], rough[0]
        h, s, v = colorsys.rgb_to_hsv(*(np.asarray(first_colour) ** (1 / 2.2)))
        if m["class"] == "metal":
            assert metal[0] == 1.0 and 0.05 <= first_rough <= 0.6
            # its colour is a metal's F0, dimmed, jittered (3% per channel) and scaled under 0.9: the
            # same chromaticity, within the jitter
            chroma = lambda c: np.asarray(c) / np.sum(c)
            gap = min(np.abs(chroma(first_colour) - chroma(f0)).max() for f0 in METAL_F0.values())
            assert gap < 0.025, first_colour
            assert set(metal) <= {0.0, 1.0}, "painted metal: the paint is a dielectric"
        else:
            assert metal == [0.0], m
        if m["class"] == "plastic":
            assert 0.2 <= min(rough) and max(rough) <= 0.6 and s > 0.35  # saturated (the 0.03 floor greys the darkest)
        if m["class"] == "rubber":
            assert min(rough) >= 0.7
        if m["class"] == "wood":
            assert h < 0.13 and s > 0.3  # browns (the 0.03 floor reddens the darkest a little)
        if m["class"] == "stone":
            assert min(rough) >= 0.6 and s < 0.2
        if m["class"] == "ceramic":
            assert max(rough) <= 0.3 and v > 0.7
    patterned = {c: np.mean(["pattern" in m for m in mats if m["class"] == c]) for c in ("wood", "stone", "rubber")}
    assert patterned["wood"] > 0.7 and patterned["stone"] > 0.6 and patterned["rubber"] < 0.35
    textures = {m["pattern"]["texture"] for m in mats if "pattern" in m}
    assert {"gradient", "gabor"} <= textures


def test_classes_use_only_listed_textures_and_stay_plain_without_them():
    p = RenderParams(scene={"material_model": "classes", "textures": ["checker"]})
    mats = _principled([scene_spec(p, 42, "train", i) for i in range(60)])
    assert {m["pattern"]["texture"] for m in mats if "pattern" in m} == {"checker"}
    assert all("pattern" not in m for m in mats if m["class"] in ("wood", "stone", "metal", "rubber"))


def test_gradient_and_gabor_are_drawn_when_listed():
    p = RenderParams(scene={"textures": ["gradient", "gabor"]})
    mats = _principled([scene_spec(p, 42, "train", i) for i in range(30)])
    assert {m["pattern"]["texture"] for m in mats if "pattern" in m} == {"gradient", "gabor"}


def test_sky_lights_take_the_point_lights_place_direction_and_irradiance():
    p = RenderParams(light={"sky_probability": 0.5})
    specs = [scene_spec(p, 42, "train", i) for i in range(60)]
    lights = [(s, l) for s in specs for v in s["lights"] for l in v]
    skies = [l["sky"] for _, l in lights if l.get("sky")]
    assert 0.4 < len(skies) / len(lights) < 0.6
    for s, l in lights:
        if not l.get("sky"):
            assert "sky" not in l, "point-lit conditions keep their spec"
            continue
        assert l["hdri"] is None and len(l["points"]) == (1 if s["kind"] == "room" else 0), "no HDRI, no key lamp"
        sky = l["sky"]
        d = np.asarray(sky["sun_direction"])
        assert abs(np.linalg.norm(d) - 1) < 1e-5
        assert math.degrees(math.asin(d[2])) >= 20 - 1e-3, "the point light's elevation clip (20 degrees)"
        irradiance = sky["strength"] * SKY_IRRADIANCE / p.light.irradiance_scale
        assert 5 * 0.9 - 1e-3 <= irradiance <= 20 * 1.1 + 1e-3, "the point light's strength range"
        assert 0.8 <= sky["air"] <= 1.5 and 0.5 <= sky["aerosol"] <= 4.0 and 0.7 <= sky["sun_intensity"] <= 1.0
    azimuths = [math.degrees(math.atan2(k["sun_direction"][1], k["sun_direction"][0])) % 360 for k in skies]
    assert np.histogram(azimuths, bins=4, range=(0, 360))[0].min() > len(skies) / 10, "suns all around"


def test_closeup_share_is_cut_from_the_object_scenes_and_leaves_the_rooms_as_they_were():
    before = RenderParams(scene={"room_fraction": 0.25})
    after = RenderParams(scene={"room_fraction": 0.25, "closeup_fraction": 0.5})
    kinds = [
        (scene_spec(before, 42, "train", i)["kind"], scene_spec(after, 42, "train", i)["kind"]) for i in range(200)
    ]
    assert all((b == "room") == (a == "room") for b, a in kinds), "one draw picks the kind: rooms stay rooms"
    assert {b for b, a in kinds if a == "closeup"} == {"object"}
    assert 0.4 < sum(a == "closeup" for _, a in kinds) / len(kinds) < 0.6


def _closeups(n: int = 80) -> list[dict]:
    p = RenderParams(scene={"room_fraction": 0.0, "closeup_fraction": 1.0}, views_per_scene=3)
    return [scene_spec(p, 42, "train", i) for i in range(n)]


def test_closeups_frame_their_subject_like_a_portrait_with_no_floor():
    specs = _closeups()
    assert {s["kind"] for s in specs} == {"closeup"}
    walls = [s for s in specs if s["backdrop"] is not None]
    assert {s["backdrop"]["type"] for s in walls} == {"wall"}, "a wall or nothing behind the subject, never a floor"
    assert 0.45 < len(walls) / len(specs) < 0.75
    for s in specs:
        subject = s["objects"][0]
        assert subject["location"] == [0.0, 0.0, 0.0]
        for v in s["views"]:
            eye, target = np.asarray(v["location"]), np.asarray(v["target"])
            distance = np.linalg.norm(eye - target)
            # the subject's radius over the picture's half-height (Blender's 36 mm sensor, square renders)
            fill = subject["scale"] / (distance * 18.0 / v["lens_mm"])
            assert 0.49 < fill < 0.91, (s["id"], fill)
            elevation = math.degrees(math.asin((eye - target)[2] / distance))
            assert abs(elevation) <= 10.0 + 1e-6, (s["id"], elevation)
            assert np.linalg.norm(target[:2]) <= 0.3 * math.sqrt(2) * subject["scale"] + 1e-4
            if s["backdrop"] is not None:  # the wall is behind the subject and faces the camera's side
                wall = s["backdrop"]
                normal = euler_xyz(wall["rotation_deg"]) @ np.array([0.0, 0.0, 1.0])
                to_eye = (eye - target) / distance
                assert normal @ to_eye > math.cos(math.radians(36.0)), (s["id"], normal, to_eye)
                assert np.asarray(wall["location"]) @ to_eye < -subject["scale"], "behind the subject"


def test_bad_closeup_share_names_both_keys(tmp_path):
    with pytest.raises(ParamsError) as err:
        _load(tmp_path, {"scene": {"room_fraction": 0.6, "closeup_fraction": 0.5}})
    assert "room_fraction (0.6) + closeup_fraction (0.5) must not exceed 1" in str(err.value)
