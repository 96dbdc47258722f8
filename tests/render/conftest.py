"""Fixtures for render tests: tiny controlled scenes rendered once per test module."""

from __future__ import annotations

from pathlib import Path

import pytest

from fixtures.render_scenes import tiny_params
from pilight.params import RenderParams


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
