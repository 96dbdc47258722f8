"""Intrinsics metrics on masked pixels, and the trivial baselines every table shows beside the model.

- albedo: PSNR (torchmetrics) over the mask, data range 1 (linear albedo in [0, 1]);
- normal: mean / median angular error in degrees and the share within 11.25, 22.5, 30 degrees
  (the paper's Table 7 layout);
- roughness, metallic: mean absolute error over the mask.
An empty mask gives NaN-free "n/a" (None), never a made-up number.
"""

from __future__ import annotations

import math

import torch
from torchmetrics.functional.image import peak_signal_noise_ratio

NORMAL_THRESHOLDS = (11.25, 22.5, 30.0)


def _masked(x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """(B, C, H, W), (B, 1, H, W) -> (N, C) of the masked pixels."""
    m = mask[:, 0] > 0.5
    return x.permute(0, 2, 3, 1)[m]


def albedo_psnr(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor) -> float | None:
    p, g = _masked(pred, mask), _masked(gt, mask)
    if p.numel() == 0:
        return None
    return float(peak_signal_noise_ratio(p.clamp(0, 1), g.clamp(0, 1), data_range=1.0))


def angular_errors(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Per-pixel angle (degrees) between predicted and true normals on the mask."""
    p = torch.nn.functional.normalize(_masked(pred, mask), dim=1, eps=1e-8)
    g = torch.nn.functional.normalize(_masked(gt, mask), dim=1, eps=1e-8)
    return torch.rad2deg(torch.acos((p * g).sum(1).clamp(-1.0, 1.0)))


def normal_metrics(errors_deg: torch.Tensor) -> dict[str, float | None]:
    if errors_deg.numel() == 0:
        return {"mean_deg": None, "median_deg": None, **{f"within_{t}": None for t in NORMAL_THRESHOLDS}}
    return {"mean_deg": float(errors_deg.mean()), "median_deg": float(errors_deg.median()),
            **{f"within_{t}": float((errors_deg < t).float().mean()) for t in NORMAL_THRESHOLDS}}


def masked_mae(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor) -> float | None:
    p, g = _masked(pred, mask), _masked(gt, mask)
    return float((p - g).abs().mean()) if p.numel() else None


def psnr_from_mse(mse: float, data_range: float = 1.0) -> float:
    return 10.0 * math.log10(data_range**2 / mse) if mse > 0 else math.inf
