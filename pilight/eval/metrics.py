"""Intrinsics metrics on masked pixels, and the trivial baselines every table shows beside the model.

- albedo: PSNR (torchmetrics) over the mask, data range 1 (linear albedo in [0, 1]), `masked_psnr`;
- normal: mean / median angular error in degrees and the share within 11.25, 22.5, 30 degrees
  (the paper's Table 7 layout);
- roughness, metallic: mean absolute error over the mask.
An empty mask gives NaN-free "n/a" (None), never a made-up number. PSNR is capped at PSNR_CAP, so
identical maps (the ground truth, a copy) give a finite, valid-JSON clamp value.

Undefined is not perfect (issue 36): a figure computed per image over maps zeroed off the mask (SSIM,
LPIPS) would score an image with an EMPTY mask as a perfect match (SSIM 1.000 over zero pixels). Such
images are left out of the mean (``mean_over_masked``, ``masked_ssim``), and a figure with no image
left is None, reported as missing ("n/a", null), as is a mean angle over no pixel
(``masked_mean_angular_error``).
"""

from __future__ import annotations

import math

import torch
from torchmetrics.functional.image import peak_signal_noise_ratio, structural_similarity_index_measure

NORMAL_THRESHOLDS = (11.25, 22.5, 30.0)
PSNR_CAP = 100.0  # dB; identical images (copy input, reconstruction setting) would give inf, not valid JSON


def _masked(x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """(B, C, H, W), (B, 1, H, W) -> (N, C) of the masked pixels."""
    m = mask[:, 0] > 0.5
    return x.permute(0, 2, 3, 1)[m]


def masked_psnr(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor) -> float | None:
    """PSNR over the masked pixels (pooled over images) of maps in [0, 1] (clamped), data range 1,
    capped at PSNR_CAP."""
    p, g = _masked(pred, mask), _masked(gt, mask)
    if p.numel() == 0:
        return None
    return min(float(peak_signal_noise_ratio(p.clamp(0, 1), g.clamp(0, 1), data_range=1.0)), PSNR_CAP)


def masked_psnr_per_image(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """(B,) PSNR of each image over its masked pixels (maps clamped to [0, 1], data range 1), capped at
    PSNR_CAP; NaN for an image with an empty mask."""
    m = (mask > 0.5).expand_as(pred).to(torch.float64)
    se = ((pred.clamp(0, 1) - gt.clamp(0, 1)).to(torch.float64) ** 2 * m).flatten(1).sum(1)
    n = m.flatten(1).sum(1)
    mse = se / n.clamp_min(1)
    psnr = (10.0 * torch.log10(1.0 / mse)).clamp(max=PSNR_CAP)  # mse 0 -> inf -> the cap
    return torch.where(n > 0, psnr, torch.full_like(psnr, float("nan")))


def angular_errors(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Per-pixel angle (degrees) between predicted and true normals on the mask."""
    p = torch.nn.functional.normalize(_masked(pred, mask), dim=1, eps=1e-8)
    g = torch.nn.functional.normalize(_masked(gt, mask), dim=1, eps=1e-8)
    return torch.rad2deg(torch.acos((p * g).sum(1).clamp(-1.0, 1.0)))


def normal_metrics(errors_deg: torch.Tensor) -> dict[str, float | None]:
    if errors_deg.numel() == 0:
        return {"mean_deg": None, "median_deg": None, **{f"within_{t}": None for t in NORMAL_THRESHOLDS}}
    return {
        "mean_deg": float(errors_deg.mean()),
        "median_deg": float(errors_deg.median()),
        **{f"within_{t}": float((errors_deg < t).float().mean()) for t in NORMAL_THRESHOLDS},
    }


def masked_mae(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor) -> float | None:
    p, g = _masked(pred, mask), _masked(gt, mask)
    return float((p - g).abs().mean()) if p.numel() else None


def masked_mean_angular_error(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor) -> float | None:
    """Mean angle (degrees) between predicted and true normals over the masked pixels; None without any."""
    errors = angular_errors(pred, gt, mask)
    return float(errors.mean()) if errors.numel() else None


def has_mask(mask: torch.Tensor) -> torch.Tensor:
    """(B,) bool: the image has at least one masked pixel."""
    return (mask > 0.5).flatten(1).any(1)


def mean_over_masked(per_image: torch.Tensor, mask: torch.Tensor) -> float | None:
    """The mean of a per-image figure (B,) over the images whose mask holds a pixel; None when none does
    (a figure over zero pixels is undefined, not perfect)."""
    keep = has_mask(mask).to(per_image.device)
    values = per_image.flatten()[keep]
    return float(values.mean()) if values.numel() else None


def masked_ssim(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor) -> float | None:
    """SSIM (``ssim_per_image``) of maps zeroed off the mask, averaged over the images with a non-empty
    mask; None when every mask is empty (the zeroed maps would match perfectly)."""
    keep = has_mask(mask)
    if not bool(keep.any()):
        return None
    if bool(keep.all()):  # one batched call, the figure as before
        return float(structural_similarity_index_measure(pred, gt, data_range=1.0))
    return float(ssim_per_image(pred[keep], gt[keep]).mean())


def psnr_per_image(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """(B,) PSNR of whole images in [0, 1], data range 1, capped at PSNR_CAP."""
    return peak_signal_noise_ratio(pred, gt, data_range=1.0, reduction="none", dim=(1, 2, 3)).clamp(max=PSNR_CAP)


def ssim_per_image(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """(B,) SSIM of whole images in [0, 1] (Gaussian 11x11)."""
    return structural_similarity_index_measure(pred, gt, data_range=1.0, reduction="none")


def psnr_from_mse(mse: float, data_range: float = 1.0) -> float:
    return 10.0 * math.log10(data_range**2 / mse) if mse > 0 else math.inf
