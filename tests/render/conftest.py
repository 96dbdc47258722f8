"""Fixtures for render tests: tiny controlled scenes rendered once per test module."""

from __future__ import annotations

import copy
from pathlib import Path

import pytest

from pilight.params import RenderParams, SplitCounts

TINY = dict(
    resolution=48,
    scenes=SplitCounts(train=1, val=0, test=0),
    views_per_scene=1,
    lights_per_view=2,
    cycles=dict(samples=16, adaptive_min_samples=8),
)


def tiny_params(**overrides) -> RenderParams:
    return RenderParams.model_validate({**TINY, **overrides})


def principled(colour, roughness, metallic) -> dict:
    return {
        "type": "principled",
        "base_color": {"const": list(colour)},
        "roughness": {"const": roughness},
        "metallic": {"const": metallic},
    }


def controlled_spec(objects: list[dict], lights: list[dict], view=None) -> dict:
    """One view looking down +y at the origin from 5 m; `lights` are per-light dicts."""
    return {
        "id": "train_0000",
        "split": "train",
        "index": 0,
        "kind": "object",
        "seed": 0,
        "cycles_seed": 7,
        "objects": copy.deepcopy(objects),
        "assets": [],
        "backdrop": None,
        "target": [0.0, 0.0, 0.0],
        "views": [view or {"location": [0.0, -5.0, 0.0], "target": [0.0, 0.0, 0.0], "lens_mm": 50.0}],
        "lights": [copy.deepcopy(lights)],
    }


def point_light(location, power=3000.0, ambient=0.02, hdri=None) -> dict:
    return {"points": [{"location": list(location), "power": power, "radius": 0.1}], "hdri": hdri, "ambient": ambient}


def sphere(material, location=(0.0, 0.0, 0.0), scale=1.0) -> dict:
    return {
        "shape": "sphere",
        "location": list(location),
        "rotation_deg": [0, 0, 0],
        "scale": scale,
        "modifiers": [],
        "material": material,
    }


@pytest.fixture(scope="session")
def bpy_render():
    """Render a controlled spec into a folder; returns (root, raw passes per light)."""
    pytest.importorskip("bpy")
    from pilight.render import scene, views

    def run(spec: dict, root: Path, params: RenderParams | None = None, verify: bool = True, lambertian: bool = True):
        p = params or tiny_params()
        handles = scene.build(spec, p, views.bundled_hdri_dir())
        tmp = root / ".tmp"
        tmp.mkdir(parents=True, exist_ok=True)
        raw = views.render_view(handles, spec, 0, root, tmp, lambertian=lambertian, verify=verify)
        return raw, handles

    return run
