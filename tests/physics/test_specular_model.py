"""The microfacet specular anchor (pilight.physics.specular_model): the light fitted to a ball, the
closed form at normal incidence, where the highlight sits, and what roughness does to it."""

from __future__ import annotations

import math

import pytest
import torch

from pilight.physics.shading import ball_from_direction
from pilight.physics.specular_model import fit_directional, ggx_specular, principled_f0, specular_from_ball


def _unit(v):
    v = torch.tensor(v, dtype=torch.float32)
    return v / v.norm()


@pytest.mark.parametrize("direction", [(0.3, 0.5, 0.8), (-0.7, 0.2, 0.4), (0.0, 0.9, -0.3), (0.5, -0.2, 0.1)])
def test_fit_recovers_an_analytic_light(direction):
    """A Lambertian ball of one distant light and a constant environment gives back its direction
    (within the 2048-direction search's ~4 degrees), intensity and ambient, colour by colour."""
    l0 = _unit(direction)
    intensity, ambient = torch.tensor([[2.0, 1.0, 0.5]]), torch.tensor([[0.1, 0.05, 0.2]])
    ball = ball_from_direction(l0, intensity, ambient, size=32)
    l, i, a = fit_directional(ball)
    assert math.degrees(math.acos(float((l[0] * l0).sum().clamp(-1, 1)))) < 4.0
    torch.testing.assert_close(i, intensity, rtol=0.08, atol=0.02)
    torch.testing.assert_close(a, ambient, rtol=0.1, atol=0.02)


def test_closed_form_with_light_at_the_camera():
    """n = l = v = +z: D = 1/(pi alpha^2), V = 1/4, F = F0, so S = I F0 / (4 alpha^2) + a F0."""
    n = torch.tensor([0.0, 0.0, 1.0]).reshape(1, 3, 1, 1)
    r, f0 = 0.5, 0.04
    s = ggx_specular(
        n,
        torch.full((1, 1, 1, 1), r),
        torch.full((1, 1, 1, 1), f0),
        torch.tensor([[0.0, 0.0, 1.0]]),
        torch.tensor([[3.0, 3.0, 3.0]]),
        torch.tensor([[0.2, 0.2, 0.2]]),
    )
    torch.testing.assert_close(s.flatten(), torch.full((3,), 3.0 * f0 / (4 * r**4) + 0.2 * f0))


def _sphere(h=33):
    y, x = torch.meshgrid(1 - 2 * (torch.arange(h) + 0.5) / h, 2 * (torch.arange(h) + 0.5) / h - 1, indexing="ij")
    inside = (x**2 + y**2) < 1
    n = torch.stack([x, y, (1 - x**2 - y**2).clamp_min(0).sqrt()]) * inside
    return n[None]


def test_highlight_sits_at_the_half_vector_and_sharpens_with_smoothness():
    n = _sphere()
    l = _unit((0.6, 0.3, 0.7))
    h = l + torch.tensor([0.0, 0.0, 1.0])
    h = h / h.norm()
    peaks = {}
    for r in (0.2, 0.6):
        s = ggx_specular(
            n,
            torch.full((1, 1, 33, 33), r),
            torch.full((1, 1, 33, 33), 0.04),
            l[None],
            torch.ones(1, 3),
            torch.zeros(1, 3),
        )[0, 0]
        at = divmod(int(s.argmax()), 33)
        assert float((n[0, :, at[0], at[1]] * h).sum()) > 0.99  # the brightest normal is the half vector
        peaks[r] = (float(s.max()), int((s > 0.5 * s.max()).sum()))
    assert peaks[0.2][0] > 4 * peaks[0.6][0] and peaks[0.2][1] < peaks[0.6][1]  # smoother: brighter, smaller


def test_metals_reflect_their_base_colour_and_dielectrics_do_not():
    a = torch.tensor([0.9, 0.5, 0.1]).reshape(1, 3, 1, 1)
    torch.testing.assert_close(principled_f0(a, torch.ones(1, 1, 1, 1)), a)
    torch.testing.assert_close(principled_f0(a, torch.zeros(1, 1, 1, 1)), torch.full((1, 3, 1, 1), 0.04))
    n = _sphere(9)
    ball = ball_from_direction(_unit((0.2, 0.2, 1.0)), 2.0, 0.05, size=32)
    s = specular_from_ball(ball, n, torch.full((1, 1, 9, 9), 0.3), a.expand(1, 3, 9, 9), torch.ones(1, 1, 9, 9))
    lit = s[0, 0] > 0
    assert lit.any() and bool((s[0, 0] >= s[0, 1]).all() and (s[0, 1] >= s[0, 2]).all())
    assert float(s[0, :, 0, 0].abs().sum()) == 0.0  # off the sphere (normal 0): nothing


@pytest.mark.parametrize("direction", [(0.3, 0.5, 0.8), (-0.7, 0.2, 0.4), (0.5, -0.2, 0.1)])
def test_the_anchor_is_computed_in_fp32_under_a_bf16_loop(direction):
    """Training and inference run under bf16 autocast; the light fit's closed form subtracts nearly equal
    sums, which bf16 matrix products turn to noise (base stage 2 went NaN at step 626 of a bf16 run).
    The fit and the GGX anchor give the fp32 result, finite, whatever autocast the caller has on."""
    ball = ball_from_direction(_unit(direction), torch.tensor([[2.0, 1.0, 0.5]]), torch.tensor([[0.1, 0.05, 0.2]]), 32)
    g = torch.Generator().manual_seed(0)
    normal = torch.nn.functional.normalize(torch.randn(1, 3, 16, 16, generator=g), dim=1)
    normal[:, 2] = normal[:, 2].abs()
    roughness, albedo = torch.rand(1, 1, 16, 16, generator=g), torch.rand(1, 3, 16, 16, generator=g)
    metallic = (torch.rand(1, 1, 16, 16, generator=g) > 0.5).float()
    exact_fit = fit_directional(ball)
    exact = specular_from_ball(ball, normal, roughness, albedo, metallic)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        fit = fit_directional(ball)
        s = specular_from_ball(ball, normal, roughness, albedo, metallic)
    for a, b in zip(fit, exact_fit):
        assert a.dtype == torch.float32
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    assert s.dtype == torch.float32 and torch.isfinite(s).all()
    torch.testing.assert_close(s, exact, rtol=0, atol=0)
