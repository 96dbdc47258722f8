"""benchmarks/direction_probes.py: a Lambertian shading of the normals reads a sphere's light from the right
side when the normals are right and backwards when their x is negated (a ring read as a filled disc does
this to stage 1's normals); the mean angle and the direction shares are what they say."""

from __future__ import annotations

import torch

from fixtures.script_modules import load_benchmark

direction_probes = load_benchmark("direction_probes")


def sphere(size: int = 32) -> tuple[torch.Tensor, torch.Tensor]:
    """Camera-space normals of a sphere filling the frame (x right, y up, z toward the camera), and its mask."""
    v, u = torch.meshgrid(torch.linspace(1, -1, size), torch.linspace(-1, 1, size), indexing="ij")
    inside = u**2 + v**2 < 0.95
    z = (1 - u**2 - v**2).clamp_min(0).sqrt()
    normal = torch.stack([u, v, z]) * inside
    return normal[None], inside[None, None].float()


def test_true_normals_read_the_right_light_and_mirrored_ones_read_it_backwards():
    normal, mask = sphere()
    right, left = direction_probes.lambert_asymmetry(normal, normal, mask)
    assert right > 0.3 and left < -0.3
    mirrored = normal * torch.tensor([-1.0, 1.0, 1.0]).view(1, 3, 1, 1)
    right_m, left_m = direction_probes.lambert_asymmetry(mirrored, normal, mask)
    assert right_m < left_m
    torch.testing.assert_close(torch.tensor([right_m, left_m]), torch.tensor([left, right]), atol=1e-5, rtol=0)


def test_mean_angle_is_zero_for_the_truth_and_ninety_for_a_quarter_turn():
    normal, mask = sphere()
    assert direction_probes.mean_angle_deg(normal, normal, mask) < 0.1
    turned = torch.zeros_like(normal)
    turned[:, 0] = 1.0  # every pixel facing camera-right: 90 degrees from the sphere's centre, less at its right rim
    sel = mask[:, 0] > 0.5
    expected = torch.rad2deg(torch.acos(normal[:, 0][sel].clamp(-1, 1))).mean()
    assert abs(direction_probes.mean_angle_deg(turned, normal, mask) - float(expected)) < 0.1


def test_shares_count_right_over_left_per_column():
    rows = [
        {"model": [0.5, -0.5], "lambert": [0.2, 0.1], "lambert_gt": [0.9, -0.9]},
        {"model": [-0.1, 0.2], "lambert": [-0.3, 0.1], "lambert_gt": [0.8, -0.7]},
        {"model": [0.3, 0.3], "lambert": [0.4, -0.4], "lambert_gt": [0.6, -0.6]},
    ]
    assert direction_probes.shares(rows) == {"model": 1 / 3, "lambert": 2 / 3, "lambert_gt": 1.0}
