"""The schema: [-1, 1] mappings round-trip, and validate_sample names what is wrong and where."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from pilight.data import schema
from pilight.data.schema import (HDR_MAX, SampleError, from_model, hdr_to_model, model_to_hdr,
                                 model_to_unit, srgb_preview, to_model, unit_to_model, validate_sample)

hdr64 = arrays(np.float64, st.integers(1, 32), elements=st.floats(0.0, HDR_MAX))
hdr32 = arrays(np.float32, st.integers(1, 32), elements=st.floats(0.0, 1e3, width=32))
unit32 = arrays(np.float32, st.integers(1, 32), elements=st.floats(0.0, 1.0, width=32))


@settings(max_examples=200, deadline=None)
@given(hdr64)
def test_hdr_round_trip_exact_in_float64(x):
    y = hdr_to_model(x)
    assert np.all(y >= -1) and np.all(y < 1)
    np.testing.assert_allclose(model_to_hdr(y), x, rtol=1e-9, atol=1e-12)


@settings(max_examples=200, deadline=None)
@given(hdr32)
def test_hdr_round_trip_float32_within_conditioning(x):
    # In float32 the curve's slope near 1 bounds the error: ~1e-7 * (1 + x) relative.
    back = model_to_hdr(hdr_to_model(x))
    assert back.dtype == np.float32
    assert np.all(np.abs(back - x) <= 1e-6 + 4e-7 * x * (2 + x))


@given(hdr32)
def test_hdr_mapping_same_on_torch(x):
    t = torch.from_numpy(x)
    np.testing.assert_allclose(hdr_to_model(t).numpy(), hdr_to_model(x), rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(model_to_hdr(hdr_to_model(t)).numpy(), x, rtol=1e-4, atol=1e-5)


@given(unit32)
def test_unit_round_trip(x):
    y = unit_to_model(x)
    assert np.all(y >= -1) and np.all(y <= 1)
    np.testing.assert_allclose(model_to_unit(y), x, atol=1e-7)


def test_curve_anchor_points_and_monotonic():
    x = np.array([0.0, 0.18, 1.0, 4.0, HDR_MAX])
    y = hdr_to_model(x)
    assert y[0] == -1 and np.all(np.diff(y) > 0) and abs(y[1] + 0.15) < 0.01
    assert np.isclose(y[-1], schema.Y_MAX)
    assert np.all(np.isfinite(model_to_hdr(np.array([-5.0, 1.0, 5.0]))))  # wild outputs stay finite
    assert model_to_hdr(np.array([5.0]))[0] <= HDR_MAX * (1 + 1e-6)


def test_to_model_dispatches_per_key():
    x = np.full((2, 2, 3), 0.5)
    assert np.allclose(to_model("albedo", x), 0.0) and np.allclose(to_model("normal", x), 0.5)
    assert np.allclose(to_model("image_a", x), hdr_to_model(x))  # loader names share the spec
    for key in ("image", "ball_b", "albedo", "mask", "normal", "roughness"):
        assert np.allclose(from_model(key, to_model(key, x)), x)


def test_srgb_preview():
    out = srgb_preview(np.array([0.0, 0.0031308, 0.214, 1.0, 7.0]))
    assert out.dtype == np.uint8 and out[0] == 0 and out[-1] == 255 and out[-2] == 255
    assert 126 <= out[2] <= 129  # linear 0.214 is sRGB ~0.5


def good_sample(h=4, w=4):
    rng = np.random.default_rng(0)
    a, d, s = rng.random((h, w, 3)), rng.random((h, w, 3)), rng.random((h, w, 3))
    n = rng.normal(size=(h, w, 3))
    return {"__key__": "train_0000_v00_l00", "image": a * d + s, "albedo": a, "diffuse": d, "specular": s,
            "ball": rng.random((2, 2, 3)), "normal": n / np.linalg.norm(n, axis=-1, keepdims=True),
            "roughness": rng.random((h, w, 1)), "metallic": rng.random((h, w, 1)),
            "mask": np.ones((h, w, 1)),
            "meta": {"scene": "train_0000", "kind": "object", "split": "train", "view": 0, "light": 0,
                     "camera": {}, "light_params": {}}}


def test_valid_sample_passes():
    validate_sample(good_sample(), "somewhere")


@pytest.mark.parametrize("key, value, message", [
    ("albedo", lambda a: np.where(a > 0.5, np.nan, a), "NaN"),
    ("specular", lambda a: np.where(a > 0.5, np.inf, a), "Inf"),
    ("roughness", lambda a: a[:3], "shape"),
    ("metallic", lambda a: a + 2, "outside"),
    ("mask", lambda a: a * 0.5, "0 or 1"),
    ("normal", lambda a: a * 1.5, "outside|longer"),
    ("diffuse", lambda a: a * 2, "albedo \\* diffuse"),
    ("meta", lambda m: {**m, "split": "dev"}, "split"),
])
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
