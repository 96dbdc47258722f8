"""Stage 2's whole objective in one place: the v-prediction loss, every lambda, the 1/t weight and the
image loss (paper, "Final loss function"; the image loss is ours):

    L = L_vpred + (1 / max(t, t_min)) (lambda_ds L_DS + lambda_ps L_PS + lambda_rec L_rec) + lambda_image L_image

* L_vpred = MSE(v, v_target) on the latents of every branch (v_target: diffusers' get_velocity);
* L_DS, L_PS, L_rec: the physics terms on the decoded outputs (pilight.relight.physics_terms, with
  the physics module's own loss functions), weighted per sample by 1/max(t, t_min)
  (pilight.physics.physics_loss);
* L_image = MSE(tonemap(I_relit), tonemap(I_b)) on the samples drawn at t = T - 1 only, where
  single-step inference runs (E2E-FT's task loss, Garcia et al. 2024); elsewhere x0 is a noisy estimate,
  and 1/t there would be 1/999, so it is not weighted by it.

``needs_decode``: with every physics lambda and lambda_image at 0 (the no-physics ablation) nothing is
decoded at all. The training Task (pilight.train.relight.RelightTask) forms the batch, the targets and
the decoded outputs; what it minimises is ``total``.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from pilight.params import RelightParams
from pilight.physics import masked_mse, physics_loss
from pilight.relight.encoding import tonemap

TERMS = ("ds", "ps", "rec")


def lambdas(p: RelightParams) -> tuple[float, float, float]:
    """(lambda_ds, lambda_ps, lambda_rec): the weights of L_DS, L_PS and L_rec."""
    return (p.lambda_ds, p.lambda_ps, p.lambda_rec)


def needs_decode(p: RelightParams) -> bool:
    """Whether any term beyond L_vpred is on (the outputs must then be decoded, with gradients)."""
    return any(lambdas(p)) or bool(p.lambda_image)


def vpred_loss(v: torch.Tensor, v_target: torch.Tensor) -> torch.Tensor:
    """L_vpred = MSE(v, v_target) over every branch's latents."""
    return F.mse_loss(v, v_target.float())


def time_weight(t: torch.Tensor, p: RelightParams) -> torch.Tensor:
    """The per-sample 1 / max(t, t_min) the physics terms are weighted by (as physics_loss weighs them)."""
    return 1.0 / t.float().clamp_min(p.t_min)


def physics_part(t: torch.Tensor, terms: dict[str, torch.Tensor], p: RelightParams) -> torch.Tensor:
    """(1 / max(t, t_min)) (lambda_ds L_DS + lambda_ps L_PS + lambda_rec L_rec), averaged over the batch."""
    return physics_loss(t, terms["ds"], terms["ps"], terms["rec"], lambdas(p), p.t_min)


def image_loss(
    relit_tonemapped: torch.Tensor, image_b: torch.Tensor, t: torch.Tensor, num_train_timesteps: int
) -> tuple[torch.Tensor, float]:
    """(L_image per batch, unweighted by lambda_image; its mean over the terminal samples, for the log):
    the formed relit image against the target in display space, on the samples at t = T - 1 only."""
    terminal = (t == num_train_timesteps - 1).to(relit_tonemapped.device, torch.float32)
    per_sample = masked_mse(relit_tonemapped, tonemap(image_b.float()), reduction="none")
    logged = float((per_sample.detach() * terminal).sum() / terminal.sum().clamp_min(1))
    return (per_sample * terminal).mean(), logged


def weighted_terms(t: torch.Tensor, terms: dict[str, torch.Tensor], p: RelightParams) -> dict[str, torch.Tensor]:
    """Each physics term as it enters L (for the gradient shares of train.grad_share_every)."""
    w = time_weight(t, p)
    return {k: (w * lam * terms[k]).mean() for k, lam in zip(TERMS, lambdas(p))}
