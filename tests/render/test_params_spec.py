"""Params validation and the paper's sampling distributions (pure Python: no Blender)."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest
import yaml

from pilight.params import ParamsError, RenderParams, load_section
from pilight.render.spec import scene_spec


def _load(tmp_path, render: dict):
    p = tmp_path / "params.yaml"
    p.write_text(yaml.safe_dump({"base": {"seed": 1}, "render": render}))
    return load_section("render", p)


@pytest.mark.parametrize(
    "render, needle",
    [
        ({"scenes": {"train": -2, "val": 0, "test": 0}}, "render.scenes.train = -2"),
        ({"resolution": 130}, "render.resolution = 130: Value error, must be divisible by 8"),
        ({"hdri": {"names": ["forest", "moon"], "test_holdout": []}}, "unknown bundled HDRI name(s) ['moon']"),
        ({"light": {"hdri_probability": -0.1}}, "render.light.hdri_probability = -0.1"),
        ({"assets": ["missing/chair.glb"]}, "asset 'missing/chair.glb' does not exist"),
        ({"hdri": {"test_holdout": ["forest"], "names": ["city"]}}, "must also be listed in names"),
        ({"colour": 1}, "render.colour"),
    ],
)
def test_bad_params_name_key_value_and_rule(tmp_path, render, needle):
    with pytest.raises(ParamsError) as err:
        _load(tmp_path, render)
    assert needle in str(err.value)
    assert "params.yaml" in str(err.value)


def test_committed_params_are_valid():
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    for section in ("base", "render", "shard"):
        load_section(section, root / "params.yaml")


def _many(split="train", n=150, **kw):
    p = RenderParams(**kw)
    return p, [scene_spec(p, 42, split, i) for i in range(n)]


def test_spec_is_deterministic_and_seed_dependent():
    p = RenderParams()
    assert scene_spec(p, 42, "train", 3) == scene_spec(p, 42, "train", 3)
    assert scene_spec(p, 42, "train", 3) != scene_spec(p, 43, "train", 3)
    assert scene_spec(p, 42, "train", 3) != scene_spec(p, 42, "test", 3)


def test_light_distribution_follows_the_paper():
    p, specs = _many(views_per_scene=4, lights_per_view=3)
    lights = [l for s in specs for view in s["lights"] for l in view]
    target = {s["id"]: np.asarray(s["target"]) for s in specs}
    elev, power_irr = [], []
    for s in specs:
        for view in s["lights"]:
            for l in view:
                d = np.asarray(l["points"][0]["location"]) - target[s["id"]]
                r = np.linalg.norm(d)
                assert abs(r - p.light.distance) < 1e-3
                el = math.degrees(math.asin(d[2] / r))  # 20..160 folds to 20..90
                elev.append(el)
                power_irr.append(l["points"][0]["power"] / (4 * math.pi * r**2) / p.light.irradiance_scale)
    assert min(elev) >= 20 - 1e-3
    hdri_share = np.mean([l["hdri"] is not None for l in lights])
    assert 0.14 < hdri_share < 0.26, hdri_share  # 20% with an environment map
    strength = np.array(power_irr)
    assert strength.min() >= 5 * 0.5 * 0.9 - 1e-6 and strength.max() <= 20 * 1.1 + 1e-6
    ambient = [l["ambient"] for l in lights]
    assert min(ambient) >= 0.01 and max(ambient) <= 0.05


def test_held_out_hdris_only_in_the_test_split():
    p = RenderParams(light={"hdri_probability": 1.0})
    for split in ("train", "val"):
        used = {l["hdri"]["name"] for i in range(40) for v in scene_spec(p, 42, split, i)["lights"] for l in v}
        assert not used & set(p.hdri.test_holdout) and used
    used = {l["hdri"]["name"] for i in range(40) for v in scene_spec(p, 42, "test", i)["lights"] for l in v}
    assert used <= set(p.hdri.test_holdout)


def test_object_views_front_back_left_right_then_random():
    _, specs = _many(n=60, views_per_scene=6, scene={"room_fraction": 0.0})
    s = specs[0]
    eyes = [np.asarray(v["location"]) - np.asarray(v["target"]) for v in s["views"]]
    polar = [math.degrees(math.acos(e[2] / np.linalg.norm(e))) for e in eyes[:4]]
    np.testing.assert_allclose(polar, 70.0, atol=1e-3)
    azimuth = sorted(round(math.degrees(math.atan2(e[1], e[0])) % 360) for e in eyes[:4])
    assert azimuth == [0, 90, 180, 270]


def test_room_cameras_and_back_light():
    p, specs = _many(n=60, scene={"room_fraction": 1.0})
    base_eye = np.array([0.0, -4.5, 1.4])
    forward = np.array([0.0, 4.5, -0.8]) / np.linalg.norm([0.0, 4.5, -0.8])
    for s in specs:
        for view, lights in zip(s["views"], s["lights"]):
            shift = np.asarray(view["location"]) - base_eye
            along = shift @ forward
            assert -0.2 - 1e-6 <= along <= 0.5 + 1e-6
            lateral = shift - along * forward
            assert np.linalg.norm(lateral) <= 0.5 + 1e-6
            for l in lights:
                back = np.asarray(l["points"][1]["location"]) - np.asarray(view["location"])
                view_dir = np.asarray(view["target"]) - np.asarray(view["location"])
                cos = -(back[:2] @ view_dir[:2]) / np.linalg.norm(back[:2]) / np.linalg.norm(view_dir[:2])
                assert cos >= math.cos(math.radians(30)) - 1e-6, "behind the camera within +-30 degrees"


def test_unquoted_no_from_dvc_exp_run_means_no_mixed_precision(tmp_path):
    """`dvc exp run -S ...` rewrites params.yaml with `mixed_precision: no`, which YAML reads as False."""
    import yaml

    from pilight.params import load_section

    raw = yaml.safe_load((Path(__file__).resolve().parents[2] / "params.yaml").read_text())
    text = re.sub(r"mixed_precision: \w+", "mixed_precision: no", yaml.safe_dump(raw))
    assert text.count("mixed_precision: no\n") == 2
    (tmp_path / "params.yaml").write_text(text)
    assert load_section("intrinsics", tmp_path / "params.yaml").train.mixed_precision == "fp32"
    assert load_section("relight", tmp_path / "params.yaml").train.mixed_precision == "fp32"


def _principled_materials(specs):
    for s in specs:
        for o in s["objects"]:
            if o["material"]["type"] == "principled":
                yield o["material"]


def test_shared_pattern_materials_blend_two_sub_materials_and_metal_is_0_or_1():
    p, specs = _many()
    mats = list(_principled_materials(specs))
    textured = [m for m in mats if "pattern" in m]
    assert 0.45 < len(textured) / len(mats) < 0.75, "about textured_probability (0.6) of the materials"
    for m in mats:
        for key in ("base_color", "roughness", "metallic"):
            assert "texture" not in m[key], "channels read the material's one pattern, never their own"
            assert ("values" in m[key]) == ("pattern" in m and "const" not in m[key])
        metal = m["metallic"].get("values", [m["metallic"].get("const")])
        assert set(metal) <= {0.0, 1.0}
    # two sub-materials that differ in colour but are both dielectric keep metallic constant
    assert any("values" in m["base_color"] and m["metallic"] == {"const": 0.0} for m in textured)
    assert any("values" in m["metallic"] for m in textured)


def test_independent_pattern_keeps_one_texture_per_map():
    _, specs = _many(scene={"material_pattern": "independent"})
    mats = list(_principled_materials(specs))
    assert all("pattern" not in m for m in mats)
    textured = [m[k] for m in mats for k in ("base_color", "roughness", "metallic") if "texture" in m[k]]
    assert 0.45 < len(textured) / (3 * len(mats)) < 0.75
