"""benchmarks/normal_frame.py: a prediction that is the truth turned about the camera's x axis is found
turned by exactly that angle, and the camera's pitch is read from the render's pose."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from fixtures.script_modules import load_benchmark

normal_frame = load_benchmark("normal_frame")


def test_a_floor_turned_toward_the_camera_is_found_and_undone():
    gt = F.normalize(torch.randn(3, 500, generator=torch.Generator().manual_seed(1)), dim=0)
    gt[2] = gt[2].abs()  # visible normals face the camera
    pred = normal_frame.turned(gt, 17.0)
    # a floor (0, cos 20, sin 20) turned by +17 degrees is the floor of a camera pitched 37 degrees down
    floor = normal_frame.turned(torch.tensor([[0.0], [math.cos(math.radians(20))], [math.sin(math.radians(20))]]), 17)
    torch.testing.assert_close(floor[:, 0], torch.tensor([0.0, math.cos(math.radians(37)), math.sin(math.radians(37))]))
    phi, err = normal_frame.best_turn(pred, gt, range(-40, 41))
    assert phi == -17.0
    assert err < 0.05  # float32 acos near 1
    assert normal_frame.mean_angle(pred, gt) > 10  # less than 17: a normal along x does not turn


def test_camera_pitch_from_the_pose():
    theta = math.radians(-20)  # looking 20 degrees below the horizon
    # Blender camera: looks down its -z; world_from_camera's third column is the camera's +z in the world
    pose = [[1, 0, 0, 0], [0, math.sin(-theta), -math.cos(theta), 0], [0, math.cos(theta), math.sin(-theta), 0]]
    assert abs(normal_frame.camera_pitch({"camera": {"world_from_camera": pose}}) + 20) < 1e-9
