"""Stage 1's task losses on the predicted maps themselves, in pixel space (`intrinsics.objective: task`).

E2E-FT (Garcia et al., "Fine-Tuning Image-Conditional Diffusion Models is Easier than You Think")
trains Marigold/GeoWizard at the one timestep single-step inference uses, on the decoded prediction,
with a loss that suits each task. Ours, each a masked mean over reliable pixels (0, not NaN, when
the mask is empty: the DESIGN's mask contract):

- normal: the angle itself, arccos(n_pred . n_gt) (E2E-FT's angular loss); n_pred is normalised first.
- roughness: L1, the metric's own error.
- metallic: binary cross-entropy with p = the predicted value in [0, 1]: metal is 0 or 1 away from
  anti-aliased edges, and BCE penalises a confident wrong class where L2 saturates at 1.
- albedo: split into STRUCTURE and LEVEL. With alpha* = <a_gt, a_pred> / <a_pred, a_pred> per image
  (Grosse et al. 2009's least-squares scale, over the mask and the three channels),

      L_albedo = mean_mask (alpha* a_pred - a_gt)^2 / mean_mask a_gt^2  +  w_level (log alpha*)^2,

  the first term is the scale-invariant MSE (what si-PSNR grades, normalised so dark and bright
  scenes weigh alike), the second the per-image level. A single photo cannot tell albedo level from
  light power, so the level weighs less by default (`intrinsics.task_loss.albedo_level`).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

ANGLE_EPS = 1e-6  # arccos' gradient is infinite at +-1
BCE_EPS = 1e-4
ALBEDO_FLOOR = 1e-4  # keeps alpha* and its log finite for an all-black prediction


def _masked_mean(x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean of x (B, C, H, W) over mask (B, 1, H, W) and channels; 0 for an empty mask."""
    m = mask.expand_as(x)
    return (x * m).sum() / m.sum().clamp_min(1.0)


def angular_loss(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean angle (radians) between normalised predicted and ground-truth normals on the mask."""
    cos = (F.normalize(pred, dim=1, eps=1e-6) * gt).sum(1, keepdim=True)
    return _masked_mean(torch.arccos(cos.clamp(-1 + ANGLE_EPS, 1 - ANGLE_EPS)), mask)


def l1_loss(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    return _masked_mean((pred - gt).abs(), mask)


def bce_loss(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """pred: values in [0, 1] (clamped inside); gt may be soft (anti-aliased edges)."""
    p = pred.clamp(BCE_EPS, 1 - BCE_EPS)
    return _masked_mean(-(gt * torch.log(p) + (1 - gt) * torch.log1p(-p)), mask)


def albedo_scale(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """(B,) least-squares alpha* = <gt, pred> / <pred, pred> over the mask and channels (1 for an empty mask)."""
    m = mask.expand_as(pred)
    num, den = (gt * pred * m).sum((1, 2, 3)), (pred * pred * m).sum((1, 2, 3))
    empty = m.sum((1, 2, 3)) == 0
    alpha = num.clamp_min(ALBEDO_FLOOR) / den.clamp_min(ALBEDO_FLOOR)
    return torch.where(empty, torch.ones_like(alpha), alpha)


def albedo_loss(
    pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor, level_weight: float
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """(structure + level_weight * level, {"albedo_structure", "albedo_level"}) as in the module docstring."""
    pred = pred.clamp_min(0)
    alpha = albedo_scale(pred, gt, mask)
    m = mask.expand_as(pred)
    err = ((alpha[:, None, None, None] * pred - gt) ** 2 * m).sum((1, 2, 3))
    energy = (gt * gt * m).sum((1, 2, 3)).clamp_min(ALBEDO_FLOOR)
    has = (m.sum((1, 2, 3)) > 0).to(pred.dtype)
    structure = (err / energy * has).sum() / has.sum().clamp_min(1.0)
    level = (torch.log(alpha) ** 2 * has).sum() / has.sum().clamp_min(1.0)
    return structure + level_weight * level, {"albedo_structure": structure, "albedo_level": level}


def weighted_terms(
    pred: dict[str, torch.Tensor], gt: dict[str, torch.Tensor], mask: torch.Tensor, weights
) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
    """({map: its weight x its loss}, {logged term: its unweighted value}) over the predicted maps;
    ``weights``: the `intrinsics.task_loss` section. The first dict is what `train.grad_share_every`
    splits the gradient by (pilight.train.grad_shares)."""
    weighted: dict[str, torch.Tensor] = {}
    terms: dict[str, torch.Tensor] = {}
    if "albedo" in pred:
        la, parts = albedo_loss(pred["albedo"], gt["albedo"], mask, weights.albedo_level)
        terms |= parts
        weighted["albedo"] = weights.albedo * la
    if "normal" in pred:
        terms["normal_angle"] = angular_loss(pred["normal"], gt["normal"], mask)
        weighted["normal"] = weights.normal * terms["normal_angle"]
    if "roughness" in pred:
        terms["roughness_l1"] = l1_loss(pred["roughness"], gt["roughness"], mask)
        weighted["roughness"] = weights.roughness * terms["roughness_l1"]
    if "metallic" in pred:
        terms["metallic_bce"] = bce_loss(pred["metallic"], gt["metallic"], mask)
        weighted["metallic"] = weights.metallic * terms["metallic_bce"]
    return weighted, terms


def summed(weighted: dict[str, torch.Tensor]) -> torch.Tensor:
    """The total of ``weighted_terms``' first dict, added in the maps' order (the same bits as always)."""
    total = next(iter(weighted.values())).new_zeros(())
    for value in weighted.values():
        total = total + value
    return total


def task_loss(
    pred: dict[str, torch.Tensor], gt: dict[str, torch.Tensor], mask: torch.Tensor, weights
) -> tuple[torch.Tensor, dict[str, float]]:
    """Weighted sum over the predicted maps; ``weights``: the `intrinsics.task_loss` section.
    ``pred`` holds linear maps (albedo in [0, 1], unit-ish normals, roughness and metallic in [0, 1])."""
    weighted, terms = weighted_terms(pred, gt, mask, weights)
    return summed(weighted), {k: float(v.detach()) for k, v in terms.items()}
