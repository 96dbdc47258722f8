"""Colour (pilight/data/colour.py): the HDR tone map round-trips, one formula serves numpy and torch,
and the sRGB curve."""

from __future__ import annotations

import numpy as np
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from pilight.data.colour import HDR_MAX, Y_MAX, hdr_to_model, linear_to_srgb, model_to_hdr, srgb_to_linear, tonemap01
from pilight.pictures import srgb_preview, to_uint8

hdr64 = arrays(np.float64, st.integers(1, 32), elements=st.floats(0.0, HDR_MAX))
hdr32 = arrays(np.float32, st.integers(1, 32), elements=st.floats(0.0, 1e3, width=32))


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


def test_curve_anchor_points_and_monotonic():
    x = np.array([0.0, 0.18, 1.0, 4.0, HDR_MAX])
    y = hdr_to_model(x)
    assert y[0] == -1 and np.all(np.diff(y) > 0) and abs(y[1] + 0.15) < 0.01
    assert np.isclose(y[-1], Y_MAX)
    assert np.all(np.isfinite(model_to_hdr(np.array([-5.0, 1.0, 5.0]))))  # wild outputs stay finite
    assert model_to_hdr(np.array([5.0]))[0] <= HDR_MAX * (1 + 1e-6)


def test_srgb_preview():
    out = srgb_preview(np.array([0.0, 0.0031308, 0.214, 1.0, 7.0]))
    assert out.dtype == np.uint8 and out[0] == 0 and out[-1] == 255 and out[-2] == 255
    assert 126 <= out[2] <= 129  # linear 0.214 is sRGB ~0.5


def test_srgb_curve_round_trips_and_is_continuous_at_the_knee():
    x = np.linspace(0.0, 1.0, 10001)
    np.testing.assert_allclose(srgb_to_linear(linear_to_srgb(x)), x, atol=1e-12)
    knee = np.array([0.0031308 * (1 - 1e-9), 0.0031308 * (1 + 1e-9)])
    assert abs(np.diff(linear_to_srgb(knee))[0]) < 1e-6  # the line meets the power law
    assert abs(float(linear_to_srgb(np.float64(0.214))) - 0.5) < 2e-3


@given(arrays(np.float32, st.integers(1, 64), elements=st.floats(-1.0, 2.0, width=32)))
def test_srgb_curve_same_on_numpy_and_torch(x):
    inside = np.clip(x, 0.0, 1.0)  # callers clip: the curve's domain
    t = torch.from_numpy(inside)
    np.testing.assert_allclose(linear_to_srgb(t).numpy(), linear_to_srgb(inside), rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(srgb_to_linear(t).numpy(), srgb_to_linear(inside), rtol=1e-6, atol=1e-7)


def test_srgb_gradient_is_finite_at_black():
    x = torch.tensor([0.0, 1e-8, 0.5], requires_grad=True)
    linear_to_srgb(x).sum().backward()
    assert torch.isfinite(x.grad).all() and x.grad[0] == 12.92


def test_eps_is_the_only_difference_of_the_physics_tone_map():
    x = torch.tensor([0.0, 0.18, 1.0, 50.0])
    assert torch.equal(hdr_to_model(x, eps=0.0), hdr_to_model(x))
    torch.testing.assert_close(hdr_to_model(x, eps=1e-3), hdr_to_model(x + 1e-3))
    z = torch.zeros(3, requires_grad=True)
    hdr_to_model(z, eps=1e-6).sum().backward()
    assert torch.isfinite(z.grad).all()


def test_uint8_tiles():
    x = torch.tensor([0.0, 0.18, 1.0, 4.0]).view(1, 2, 2)  # one channel: replicated to three
    u = to_uint8(x, hdr=True)
    assert u.shape == (2, 2, 3) and u.dtype == np.uint8
    assert u[..., 0].ravel().tolist() == srgb_preview(np.array([0.0, 0.18, 1.0, 4.0])).tolist() == [0, 118, 255, 255]
    d = to_uint8(tonemap01(x), hdr=False)  # display values (hdr_to_model + 1) / 2, +0.5 then truncated
    want = np.floor((hdr_to_model(np.array([0.0, 0.18, 1.0, 4.0])) + 1) / 2 * 255 + 0.5)
    assert d[..., 0].ravel().tolist() == want.tolist()
