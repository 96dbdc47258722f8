"""params.yaml values that once passed validation and cost hours or wrote garbage (issue: trust
nothing damaged): each is refused before any work, naming the key."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from pilight.params import ParamsError, load_section

ROOT = Path(__file__).resolve().parents[1]


def _params(tmp_path: Path, text: str | None = None, **edits) -> Path:
    raw = yaml.safe_load((ROOT / "params.yaml").read_text())
    for dotted, value in edits.items():
        *keys, last = dotted.split("__")
        d = raw
        for k in keys:
            d = d[k]
        d[last] = value
    path = tmp_path / "params.yaml"
    path.write_text(text if text is not None else yaml.safe_dump(raw))
    return path


@pytest.mark.parametrize(
    "section, edit, key",
    [
        ("infer_intrinsics", {"infer_intrinsics__cfg_scale": float("inf")}, "infer_intrinsics.cfg_scale"),
        ("render", {"render__light__elevation_mean_deg": float("nan")}, "render.light.elevation_mean_deg"),
        ("render", {"render__light__strength": {"lo": 5, "hi": float("inf")}}, "render.light.strength.hi"),
        ("render", {"render__resolution": 100000}, "render.resolution"),
        ("relight", {"relight__train__lr": float("nan")}, "relight.train.lr"),
        ("render", {"render__scenes": {"train": True, "val": 1, "test": 1}}, "render.scenes"),
        ("render", {"render__views_per_scene": False}, "render.views_per_scene"),
    ],
)
def test_non_finite_unbounded_and_boolean_numbers_are_refused_by_key(tmp_path, section, edit, key):
    with pytest.raises(ParamsError, match=key.replace(".", r"\.")):
        load_section(section, _params(tmp_path, **edit))


def test_a_typo_d_section_is_an_error(tmp_path):
    text = (ROOT / "params.yaml").read_text().replace("\nrender:", "\nrendr:", 1)
    with pytest.raises(ParamsError, match=r"unknown top-level section\(s\) \['rendr'\]"):
        load_section("base", _params(tmp_path, text=text))


def test_a_duplicate_key_is_an_error_not_the_last_value(tmp_path):
    text = (ROOT / "params.yaml").read_text().replace("  resolution: 128", "  resolution: 128\n  resolution: 64", 1)
    with pytest.raises(ParamsError, match="duplicate key 'resolution'"):
        load_section("render", _params(tmp_path, text=text))


def test_the_embedded_default_still_loads():
    for section in (
        "base",
        "render",
        "shard",
        "intrinsics",
        "infer_intrinsics",
        "relight",
        "relight_infer",
        "evaluate",
    ):
        load_section(section, ROOT / "params.yaml")
