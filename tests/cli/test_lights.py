"""Light specs -> light balls: the documented direction and HDRI conventions."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pilight import lights
from pilight.lights import LightError


def side_means(ball: torch.Tensor) -> tuple[float, float, float, float]:
    """Mean of the left, right, top and bottom halves of a (3, S, S) ball."""
    s = ball.shape[-1] // 2
    return (
        float(ball[:, :, :s].mean()),
        float(ball[:, :, s:].mean()),
        float(ball[:, :s].mean()),
        float(ball[:, s:].mean()),
    )


def test_named_lights_light_the_side_they_name():
    left, right, top, bottom = (side_means(lights.named(n).ball) for n in ("left", "right", "top", "bottom"))
    assert left[0] > 2 * left[1] and right[1] > 2 * right[0]
    assert top[2] > 2 * top[3] and bottom[3] > 2 * bottom[2]
    front = lights.named("front").ball
    c = front.shape[-1] // 2
    assert float(front[:, c, c].mean()) == pytest.approx(float(front.amax()), rel=0.02)  # brightest facing the camera


def test_azimuth_and_elevation_convention():
    d = lights.direction
    np.testing.assert_allclose(d(0, 0), [0, 0, 1], atol=1e-6)  # from the camera
    np.testing.assert_allclose(d(90, 0), [1, 0, 0], atol=1e-6)  # from the right
    np.testing.assert_allclose(d(-90, 0), [-1, 0, 0], atol=1e-6)
    np.testing.assert_allclose(d(0, 90), [0, 1, 0], atol=1e-6)  # from above


def test_intensity_scales_the_light():
    np.testing.assert_allclose(lights.named("left", intensity=3.0).ball, 3.0 * lights.named("left").ball, rtol=1e-5)


def test_hdri_centre_is_ahead_and_rotate_turns_it_clockwise():
    h, w = 32, 64
    pano = np.zeros((h, w, 3), np.float32)
    pano[h // 2 - 4 : h // 2 + 4, w // 4 - 4 : w // 4 + 4] = 50.0  # a bright patch at the left quarter
    left = lights.from_hdri(pano, 0.0, size=32).ball
    l, r, _, _ = side_means(left)
    assert l > 2 * r  # the left quarter of the panorama lights the ball's left
    ahead = lights.from_hdri(pano, 90.0, size=32).ball  # +90: what was on the left is now straight ahead
    l2, r2, _, _ = side_means(ahead)
    assert abs(l2 - r2) < 0.1 * (l2 + r2)
    # Straight ahead of the camera is behind the subject: the ball's rim, not its centre, gets it.
    c = ahead.shape[-1] // 2
    assert float(ahead[:, c, c].mean()) < float(lights.from_hdri(pano, -90.0, size=32).ball[:, c, c].mean())


def test_bad_light_specs_say_what_is_wrong(tmp_path):
    with pytest.raises(LightError, match="unknown light 'sideways'"):
        lights.named("sideways")
    with pytest.raises(LightError, match="2:1"):
        lights.from_hdri(np.ones((10, 30, 3), np.float32), name="wide.exr")
    with pytest.raises(LightError, match="--elevation"):
        lights.parse_lights(azimuths=[10.0])
    with pytest.raises(LightError, match="no light given"):
        lights.parse_lights()
    with pytest.raises(LightError, match="more than once"):
        lights.parse_lights(names=["left", "left"])
    with pytest.raises(LightError, match="square"):
        lights.from_ball(np.ones((10, 12, 3), np.float32), name="ball.exr")
    missing = tmp_path / "nope.exr"
    with pytest.raises(LightError, match="nope.exr"):
        lights.parse_lights(hdris=[missing])


def test_one_hdri_with_several_rotations_gives_one_light_each():
    import pathlib
    import tempfile

    from pilight.data.exr import write_exr

    with tempfile.TemporaryDirectory() as d:
        path = pathlib.Path(d) / "env.exr"
        write_exr(path, np.ones((16, 32, 3), np.float32), half=True)
        ls = lights.parse_lights(hdris=[path], rotates=[0.0, 90.0, 180.0], size=16)
    assert [l.name for l in ls] == ["hdri-env", "hdri-env_rot90", "hdri-env_rot180"]
