"""The schema: [-1, 1] mappings round-trip, and validate_sample names what is wrong and where
(the HDR tone map itself: tests/data/test_colour.py)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from pilight.data.colour import hdr_to_model
from pilight.data.schema import SampleError, from_model, model_to_unit, to_model, unit_to_model, validate_sample

unit32 = arrays(np.float32, st.integers(1, 32), elements=st.floats(0.0, 1.0, width=32))


@given(unit32)
def test_unit_round_trip(x):
    y = unit_to_model(x)
    assert np.all(y >= -1) and np.all(y <= 1)
    np.testing.assert_allclose(model_to_unit(y), x, atol=1e-7)


def test_to_model_dispatches_per_key():
    x = np.full((2, 2, 3), 0.5)
    assert np.allclose(to_model("albedo", x), 0.0) and np.allclose(to_model("normal", x), 0.5)
    assert np.allclose(to_model("image_a", x), hdr_to_model(x))  # loader names share the spec
    for key in ("image", "ball_b", "albedo", "mask", "normal", "roughness"):
        assert np.allclose(from_model(key, to_model(key, x)), x)


def good_sample(h=4, w=4):
    rng = np.random.default_rng(0)
    a, d, s = rng.random((h, w, 3)), rng.random((h, w, 3)), rng.random((h, w, 3))
    n = rng.normal(size=(h, w, 3))
    return {
        "__key__": "train_0000_v00_l00",
        "image": a * d + s,
        "albedo": a,
        "diffuse": d,
        "specular": s,
        "ball": rng.random((2, 2, 3)),
        "normal": n / np.linalg.norm(n, axis=-1, keepdims=True),
        "roughness": rng.random((h, w, 1)),
        "metallic": rng.random((h, w, 1)),
        "mask": np.ones((h, w, 1)),
        "meta": {
            "scene": "train_0000",
            "kind": "object",
            "split": "train",
            "view": 0,
            "light": 0,
            "camera": {},
            "light_params": {},
        },
    }


def test_valid_sample_passes():
    validate_sample(good_sample(), "somewhere")


@pytest.mark.parametrize(
    "key, value, message",
    [
        ("albedo", lambda a: np.where(a > 0.5, np.nan, a), "NaN"),
        ("specular", lambda a: np.where(a > 0.5, np.inf, a), "Inf"),
        ("roughness", lambda a: a[:3], "shape"),
        ("metallic", lambda a: a + 2, "outside"),
        ("mask", lambda a: a * 0.5, "0 or 1"),
        ("normal", lambda a: a * 1.5, "outside|longer"),
        ("diffuse", lambda a: a * 2, "albedo \\* diffuse"),
        ("meta", lambda m: {**m, "split": "dev"}, "split"),
    ],
)
def test_bad_values_are_named(key, value, message):
    sample = good_sample()
    sample[key] = value(sample[key])
    files = {k: f"/r/{k}.exr" for k in sample}
    with pytest.raises(SampleError, match=message) as err:
        validate_sample(sample, files)
    text = str(err.value)
    assert "train_0000_v00_l00" in text and (f"/r/{key}.exr" in text or key == "diffuse")


def test_missing_key_is_named():
    sample = good_sample()
    del sample["ball"]
    with pytest.raises(SampleError, match="'ball'.*shard-3.tar:ball"):
        validate_sample(sample, "shard-3.tar")
