"""Physics-inspired losses of PI-Light (paper, "Training Objectives").

All losses act in RGB space (after the VAE decoder), take ``B x C x H x W``
tensors and return a scalar (``reduction="mean"``: mean over the batch of the
per-sample values) or the per-sample values ``(B,)`` (``reduction="none"``),
which ``physics_loss`` needs for its per-sample ``1/t`` weight.
"""

from __future__ import annotations

import os

import torch
import torch.nn as nn
import torch.nn.functional as F

from pilight.optional import require

from .shading import compose

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


def _reduce(per_sample: torch.Tensor, reduction: str) -> torch.Tensor:
    if reduction == "none":
        return per_sample
    if reduction == "mean":
        return per_sample.mean()
    raise ValueError(f"reduction must be 'mean' or 'none', got {reduction!r}")


def masked_mse(
    a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor | None = None, reduction: str = "mean"
) -> torch.Tensor:
    """Per-sample mean of ``(a-b)^2`` over valid pixels and channels; 0 for an empty mask.

    The denominator is clamped, not the result: with an all-zero mask the
    numerator is exactly 0, so loss and gradient are 0, never NaN.

    Accumulated in >= fp32 whatever the input dtype: in fp16 the pixel count
    of one 3 x 256^2 sample (196608) is past fp16's largest value (65504),
    so the denominator became inf and the loss 0.  Masked-out pixels are
    selected away (``torch.where``), not multiplied by 0: a NaN or Inf
    there (an undefined background normal, say) would otherwise make the
    whole loss NaN.  Where the mask is > 0, ``err * mask`` is what it was.
    """
    work = torch.promote_types(torch.promote_types(a.dtype, b.dtype), torch.float32)
    diff = a.to(work) - b.to(work)
    if mask is None:
        return _reduce(diff.square().flatten(1).mean(1), reduction)
    m = mask.to(work)
    # Selected before squaring, so the backward pass gets 0 (not NaN * 0) at those pixels too.
    diff = torch.where(m > 0, diff, torch.zeros((), dtype=work, device=diff.device))
    err = diff.square()
    num = (err * m).flatten(1).sum(1)
    den = (m.expand_as(err) if m.shape[1] == 1 else m).flatten(1).sum(1)
    return _reduce(num / den.clamp_min(1e-8), reduction)


def _identity(x):
    return x


def diffuse_shading_loss(d_calc, d_pred, mask, reduction: str = "mean", space=_identity):
    """``L_DS = MSE(D_calculated, D_pred)`` over the foreground (paper, Diffuse Shading Loss).

    ``d_calc`` comes from ``diffuse_shading`` (data, not a prediction); the
    caller decides whether to detach it. ``space``: applied to both sides before the MSE (stage 2
    compares in its tone-mapped space, pilight.relight.physics_terms); the identity = linear HDR.
    """
    return masked_mse(space(d_calc), space(d_pred), mask, reduction)


def physical_shading_loss(relit, albedo, d_pred, s_pred, mask=None, reduction: str = "mean", space=_identity):
    """``L_PS = MSE(I_relit, A (.) D_pred + S_pred)`` (paper eq. lpb): the identity is formed in linear
    HDR, then both sides pass through ``space`` (as in ``diffuse_shading_loss``)."""
    return masked_mse(space(relit), space(compose(albedo, d_pred, s_pred)), mask, reduction)


def reconstruction_loss(relit, inp, extractor: nn.Module, reduction: str = "mean"):
    """``L_rec = ||phi(I_relit) - phi(I_in)||_2^2`` (paper, Reconstruction Loss), as a mean.

    A mean (not a sum) keeps the scale independent of the feature size, so
    ``lambda_3`` transfers between extractors of different widths.  ``I_in``
    is a fixed target: its features are computed without a graph.
    """
    f_relit = extractor(relit)
    with torch.no_grad():
        f_in = extractor(inp)
    return _reduce((f_relit - f_in).square().flatten(1).mean(1), reduction)


class PooledRGBFeatures(nn.Module):
    """Substitute for DINO when no DINOv2 weights are configured: ``grid x grid`` average-pooled RGB.

    Not perceptual; it only says "the low-frequency colour layout is kept".
    Reports must name it (``.name``), never call it DINO.
    """

    def __init__(self, grid: int = 8):
        super().__init__()
        self.grid = grid
        self.name = f"pooled-rgb-{grid}x{grid}"

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return F.adaptive_avg_pool2d(images, self.grid).flatten(1)


