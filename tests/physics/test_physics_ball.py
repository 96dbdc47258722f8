"""Light balls made without rendering: distant light and Blender-world HDRI."""

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from physics_bruteforce import ball_pixel_normals, irradiance, smooth_env

from pilight.physics import ball_from_direction, ball_from_hdri, ball_from_light, ball_normals, hdri_directions


def _rot_z(deg):
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


# Blender camera at the origin looking along world +x, z up: camera x = world -y,
# camera y = world z, camera z (toward the viewer) = world -x.
W2C_LOOK_PLUS_X = torch.tensor([[0.0, -1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, 0.0, 0.0]])


unit3 = st.tuples(*[st.floats(-1, 1)] * 3).filter(lambda v: 0.1 < np.linalg.norm(v))


@settings(max_examples=30, deadline=None)
@given(l=unit3, intensity=st.floats(0.0, 10.0), ambient=st.floats(0.0, 2.0))
def test_ball_from_direction_analytic(l, intensity, ambient):
    size = 32
    ball = ball_from_light(direction=torch.tensor(l), intensity=intensity, ambient=ambient, size=size)
    n, inside = ball_pixel_normals(size)
    lu = np.array(l) / np.linalg.norm(l)
    ref = 0.5 * (intensity * np.clip(n @ lu, 0, None) + ambient) * inside
    assert ball.shape == (1, 3, size, size)
    np.testing.assert_allclose(ball[0].numpy(), np.broadcast_to(ref, (3, size, size)), atol=1e-5, rtol=1e-5)


def test_ball_from_direction_batched_colour():
    ball = ball_from_direction(
        torch.tensor([[0, 0, 1.0], [1.0, 0, 0]]), intensity=torch.tensor([[1.0, 2.0, 3.0], [1.0, 1.0, 1.0]]), size=16
    )
    assert ball.shape == (2, 3, 16, 16)
    centre = ball[0, :, 7:9, 7:9].mean((1, 2))
    torch.testing.assert_close(centre / centre[0], torch.tensor([1.0, 2.0, 3.0]), atol=1e-5, rtol=0)
    assert ball[1, :, :, :8].max() == 0  # light from +x leaves the left half dark


def test_hdri_constant_gives_D_equals_L():
    L = torch.tensor([0.3, 1.0, 7.5])
    hdri = L[:, None, None].expand(3, 64, 128)
    ball = ball_from_hdri(hdri, _rot_z(37.0), size=32)
    _, inside = ball_normals(32, 32)
    torch.testing.assert_close(ball[0] / 0.5, L[:, None, None] * inside[0], atol=1e-5, rtol=1e-5)


def test_hdri_convention_matches_cycles():
    """Measured with bpy 5.0.1 / Cycles: the image centre column is world +x, the quarter column +y.

    (Cycles direction_to_equirectangular: u = 0.5 - atan2(d_y, d_x) / 2pi.)
    """
    d, _ = hdri_directions(8, 16)
    np.testing.assert_allclose(d[:, 3:5, 7:9].mean((1, 2)) / d[:, 3:5, 7:9].mean((1, 2)).norm(), [1, 0, 0], atol=1e-6)
    np.testing.assert_allclose(d[:, 3:5, 3:5].mean((1, 2)) / d[:, 3:5, 3:5].mean((1, 2)).norm(), [0, 1, 0], atol=1e-6)
    assert torch.all(d[2, 0] > 0.9)  # row 0 = zenith


@pytest.mark.parametrize("yaw", [0.0, 90.0, -135.0])
def test_hdri_bright_direction_lights_facing_side(yaw):
    """A sun at world +x; the camera looks along world +x yawed by `yaw` about z.

    Ball pixels whose normal faces the rotated sun direction are lit, those
    facing away are black.  yaw = 0 looks straight at the sun: it is behind the
    ball (camera -z), so the whole visible ball is (nearly) black.
    """
    h, w = 64, 128
    hdri = torch.zeros(1, 3, h, w)
    hdri[..., 30:34, 62:66] = 1000.0  # around the image centre = world +x, on the horizon
    R = W2C_LOOK_PLUS_X @ _rot_z(-yaw)  # world -> camera for a camera yawed by `yaw`
    sun_cam = R @ torch.tensor([1.0, 0.0, 0.0])
    ball = ball_from_hdri(hdri, R, size=64)
    n, inside = ball_normals(64, 64)
    facing = ((n * sun_cam[None, :, None, None]).sum(1, keepdim=True) > 0.3) & (inside > 0)
    away = ((n * sun_cam[None, :, None, None]).sum(1, keepdim=True) < -0.2) & (inside > 0)
    if facing.any():
        assert ball[:, :, facing[0, 0]].mean() > 10 * ball[:, :, away[0, 0]].mean().clamp_min(1e-6)
    assert ball[:, :, away[0, 0]].max() == 0  # sun patch (+-8 deg) is > 90 deg from these normals


def test_hdri_sun_to_the_right():
    """Camera looks along world +y (yaw 90); a sun at world +x is then on the camera's right."""
    hdri = torch.zeros(3, 64, 128)
    hdri[:, 30:34, 62:66] = 1000.0
    R = W2C_LOOK_PLUS_X @ _rot_z(-90.0)
    torch.testing.assert_close(R @ torch.tensor([0.0, 1.0, 0.0]), torch.tensor([0.0, 0.0, -1.0]))
    ball = ball_from_hdri(hdri, R, size=64)
    assert ball[..., 40:].mean() > 10 * ball[..., :24].mean().clamp_min(1e-6)


def test_hdri_vs_bruteforce():
    """ball_from_hdri on a smooth world environment vs numpy integration (1% of max D)."""
    fn = smooth_env(7)
    h, w = 128, 256
    d_world, _ = hdri_directions(h, w, dtype=torch.float64)
    hdri = torch.tensor(fn(d_world.reshape(3, -1).T.numpy()).T.reshape(3, h, w))
    R = W2C_LOOK_PLUS_X.double() @ _rot_z(25.0).double()
    ball = ball_from_hdri(hdri, R, size=24)[0]
    n, inside = ball_pixel_normals(24)
    n_world = n.reshape(-1, 3)[inside.reshape(-1)] @ R.numpy()  # R^T n, row vectors
    ref = 0.5 * irradiance(n_world, fn)
    got = ball.reshape(3, -1).T.numpy()[inside.reshape(-1)]
    assert np.abs(got - ref).max() / ref.max() < 0.01


def test_ball_from_light_requires_one_source():
    with pytest.raises(ValueError):
        ball_from_light()
    with pytest.raises(ValueError):
        ball_from_light(direction=[0, 0, 1.0], hdri=torch.zeros(3, 8, 16))
    with pytest.raises(ValueError, match="world_to_camera"):
        ball_from_light(hdri=torch.zeros(3, 8, 16))
