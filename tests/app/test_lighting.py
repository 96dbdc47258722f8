"""The app's ball picker and light mixing (pilight/app/lighting.py)."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from pilight.app.lighting import (
    MAX_LIGHTS,
    LightSpec,
    hex_colour,
    mix,
    picker_direction,
    picker_picture,
    picker_position,
)
from pilight.lights import LightError, directional
from pilight.physics.envmap import light_level

SIZE = 256


@pytest.mark.parametrize(
    "xy, azimuth, elevation",
    [
        ((SIZE / 2 - 0.5, SIZE / 2 - 0.5), 0.0, 0.0),  # the centre faces the camera: light from the camera
        ((SIZE - 0.5, SIZE / 2 - 0.5), 90.0, 0.0),  # the right rim: from the right
        ((-0.5, SIZE / 2 - 0.5), -90.0, 0.0),  # the left rim: from the left
        ((SIZE / 2 - 0.5, -0.5), 0.0, 90.0),  # the top: from above
        ((SIZE * 2, SIZE / 2 - 0.5), 90.0, 0.0),  # off the disk: taken to the rim
    ],
)
def test_the_picker_says_where_the_light_comes_from(xy, azimuth, elevation):
    a, e = picker_direction(*xy, SIZE)
    assert a == pytest.approx(azimuth, abs=1e-6) and e == pytest.approx(elevation, abs=1e-6)


@settings(max_examples=60, deadline=None)
@given(st.floats(-89.0, 89.0), st.floats(-89.0, 89.0))
def test_a_light_sits_where_it_was_placed(azimuth, elevation):
    at = picker_position(azimuth, elevation, SIZE)
    assert at is not None
    a, e = picker_direction(*at, SIZE)
    assert a == pytest.approx(azimuth, abs=1e-6) and e == pytest.approx(elevation, abs=1e-6)


def test_the_brightest_point_of_the_lit_ball_is_where_the_light_was_placed():
    picture = picker_picture([LightSpec(50.0, 20.0)], SIZE).astype(float).sum(2)
    y, x = divmod(int(picture.argmax()), SIZE)
    a, e = picker_direction(x, y, SIZE)
    assert math.hypot(a - 50.0, e - 20.0) < 8.0  # within a few pixels of the marker's ring
    assert picker_position(150.0, 0.0, SIZE) is None  # behind the ball: no marker


def test_a_mix_is_the_lights_together_at_the_level_of_their_intensities():
    left, right = LightSpec(-90, 30, 1.0), LightSpec(90, 30, 2.0, (1.0, 0.5, 0.25))
    m = mix([left.light(), right.light()])
    assert m.intensity == 3.0 and float(light_level(m.ball[None])) == pytest.approx(3.0, rel=1e-5)
    unit = lambda spec: spec.light().ball / light_level(spec.light().ball[None])[0]  # noqa: E731
    torch.testing.assert_close(m.ball, unit(left) * 1.0 + unit(right) * 2.0, rtol=1e-5, atol=1e-6)
    one = directional(10, 20)
    assert mix([one]) is one
    with pytest.raises(LightError, match="no light"):
        mix([])
    with pytest.raises(LightError, match=f"at most {MAX_LIGHTS}"):
        mix([one] * (MAX_LIGHTS + 1))


def test_colours_are_read_from_the_picker_or_refused():
    assert hex_colour("#ff8000") == (1.0, 128 / 255, 0.0)
    for bad in ("red", "#ff80", "", "#gg0000"):
        with pytest.raises(LightError, match="#rrggbb"):
            hex_colour(bad)
    tinted = LightSpec(0, 0, 1.0, (1.0, 0.0, 0.0)).light().ball
    assert float(tinted[1:].abs().max()) == 0.0 and float(tinted[0].max()) > 0