class Dinov2Features(nn.Module):
    """Frozen DINOv2 (``transformers.Dinov2Model``) last-hidden-layer tokens, from a local path.

    Images in [0, 1] are resized (bilinear, antialiased) so the short side is
    ``resolution`` with both sides multiples of the patch size, then
    normalised with ImageNet mean/std (as DINOv2 was trained).  Output:
    ``B x (1 + tokens) x hidden`` (CLS + patch tokens, after the final layernorm).
    """

    def __init__(self, path: str | os.PathLike, resolution: int = 224):
        super().__init__()
        Dinov2Model = require("transformers", "rec_features: dinov2").Dinov2Model

        path = os.fspath(path)
        if not os.path.isfile(os.path.join(path, "config.json")):
            raise FileNotFoundError(
                f"DINOv2 weights not found at {path!r} (expected a save_pretrained folder "
                "with config.json); download them before training, nothing is fetched at run time"
            )
        self.model = Dinov2Model.from_pretrained(path, local_files_only=True)
        self.model.requires_grad_(False).eval()
        self.patch = int(self.model.config.patch_size)
        self.resolution = resolution
        self.name = f"dinov2:{os.path.basename(os.path.normpath(path))}@{resolution}"
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)

    def train(self, mode: bool = True):
        super().train(mode)
        self.model.eval()  # frozen: dropout/droppath stay off even inside a training module
        return self

    def _size(self, h: int, w: int) -> tuple[int, int]:
        s = self.resolution / min(h, w)
        return (
            max(self.patch, round(h * s / self.patch) * self.patch),
            max(self.patch, round(w * s / self.patch) * self.patch),
        )

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        dtype = self.model.dtype
        x = images.to(dtype)
        size = self._size(*x.shape[-2:])
        if tuple(x.shape[-2:]) != size:
            x = F.interpolate(x, size=size, mode="bilinear", align_corners=False, antialias=True)
        x = (x - self.mean.to(dtype)) / self.std.to(dtype)
        return self.model(pixel_values=x).last_hidden_state


def make_feature_extractor(kind: str, path: str | None = None, **kw) -> nn.Module:
    """``kind``: ``"dinov2"`` (needs ``path``) or ``"pooled-rgb"``.  No silent fallback."""
    if kind == "dinov2":
        if not path:
            raise ValueError(
                "feature extractor 'dinov2' needs a local weights path; "
                "configure one or choose kind='pooled-rgb' explicitly"
            )
        return Dinov2Features(path, **kw)
    if kind == "pooled-rgb":
        return PooledRGBFeatures(**kw)
    raise ValueError(f"unknown feature extractor kind {kind!r} (expected 'dinov2' or 'pooled-rgb')")


def physics_loss(t, l_ds, l_ps, l_rec, lambdas=(1.0, 1.0, 1.0), t_min: float = 1.0) -> torch.Tensor:
    """Physics part of the final loss (paper, "Final loss function"):

        L_stage2 = L_V-pred + 1/t (lambda_1 L_DS + lambda_2 L_PS + lambda_3 L_rec)

    ``1/t`` down-weights the RGB losses at high noise, where ``z_0`` inferred
    from ``z_t`` is unreliable.  ``t``: int, 0-d or ``(B,)`` diffusion
    timesteps (e.g. 0..999), floored at ``t_min > 0`` so t = 0 never divides
    by zero.  ``l_*``: scalars or per-sample ``(B,)``.  Returns the batch mean
    of the per-sample weighted sums (caller adds ``L_V-pred``).
    """
    if t_min <= 0:
        raise ValueError(f"t_min must be > 0, got {t_min}")
    l1, l2, l3 = lambdas
    total = l1 * torch.as_tensor(l_ds) + l2 * torch.as_tensor(l_ps) + l3 * torch.as_tensor(l_rec)
    # weights in >= fp32: bf16 cannot tell t = 999 from t = 1000
    t = torch.as_tensor(t, device=total.device).to(torch.promote_types(total.dtype, torch.float32))
    w = 1.0 / t.clamp_min(t_min)
    return (w * total).mean()
