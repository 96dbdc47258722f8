"""Scale-invariant grading: what an error is once the one unknowable number, the level, is forgiven.

A single photo cannot tell an albedo's level from the light's power, nor (relit) the target light's
absolute power from the input's. The intrinsic-image field therefore grades after a least-squares
scale (Grosse et al., ICCV 2009, "Ground truth dataset and baseline evaluations for intrinsic image
algorithms", section 4):

    alpha* = argmin_a sum_mask (gt - a est)^2 = <gt, est>_mask / <est, est>_mask        (one per image)

over every masked pixel and channel of one image, and LMSE, the same fitted per local window:

    LMSE = sum_w sum_{x in w} m (gt - alpha_w est)^2 / sum_w sum_{x in w} m gt^2

(Grosse: 20 px windows, stride 10, at the MIT images' size; here ``LMSE_WINDOW`` = 16 px, stride
``LMSE_STRIDE`` = 8 at 128^2: the same half-window overlap, a window of 1/8 of the side, near the
10% that Chen & Koltun use for Sintel; at other sizes the window is capped at the image). An estimate
whose masked energy is below ``GROSSE_EMPTY`` gets alpha = 0, as in Grosse's code.

The level itself is graded by ``level_error``: the sd over pairs of log(mean prediction / mean target)
on the mask, in linear HDR; a method off by one constant factor everywhere scores 0, one that
misjudges each image's level by a random factor exp(e) scores sd(e).
"""

from __future__ import annotations

import torch

LMSE_WINDOW = 16  # px at 128^2 (Grosse: 20 px at the MIT images' size)
LMSE_STRIDE = 8  # half a window, as Grosse's 20 / 10
GROSSE_EMPTY = 1e-5  # sum m est^2 below which alpha = 0 (Grosse's ssq_error)
LEVEL_FLOOR = 1e-8  # mean radiance below which a level is taken as this (a black prediction stays finite)


def least_squares_scale(est: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """(B, 1, 1, 1) alpha* = <gt, est> / <est, est> over the MASKED pixels (all channels) of each image;
    0 where the masked estimate is (near) empty. est, gt (B, C, H, W); mask (B, 1, H, W)."""
    m = (mask > 0.5).to(torch.float64)
    e, g = est.to(torch.float64), gt.to(torch.float64)
    num = (m * g * e).flatten(1).sum(1)
    den = (m * e * e).flatten(1).sum(1)
    alpha = torch.where(den > GROSSE_EMPTY, num / den.clamp_min(GROSSE_EMPTY), torch.zeros_like(num))
    return alpha.to(torch.promote_types(est.dtype, torch.float32))[:, None, None, None]


def scaled_to(est: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """est x alpha* (``least_squares_scale``): the estimate at the truth's level, fitted on the mask."""
    return est * least_squares_scale(est, gt, mask)


def lmse(
    est: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor, window: int = LMSE_WINDOW, stride: int = LMSE_STRIDE
) -> torch.Tensor:
    """(B,) Grosse's local MSE per image (module docstring), NaN for an image whose masked truth is 0
    (no windows to normalise by); one alpha per window over its masked pixels and all channels."""
    h, w = est.shape[-2:]
    k = (min(window, h), min(window, w))
    s = (min(stride, k[0]), min(stride, k[1]))
    unfold = lambda x: torch.nn.functional.unfold(x.to(torch.float64), k, stride=s)  # (B, C*kh*kw, L)
    c = est.shape[1]
    m = (mask > 0.5).expand(-1, c, -1, -1)
    e, g, mm = unfold(est), unfold(gt), unfold(m)
    den = (mm * e * e).sum(1)
    alpha = torch.where(den > GROSSE_EMPTY, (mm * g * e).sum(1) / den.clamp_min(GROSSE_EMPTY), torch.zeros_like(den))
    ssq = (mm * (g - alpha[:, None] * e) ** 2).sum((1, 2))
    total = (mm * g * g).sum((1, 2))
    return torch.where(total > 0, ssq / total.clamp_min(1e-300), torch.full_like(total, float("nan")))


def level_log_ratio(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """(B,) log(mean pred / mean target) over each image's masked pixels and channels (linear HDR);
    NaN for an empty mask. Means below LEVEL_FLOOR count as LEVEL_FLOOR."""
    m = (mask > 0.5).expand_as(pred).to(torch.float64)
    n = m.flatten(1).sum(1)
    mean = lambda x: (x.to(torch.float64) * m).flatten(1).sum(1) / n.clamp_min(1)
    ratio = torch.log(mean(pred).clamp_min(LEVEL_FLOOR)) - torch.log(mean(target).clamp_min(LEVEL_FLOOR))
    return torch.where(n > 0, ratio, torch.full_like(ratio, float("nan")))


def level_error(log_ratios: torch.Tensor) -> float | None:
    """The population sd of the finite ``level_log_ratio`` values (None with fewer than 2)."""
    x = log_ratios[torch.isfinite(log_ratios)].to(torch.float64)
    return float(x.std(unbiased=False)) if x.numel() >= 2 else None
