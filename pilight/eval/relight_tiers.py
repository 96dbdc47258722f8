"""Relighting graded in three tiers, so a real error is never confused with an unknowable one.

A relit image's absolute brightness cannot be recovered from one photo (the renders draw each light's
power at random), so every method is graded three ways, each on the same pairs:

* ``absolute``: the paper's setting. The model is given the target ball exactly as rendered (the
  relit folder's ``<split>_abs`` splits); images as they come.
* ``relative``: the product's setting. The model is told r = level(ball_b) / level(ball_a) of the
  rendered balls (pilight.physics.envmap.light_level), what a user states as ``--intensity k``, and
  scales the target ball to r times its own estimate of the input's light (``<split>`` splits). The
  baseline that knows r too is the EXPOSURE-MATCHED COPY, I_a x r.
* ``scale_invariant``: each method's ABSOLUTE-mode image (and the input, for the copy) is first
  multiplied by its least-squares scale against the target, fitted on the mask in linear HDR
  (pilight.eval.scale_invariant): s* = <I_b, I_hat>_mask / <I_hat, I_hat>_mask. What is left is
  structure: where the light falls, not how much of it there is. The copy x s* is the
  exposure-matched copy of this tier.

In each tier, per method: PSNR and SSIM of whole images and change_r2 (full image and mask; pooled
over pixels) in the display space u = tonemap01(x) = (schema.to_model(x) + 1) / 2, over the cross-light
pairs ("relight") and, where the method's split holds them, the identity pairs ("reconstruction");
and the LEVEL ERROR: the sd over the cross-light pairs of log(mean I_hat / mean I_b) on the mask, in
linear HDR (pilight.eval.scale_invariant.level_error).

Methods (``Method.kind``): "model"; "baseline" (needs nothing the model is not given: copy the input,
the exposure-matched copy, the zero-gain physics anchor on the model's own conditions);
"oracle" (uses ground truth at test time: the model and the anchor with ground-truth conditions, the
analytic A * D_calc of ground-truth albedo and normals under the target ball). The "strongest
baseline" of a tier is the best "baseline" method on each figure.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from pilight.data.colour import tonemap01
from pilight.eval.light_following import ChangeR2
from pilight.eval.metrics import psnr_per_image, ssim_per_image
from pilight.eval.scale_invariant import level_error, level_log_ratio, scaled_to
from pilight.physics.envmap import light_level

TIERS = ("absolute", "relative", "scale_invariant")


@dataclass(frozen=True)
class Method:
    name: str  # its key in metrics/evaluate.json
    label: str  # its row in reports/relight.md
    kind: str  # "model" | "baseline" | "oracle" (module docstring)
    split_suffix: str | None = None  # its relit split is <split><suffix>; None: formed from the pair itself


def _relit_methods(mode: str) -> tuple[Method, ...]:
    """The relit folder's four methods in one intensity mode ("" relative, "_abs" absolute)."""
    return (
        Method("model", "model", "model", mode),
        Method("model_gt", "model, ground-truth conditions", "oracle", f"_gt{mode}"),
        Method("anchor", "physics anchor, zero gains", "baseline", f"_anchor{mode}"),
        Method("anchor_gt", "physics anchor, zero gains, ground-truth conditions", "oracle", f"_gt_anchor{mode}"),
    )


COPY = Method("copy_input", "copy the input", "baseline")
EXPOSURE_MATCHED_COPY = Method("exposure_matched_copy", "exposure-matched copy: input x r", "baseline")
ANALYTIC = Method("analytic_ad", "A * D_calc, ground-truth A and N", "oracle")
TIER_METHODS: dict[str, tuple[Method, ...]] = {
    "absolute": (*_relit_methods("_abs"), COPY, ANALYTIC),
    "relative": (*_relit_methods(""), COPY, EXPOSURE_MATCHED_COPY),
    "scale_invariant": (
        *_relit_methods("_abs"),
        Method("copy_input", "copy the input x s* (exposure-matched)", "baseline"),
        ANALYTIC,
    ),
}
SPACES = {
    "absolute": "images as they come (the target ball as rendered)",
    "relative": "the model told r = level(ball_b) / level(ball_a) of the rendered balls",
    "scale_invariant": "each image (absolute mode) x its least-squares scale s* against the target, fitted on "
    "the mask in linear HDR",
}


