"""Metrics against known values: PSNR of known noise, SSIM of identical images, angular error of
rotated normals, MAE, empty masks, the Table-1 layout."""

from __future__ import annotations

import math

import pytest
import torch

from pilight.eval.intrinsics import table1
from pilight.eval.metrics import (
    angular_errors,
    masked_mae,
    masked_psnr,
    normal_metrics,
    psnr_from_mse,
    psnr_per_image,
    ssim_per_image,
)


def test_psnr_of_known_noise():
    g = torch.full((2, 3, 16, 16), 0.5)
    mask = torch.ones(2, 1, 16, 16)
    noise = torch.where(torch.rand(g.shape, generator=torch.Generator().manual_seed(0)) > 0.5, 0.1, -0.1)
    assert masked_psnr(g + noise, g, mask) == pytest.approx(20.0, abs=1e-4)  # MSE 0.01 -> 20 dB
    assert float(psnr_per_image(g + noise, g).mean()) == pytest.approx(20.0, abs=1e-4)
    assert psnr_from_mse(1e-4) == pytest.approx(40.0) and psnr_from_mse(0.0) == math.inf


def test_ssim_of_identical_images_is_one_and_drops_with_noise():
    x = torch.rand(2, 3, 32, 32, generator=torch.Generator().manual_seed(1))
    assert torch.allclose(ssim_per_image(x, x), torch.ones(2))
    assert float(ssim_per_image((x + 0.2 * torch.randn(x.shape)).clamp(0, 1), x).max()) < 0.95


@pytest.mark.parametrize("degrees", [0.0, 5.0, 30.0, 90.0])
def test_angular_error_of_rotated_normals(degrees):
    g = torch.nn.functional.normalize(torch.randn(1, 3, 8, 8, generator=torch.Generator().manual_seed(2)), dim=1)
    a = math.radians(degrees)
    rot = torch.tensor([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]])
    # Rotating every normal about z by `degrees` moves it by that angle only if it lies in the xy-plane.
    g[:, 2] = 0
    g = torch.nn.functional.normalize(g, dim=1)
    p = torch.einsum("ij,bjhw->bihw", rot, g)
    err = angular_errors(p, g, torch.ones(1, 1, 8, 8))
    assert torch.allclose(err, torch.full_like(err, degrees), atol=1e-2)
    m = normal_metrics(err)
    assert m["mean_deg"] == pytest.approx(degrees, abs=1e-2) and m["within_11.25"] == (1.0 if degrees < 11.25 else 0.0)


def test_mae_and_empty_masks():
    g, p = torch.zeros(1, 1, 4, 4), torch.full((1, 1, 4, 4), 0.25)
    mask = torch.zeros(1, 1, 4, 4)
    mask[..., :2, :] = 1
    assert masked_mae(p, g, mask) == pytest.approx(0.25)
    empty = torch.zeros_like(mask)
    assert masked_mae(p, g, empty) is None and masked_psnr(p, g, empty) is None
    assert normal_metrics(torch.zeros(0))["mean_deg"] is None


def test_table1_has_each_domain_and_the_average():
    gen = torch.Generator().manual_seed(3)
    gt = {
        "albedo": torch.rand(2, 3, 32, 32, generator=gen),
        "normal": torch.rand(2, 3, 32, 32, generator=gen) * 2 - 1,
        "roughness": torch.rand(2, 1, 32, 32, generator=gen),
        "metallic": torch.rand(2, 1, 32, 32, generator=gen),
    }
    mask = torch.ones(2, 1, 32, 32)
    same = table1(gt, gt, mask)
    assert set(same) == {"albedo", "normal", "roughness", "metallic", "average"}
    assert same["average"]["ssim"] == pytest.approx(1.0, abs=1e-5) and same["average"]["lpips"] is None
    noisy = table1({k: v + 0.05 for k, v in gt.items()}, gt, mask)
    assert noisy["albedo"]["psnr"] < 30 and noisy["average"]["ssim"] < 1.0
