"""A prior on the input light's level (`relight.level_prior`): the estimate shrunk toward the training lights'.

Relative intensity scales a target light to the input's estimated light level l, from a first-order fit of
the input's shading (pilight.physics.source_light). That level is an extrapolation from the normals a
photo shows, and it scatters: on the base's training inputs its log is off by 0.80 rms with ground-truth
maps, large estimates too large and small ones too small. A least-squares line through the training
inputs' (log l, log l_rendered) points,

    log l' = alpha + beta log l            (beta < 1 shrinks toward exp(alpha / (1 - beta)))

cuts that error to 0.50 rms (docs/pipeline/stage2.md, "A prior on the light's level"). It is a property
of the training lights, so the numbers belong to the model trained with them: stage 2 is trained and
run with the same prior, never one without the other (the network learns its gains on anchors at that
level). ``fit_level_prior`` gives the numbers; `benchmarks/fit_level_prior.py` collects the levels from
a split's shards.

What it costs: with beta < 1 the conditioning albedo's level no longer cancels in the relative form
(twice the albedo halves l but l' only by 2^beta), so the relit image follows the albedo's level as the
dielectric highlight already did. A photo at ``exposure: photo`` keeps its exposure either way.
"""

from __future__ import annotations

import math

import numpy as np
import torch

LEVEL_FLOOR = 1e-8  # log of a black estimate: such inputs are "not found" and never scaled anyway


def shrink_level(level: torch.Tensor, alpha: float, beta: float) -> torch.Tensor:
    """log l' = alpha + beta log l, elementwise; (0, 1) is the identity."""
    return torch.exp(alpha + beta * torch.log(level.clamp_min(LEVEL_FLOOR)))


def fit_level_prior(estimated: np.ndarray, rendered: np.ndarray) -> dict[str, float | int]:
    """(alpha, beta) of the least-squares line log rendered = alpha + beta log estimated, over inputs whose
    light was estimated; with the fit's rms log error before (alpha 0, beta 1) and after."""
    est, true = np.asarray(estimated, dtype=np.float64), np.asarray(rendered, dtype=np.float64)
    if est.shape != true.shape or est.ndim != 1:
        raise ValueError(
            f"estimated and rendered levels must be two 1-D arrays of one length, got {est.shape}, {true.shape}"
        )
    if len(est) < 3:
        raise ValueError(f"fitting a level prior needs at least 3 inputs with an estimated light, got {len(est)}")
    if (est <= 0).any() or (true <= 0).any():
        raise ValueError("light levels must be positive to fit their logs")
    x, y = np.log(est), np.log(true)
    if np.ptp(x) == 0:
        raise ValueError("every estimated level is the same: the slope of the prior is undetermined")
    design = np.stack([np.ones_like(x), x], 1)
    (alpha, beta), *_ = np.linalg.lstsq(design, y, rcond=None)
    rms = lambda r: math.sqrt(float(np.mean(r**2)))
    return {
        "alpha": float(alpha),
        "beta": float(beta),
        "inputs": int(len(x)),
        "rms_log_error_before": rms(y - x),
        "rms_log_error_after": rms(y - design @ np.array([alpha, beta])),
    }
