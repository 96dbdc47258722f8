"""Numerical stability at the extremes, low precision, and float64 gradcheck."""

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from pilight.physics import (
    ball_from_direction,
    ball_normals,
    ball_to_envmap,
    diffuse_shading,
    diffuse_shading_loss,
    normal_to_uv,
)


def _env(intensity=2.0, ambient=0.3, l=(0.3, 0.5, 0.8), size=64, dtype=torch.float32):
    return ball_to_envmap(ball_from_direction(torch.tensor(l), intensity, ambient, size=size).to(dtype))


def _extreme_normals():
    """Poles, silhouette (n_z = 0, incl. the u = +-0.5 seam), back seam (n_x = 0, n_z < 0), zeros."""
    s = 1 / math.sqrt(2)
    n = torch.tensor(
        [
            [0, 1, 0],
            [0, -1, 0],
            [1, 0, 0],
            [-1, 0, 0],
            [s, s, 0],
            [-s, -s, 0],
            [0, 0, -1],
            [0, s, -s],
            [0, 0, 0],
            [0, 0, 1],
            [1e-8, 1 - 1e-8, 0],
        ],
        dtype=torch.float32,
    )
    return n.T.reshape(1, 3, 1, -1).contiguous()


def test_extreme_normals_value_and_grad_finite():
    env, _ = _env(size=256)
    env.requires_grad_(True)
    n = _extreme_normals().requires_grad_(True)
    d = diffuse_shading(env, n)
    assert torch.isfinite(d).all()
    d.sum().backward()
    assert torch.isfinite(n.grad).all() and torch.isfinite(env.grad).all()
    uv = normal_to_uv(n.detach())
    assert uv.abs().max() <= 1.0
    # poles lie on the ball's silhouette: silhouette tolerance 0.16 I (test_physics_envmap)
    ly = 0.5 / math.sqrt(0.98)
    torch.testing.assert_close(d[0, 0, 0, 0], torch.tensor(2 * ly + 0.3), atol=0.32, rtol=0)
    torch.testing.assert_close(d[0, 0, 0, 1], torch.tensor(0.3), atol=0.32, rtol=0)


def test_zero_normals_masked_out_with_finite_grad():
    env, _ = _env()
    n = torch.zeros(2, 3, 8, 8, requires_grad=True)
    mask = torch.zeros(2, 1, 8, 8)
    d = diffuse_shading(env, n, mask)
    assert torch.equal(d, torch.zeros_like(d))
    d.sum().backward()
    assert torch.isfinite(n.grad).all()
    n2 = torch.zeros(1, 3, 4, 4, requires_grad=True)  # unmasked zeros: finite too
    diffuse_shading(env, n2).sum().backward()
    assert torch.isfinite(n2.grad).all()


def test_empty_mask_loss_is_zero():
    d_calc = torch.rand(2, 3, 8, 8)
    d_pred = torch.rand(2, 3, 8, 8, requires_grad=True)
    loss = diffuse_shading_loss(d_calc, d_pred, torch.zeros(2, 1, 8, 8))
    assert loss.item() == 0.0
    loss.backward()
    assert torch.equal(d_pred.grad, torch.zeros_like(d_pred))


def test_black_ball():
    env, valid = ball_to_envmap(torch.zeros(1, 3, 32, 32, requires_grad=True))
    assert torch.equal(env, torch.zeros_like(env)) and valid.sum() == 16 * 16
    n, inside = ball_normals(16, 16)
    assert torch.equal(diffuse_shading(env, n, inside), torch.zeros(1, 3, 16, 16))


def test_hdr_ball_is_linear():
    ball = ball_from_direction(torch.tensor([0.2, 0.6, 0.7]), 1.0, 0.1, size=64)
    n, inside = ball_normals(32, 32)
    d1 = diffuse_shading(ball_to_envmap(ball)[0], n, inside)
    big = (ball * 1e4).requires_grad_(True)
    env_big, _ = ball_to_envmap(big)
    d_big = diffuse_shading(env_big, n, inside)
    assert torch.isfinite(d_big).all() and d_big.max() > 1e4
    torch.testing.assert_close(d_big, d1 * 1e4, rtol=1e-5, atol=1e-2)
    d_big.sum().backward()
    assert torch.isfinite(big.grad).all()


def _rel(a, b):
    return ((a.float() - b).norm() / b.norm()).item()


@pytest.mark.parametrize("dtype,bound", [(torch.bfloat16, 5e-3), (torch.float16, 6e-4)])
def test_low_precision_close_to_fp32(dtype, bound):
    """Whole chain in low precision vs fp32 on the same inputs; bounds ~2x the measured error."""
    torch.manual_seed(0)
    ball = ball_from_direction(torch.tensor([0.3, 0.5, 0.8]), 3.0, 0.2, size=128)
    n = torch.randn(2, 3, 32, 32)
    n[:, 2] = n[:, 2].abs()
    n = n / n.norm(dim=1, keepdim=True)
    n[0, :, 0, :4] = 0  # zero normals
    n[0, :, 1, 0] = torch.tensor([0.0, 1.0, 0.0])  # pole
    env32, _ = ball_to_envmap(ball)
    d32 = diffuse_shading(env32, n)
    env_lo, valid_lo = ball_to_envmap(ball.to(dtype))
    assert env_lo.dtype == dtype and valid_lo.dtype == dtype
    d_lo = diffuse_shading(env_lo, n.to(dtype))
    assert d_lo.dtype == dtype and torch.isfinite(d_lo).all()
    rel_env, rel_d = _rel(env_lo, env32), _rel(d_lo, d32)
    print(f"{dtype}: rel err envmap {rel_env:.2e}, D_calculated {rel_d:.2e}")
    assert rel_env < bound and rel_d < bound
    loss_lo = diffuse_shading_loss(d_lo, d_lo.detach() * 0.9, torch.ones(2, 1, 32, 32, dtype=dtype))
    loss32 = diffuse_shading_loss(d32, d32 * 0.9, torch.ones(2, 1, 32, 32))
    assert torch.isfinite(loss_lo) and abs(loss_lo.float().item() / loss32.item() - 1) < 10 * bound


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 10_000))
def test_random_normals_finite_grad(seed):
    g = torch.Generator().manual_seed(seed)
    n = torch.randn(1, 3, 6, 6, generator=g)
    n[0, :, 0, 0] = 0
    n = n.requires_grad_(True)
    env = torch.rand(1, 3, 16, 32, generator=g, requires_grad=True)
    diffuse_shading(env, n).pow(2).sum().backward()
    assert torch.isfinite(n.grad).all() and torch.isfinite(env.grad).all()