def intensity_ratio(ball_a: torch.Tensor, ball_b: torch.Tensor) -> torch.Tensor:
    """(B, 1, 1, 1) r = level(ball_b) / level(ball_a) of the rendered gray balls: the target light's
    intensity relative to the input's own, what the relative mode is told."""
    return light_level(ball_b) / light_level(ball_a)


def exposure_matched_copy(image_a: torch.Tensor, ball_a: torch.Tensor, ball_b: torch.Tensor) -> torch.Tensor:
    """The input at the target light's level: I_a x r (``intensity_ratio``)."""
    return image_a * intensity_ratio(ball_a, ball_b)


def tier_image(tier: str, image: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """What a tier grades of a method's linear HDR image: the image itself, or in the scale-invariant
    tier the image x s* fitted against ``target`` on ``mask``."""
    return scaled_to(image, target, mask) if tier == "scale_invariant" else image


@dataclass(frozen=True)
class Pairs:
    """What a batch of pairs is graded against, tone-mapped once for every method: the linear target,
    its and the input's display values u, the mask and which pairs are cross-light."""

    target: torch.Tensor  # (B, 3, H, W) linear HDR
    u_target: torch.Tensor
    u_input: torch.Tensor
    mask: torch.Tensor  # (B, 1, H, W)
    cross: torch.Tensor  # (B,) bool; the others are identity pairs

    @classmethod
    def of(cls, image_a: torch.Tensor, image_b: torch.Tensor, mask: torch.Tensor, cross: torch.Tensor) -> Pairs:
        return cls(image_b, tonemap01(image_b), tonemap01(image_a), mask, cross)

    def select(self, sel: torch.Tensor) -> Pairs:
        return (
            self
            if bool(sel.all())
            else Pairs(*(x[sel] for x in (self.target, self.u_target, self.u_input)), self.mask[sel], self.cross[sel])
        )


class MethodScores:
    """One method's figures in one tier, accumulated over batches (module docstring)."""

    def __init__(self):
        self.relight = {"psnr": [], "ssim": [], "lpips": []}
        self.reconstruction = {"psnr": [], "ssim": [], "lpips": []}
        self.change = ChangeR2()
        self.levels: list[torch.Tensor] = []

    def update(self, pred: torch.Tensor, pairs: Pairs, lpips=None) -> None:
        """``pred``: the method's linear HDR images (B, 3, H, W) of the B ``pairs``, as its tier grades them."""
        u, gt, cross = tonemap01(pred), pairs.u_target, pairs.cross
        for scores, sel in ((self.relight, cross), (self.reconstruction, ~cross)):
            if sel.any():
                scores["psnr"].append(psnr_per_image(u[sel], gt[sel]))
                scores["ssim"].append(ssim_per_image(u[sel], gt[sel]))
                if lpips is not None:
                    scores["lpips"].append(lpips(u[sel], gt[sel]).flatten())
        if cross.any():
            self.change.update(u[cross], gt[cross], pairs.u_input[cross], pairs.mask[cross])
            self.levels.append(level_log_ratio(pred[cross], pairs.target[cross], pairs.mask[cross]))

    def compute(self) -> dict[str, float | int]:
        """Figures of the pairs seen; a figure with no pair (or no LPIPS) is left out."""
        mean = lambda xs: float(torch.cat(xs).float().mean())
        out: dict[str, float | int] = {}
        for prefix, scores in (("", self.relight), ("reconstruction_", self.reconstruction)):
            if scores["psnr"]:
                out[f"{prefix}pairs"] = len(torch.cat(scores["psnr"]))
                out |= {f"{prefix}{k}": mean(v) for k, v in scores.items() if v}
        r2 = self.change.compute()
        out |= {f"change_r2_{k}": v for k, v in r2.items() if v is not None}
        level = level_error(torch.cat(self.levels)) if self.levels else None
        if level is not None:
            out["level_sd"] = level
        return out


def strongest_baseline(tier_scores: dict[str, dict], tier: str, figure: str) -> tuple[str, float] | None:
    """(method name, value) of the best "baseline" method of ``tier`` on ``figure`` (higher is better)."""
    kinds = {m.name: m.kind for m in TIER_METHODS[tier]}
    found = [(v[figure], k) for k, v in tier_scores.items() if kinds.get(k) == "baseline" and figure in v]
    if not found:
        return None
    value, name = max(found)
    return name, value
