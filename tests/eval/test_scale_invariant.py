"""Scale-invariant grading against values computed by hand: Grosse's least-squares scale (fitted on the
mask only), si-PSNR, LMSE and the level error."""

from __future__ import annotations

import math

import pytest
import torch

from pilight.eval.metrics import PSNR_CAP, masked_psnr
from pilight.eval.scale_invariant import least_squares_scale, level_error, level_log_ratio, lmse, scaled_to


def _maps(b=3, c=3, size=32, seed=0):
    g = torch.Generator().manual_seed(seed)
    gt = torch.rand(b, c, size, size, generator=g) * 0.8 + 0.1
    mask = (torch.rand(b, 1, size, size, generator=g) > 0.3).float()
    return gt, mask, g


def test_si_psnr_of_a_scaled_copy_of_the_truth_is_the_clamp_value():
    gt, mask, _ = _maps()
    est = gt * torch.tensor([0.5, 2.0, 0.1])[:, None, None, None]  # one (different) scale per image
    assert masked_psnr(est, gt, mask) < 20  # raw PSNR sees the level
    assert masked_psnr(scaled_to(est, gt, mask), gt, mask) == PSNR_CAP
    assert least_squares_scale(est, gt, mask).flatten().tolist() == pytest.approx([2.0, 0.5, 10.0], rel=1e-5)


def test_the_scale_is_fitted_on_the_mask_only():
    """On the mask the estimate is 2 x the truth; off it, anything. A fit over the whole image would not
    give exactly 1/2, and the scaled estimate would not equal the truth on the mask."""
    gt, mask, g = _maps()
    est = torch.where(mask > 0.5, 2 * gt, 50 * torch.rand(gt.shape, generator=g))
    assert least_squares_scale(est, gt, mask).flatten().tolist() == pytest.approx([0.5] * 3, rel=1e-6)
    on = (mask > 0.5).expand_as(gt)
    assert torch.allclose(scaled_to(est, gt, mask)[on], gt[on], atol=1e-6)
    assert masked_psnr(scaled_to(est, gt, mask), gt, mask) == PSNR_CAP
    assert lmse(est, gt, mask).max() < 1e-12  # every local window too


def test_lmse_of_the_truth_is_zero_and_of_a_known_error_is_as_computed_by_hand():
    gt, mask, _ = _maps()
    assert lmse(gt, gt, mask).tolist() == [0.0, 0.0, 0.0]
    assert lmse(gt * 3.0, gt, mask).max() < 1e-12  # a scale is forgiven
    # Every 16 px window: truth 1 on half its pixels (even columns), 0 on the rest; estimate 1 everywhere.
    # alpha = <gt, est> / <est, est> = n/2 / n = 1/2; sum (gt - est/2)^2 = n/4; sum gt^2 = n/2: LMSE 1/2.
    gt = torch.zeros(1, 1, 32, 32)
    gt[..., ::2] = 1.0
    assert lmse(torch.ones_like(gt), gt, torch.ones_like(gt)).item() == pytest.approx(0.5)
    # an estimate that is the truth in one window and wrong in the other keeps its windows apart:
    # left half exact, right half flat: only the windows that see the right half cost anything
    est = torch.where(torch.arange(32) < 16, gt, torch.ones_like(gt))
    assert 0 < lmse(est, gt, torch.ones_like(gt)).item() < 0.5


def test_level_error_of_per_image_scaled_predictions_is_the_sd_of_their_log_scales():
    gt, mask, g = _maps(b=6)
    logs = torch.tensor([-0.4, 0.4, -0.4, 0.4, -0.4, 0.4])  # population sd 0.4 exactly, mean 0
    pred = gt * 1.7 * logs.exp()[:, None, None, None]  # a common factor 1.7: a bias, not an error of level
    pred = torch.where(mask > 0.5, pred, 100 * torch.rand(gt.shape, generator=g))  # off the mask: ignored
    ratios = level_log_ratio(pred, gt, mask)
    assert ratios.tolist() == pytest.approx((logs + math.log(1.7)).tolist(), abs=1e-6)
    assert level_error(ratios) == pytest.approx(0.4, abs=1e-6)
    uneven = torch.tensor([0.0, 0.0, 0.0, 0.3])  # mean 0.075; population sd sqrt(3 * 0.075^2 + 0.225^2) / 2
    assert level_error(uneven) == pytest.approx(math.sqrt((3 * 0.075**2 + 0.225**2) / 4))


def test_empty_masks_give_no_number():
    gt, _, _ = _maps(b=2)
    empty = torch.zeros(2, 1, 32, 32)
    assert least_squares_scale(gt, gt, empty).flatten().tolist() == [0.0, 0.0]
    assert torch.isnan(lmse(gt, gt, empty)).all() and torch.isnan(level_log_ratio(gt, gt, empty)).all()
    assert level_error(torch.tensor([float("nan"), 0.2])) is None