def test_gradcheck_diffuse_shading():
    g = torch.Generator().manual_seed(0)
    # away from poles/seam (kinks of the clamp and atan2 branch cut are not differentiable)
    n = torch.randn(1, 3, 3, 3, generator=g, dtype=torch.float64)
    n[:, 2] = n[:, 2].abs() + 0.5
    n[:, 1] = n[:, 1].clamp(-0.8, 0.8)
    n.requires_grad_(True)
    env = torch.rand(1, 2, 16, 32, generator=g, dtype=torch.float64, requires_grad=True)
    mask = torch.ones(1, 1, 3, 3, dtype=torch.float64)
    assert torch.autograd.gradcheck(diffuse_shading, (env, n, mask), eps=1e-6, atol=1e-5)


def test_gradcheck_ball_to_envmap():
    ball = torch.rand(1, 3, 12, 12, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda b: ball_to_envmap(b)[0], (ball,), eps=1e-6, atol=1e-5)


# --- issue 18: damaged inputs are refused or masked, never spread silently --------------------
def test_masked_mse_fp16_accumulates_in_fp32():
    from pilight.physics import masked_mse

    # 3 x 256^2 valid values per sample: the old fp16 denominator overflowed to inf and the loss read 0.
    g = torch.Generator().manual_seed(0)
    a, b = torch.rand(4, 3, 256, 256, generator=g), torch.rand(4, 3, 256, 256, generator=g)
    mask = torch.ones(4, 1, 256, 256)
    ref = masked_mse(a.double(), b.double(), mask.double())
    got = masked_mse(a.half(), b.half(), mask.half())
    assert got.dtype == torch.float32
    assert float(got) == pytest.approx(float(ref), rel=1e-3) and float(ref) == pytest.approx(1 / 6, rel=0.02)


def test_masked_mse_ignores_nan_in_masked_out_pixels_value_and_grad():
    from pilight.physics import masked_mse

    a = torch.rand(2, 3, 4, 4, requires_grad=True)
    b = torch.rand(2, 3, 4, 4)
    mask = torch.ones(2, 1, 4, 4)
    mask[:, :, 0, 0] = 0
    b_nan = b.clone()
    b_nan[:, :, 0, 0] = float("nan")
    loss = masked_mse(a, b_nan, mask)
    assert torch.isfinite(loss) and torch.equal(loss, masked_mse(a, b, mask))
    loss.backward()
    assert torch.isfinite(a.grad).all()


def test_masked_mse_fp32_values_unchanged():
    from pilight.physics import masked_mse

    # Correct runs must keep their bits: the where-select equals the old multiply wherever the mask is > 0.
    g = torch.Generator().manual_seed(1)
    a, b = torch.rand(3, 3, 8, 8, generator=g), torch.rand(3, 3, 8, 8, generator=g)
    mask = (torch.rand(3, 1, 8, 8, generator=g) > 0.4).float()
    err = (a - b).square()
    old = (err * mask).flatten(1).sum(1) / mask.expand_as(err).flatten(1).sum(1).clamp_min(1e-8)
    assert torch.equal(masked_mse(a, b, mask, reduction="none"), old)


def test_nan_ball_texel_inside_the_disk_is_refused():
    ball = ball_from_direction(torch.tensor([0.3, 0.5, 0.8]), 2.0, 0.3, size=16)
    ball[0, 1, 8, 8] = float("nan")
    with pytest.raises(ValueError, match=r"ball_to_envmap: light ball.*NaN/Inf.*\[0, 1, 8, 8\]"):
        ball_to_envmap(ball)
    ball[0, 1, 8, 8] = float("inf")
    with pytest.raises(ValueError, match="non-finite"):
        ball_to_envmap(ball)


def test_nan_ball_pixel_outside_the_valid_mask_is_masked():
    ball = ball_from_direction(torch.tensor([0.3, 0.5, 0.8]), 2.0, 0.3, size=16)
    env, valid = ball_to_envmap(ball)
    outside = ball_normals(16, 16)[1].expand_as(ball) == 0
    damaged = torch.where(outside, torch.tensor(float("nan")), ball)  # every pixel off the disk, rim neighbours too
    env2, valid2 = ball_to_envmap(damaged)
    assert torch.equal(env, env2) and torch.equal(valid, valid2)


def test_nan_normal_is_refused_by_diffuse_shading():
    n = _extreme_normals()
    n[0, 2, 0, 3] = float("nan")
    with pytest.raises(ValueError, match=r"normals: 1 non-finite value"):
        diffuse_shading(_env()[0], n)


def test_empty_ball_is_a_clear_error():
    with pytest.raises(ValueError, match="size 0x0"):
        ball_to_envmap(torch.zeros(1, 3, 0, 0))
    with pytest.raises(ValueError, match="size 0x0"):
        ball_normals(0, 0)
