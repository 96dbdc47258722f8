"""Noise schedule and the v-parameterisation, written once (paper Sec. Stage 1, "V-prediction").

Stage 1 trains on ``L = MSE(v_pred * m_z, v_target * m_z)``; ``v_target`` is the
v-prediction target of Salimans & Ho (2022), diffusers' ``DDPMScheduler.get_velocity``:

    x_t = sqrt(a_t) x0 + sqrt(1 - a_t) eps
    v   = sqrt(a_t) eps - sqrt(1 - a_t) x0
    x0  = sqrt(a_t) x_t - sqrt(1 - a_t) v
    eps = sqrt(1 - a_t) x_t + sqrt(a_t) v

with ``a_t = alphas_cumprod[t]``; x_t itself comes from the diffusers scheduler's ``add_noise``.
All helpers take a per-sample ``t`` of shape (B,)
and broadcast it over the remaining dimensions.  They stay correct at a zero-SNR
terminal step (``a_{T-1} = 0``): there ``x0 = -v``.
"""

from __future__ import annotations

import torch
from diffusers import DDPMScheduler


def make_train_scheduler(
    num_train_timesteps: int = 1000,
    beta_schedule: str = "scaled_linear",
    rescale_zero_snr: bool = False,
    timestep_spacing: str = "leading",
) -> DDPMScheduler:
    """The training schedule (Stable Diffusion 2 betas by default) with v-prediction.

    ``clip_sample=False``: latents (VAE or pixel-unshuffled) are not bounded to [-1, 1]
    in general, so clipping the predicted x0 would be wrong for the VAE codec.
    """
    return DDPMScheduler(
        num_train_timesteps=num_train_timesteps,
        beta_start=0.00085,
        beta_end=0.012,
        beta_schedule=beta_schedule,
        prediction_type="v_prediction",
        clip_sample=False,
        rescale_betas_zero_snr=rescale_zero_snr,
        timestep_spacing=timestep_spacing,
    )


def sample_timesteps(
    n: int, num_train_timesteps: int, terminal_fraction: float = 0.0, generator: torch.Generator | None = None
) -> torch.Tensor:
    """Training timesteps (n,): uniform over [0, T), then a ``terminal_fraction`` share set to T-1.

    Why the extra share at T-1: single-step inference evaluates the model only there (zero SNR:
    the input is pure noise and x0 = -v), but uniform sampling trains that regime 1/T of the
    time, so an under-trained model copies input noise into its prediction.  Extra terminal
    samples teach it to ignore the noise and regress x0 from the condition (the observation
    behind single-step fine-tuning in Lotus and E2E-FT); the rest keep DDIM usable.
    With fraction 0 no extra random numbers are drawn (the uniform stream stays as it was)."""
    if not 0.0 <= terminal_fraction <= 1.0:
        raise ValueError(f"terminal_fraction must lie in [0, 1], got {terminal_fraction}")
    t = torch.randint(0, num_train_timesteps, (n,), generator=generator)
    if terminal_fraction > 0:
        t = torch.where(torch.rand(n, generator=generator) < terminal_fraction, num_train_timesteps - 1, t)
    return t


def _coefficients(alphas_cumprod: torch.Tensor, t: torch.Tensor, like: torch.Tensor):
    """sqrt(a_t), sqrt(1 - a_t) for per-sample t (B,), shaped (B, 1, ..., 1) like ``like``."""
    if t.ndim != 1 or t.shape[0] != like.shape[0]:
        raise ValueError(f"t must have shape ({like.shape[0]},) (one timestep per sample), got {tuple(t.shape)}")
    if t.is_floating_point() or t.is_complex() or t.dtype == torch.bool:
        raise ValueError(f"t must hold integer timesteps, got dtype {t.dtype}")
    # Indexing would wrap a negative t around (t = -1 read a_{T-1}) and fail opaquely past the end.
    last = alphas_cumprod.shape[0] - 1
    if t.numel() and (bool((t < 0).any()) or bool((t > last).any())):
        bad = t[(t < 0) | (t > last)]
        raise ValueError(f"timesteps must lie in [0, {last}] (T = {last + 1}), got {bad[:4].tolist()}")
    a = alphas_cumprod.to(device=like.device, dtype=torch.float64)[t.to(like.device).long()]
    a = a.clamp(0.0, 1.0)  # exact 0 at a zero-SNR terminal step; guard sqrt against rounding
    shape = (-1,) + (1,) * (like.ndim - 1)
    return a.sqrt().to(like.dtype).view(shape), (1.0 - a).sqrt().to(like.dtype).view(shape)


def v_to_x0(x_t: torch.Tensor, v: torch.Tensor, alphas_cumprod: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """x0 = sqrt(a) x_t - sqrt(1 - a) v."""
    sa, s1a = _coefficients(alphas_cumprod, t, x_t)
    return sa * x_t - s1a * v


def v_to_eps(x_t: torch.Tensor, v: torch.Tensor, alphas_cumprod: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """eps = sqrt(1 - a) x_t + sqrt(a) v."""
    sa, s1a = _coefficients(alphas_cumprod, t, x_t)
    return s1a * x_t + sa * v
