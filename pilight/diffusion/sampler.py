"""Sampling x0 latents from a ``DomainDiffusion`` (v-prediction).

All V requested domains of all samples run in one batched UNet call per step, so the
items can attend to each other.  Batch layout of one call, outer to inner:

    [guidance branch (cond, uncond)] x [ensemble member] x [sample] x [item]

Every block boundary is a multiple of V, so a cross-batch attention group of V
consecutive items always holds the V items of one (branch, member, sample): the
conditional and unconditional items are never mixed.
"""

from __future__ import annotations

import warnings
from typing import Any

import torch
from diffusers import DDIMScheduler

from .conditioning import null_like
from .schedule import make_train_scheduler, v_to_x0


@torch.no_grad()
def sample(
    model,
    cond_latents: torch.Tensor,
    domain_ids: torch.Tensor,
    encoder_hidden_states: torch.Tensor,
    *,
    items_per_sample: int,
    steps: int = 10,
    cfg_scale: float = 1.0,
    timestep_spacing: str = "trailing",
    mode: str = "ddim",
    ensemble: int = 1,
    generator: torch.Generator | None = None,
    null_hidden_states: torch.Tensor | None = None,
    scheduler_config: Any = None,
    noise: torch.Tensor | None = None,
) -> torch.Tensor:
    """x0 latents (B*V x C x h x w) for ``B*V`` items (sample-major, V = ``items_per_sample``).

    ``cond_latents``, ``domain_ids``, ``encoder_hidden_states`` have one entry per item;
    any subset of domains works (e.g. albedo + normal only: V = 2, half the cost).

    mode "ddim": deterministic DDIM (eta 0) with ``steps`` steps and ``timestep_spacing``;
      ``set_alpha_to_one=True`` so the last step lands on x0 itself (no residual noise);
      with trailing spacing the first step is t = T-1, so steps=1 equals "single_step".
    mode "single_step": one evaluation at t = T-1 on pure noise, x0 = v_to_x0
      (meant for zero-SNR schedules, where x_T is exactly noise).
    cfg_scale != 1: v = v_u + s (v_c - v_u); the unconditional branch zeroes the condition
      latents and uses ``null_hidden_states`` (default zeros, ``null_like``).
    ensemble: that many independent noise draws per item, returned as their mean x0.
    noise: optional initial noise, shape (ensemble*B*V, C, h, w), ensemble-major.
    ``scheduler_config``: the training scheduler's config (default ``make_train_scheduler()``).
    """
    n, _, h, w = cond_latents.shape
    if n % items_per_sample:
        raise ValueError(f"{n} items are not samples x items_per_sample ({items_per_sample})")
    if domain_ids.shape != (n,) or encoder_hidden_states.shape[0] != n:
        raise ValueError(
            f"need one domain id and one embedding per item ({n}), got {tuple(domain_ids.shape)} "
            f"and {tuple(encoder_hidden_states.shape)}"
        )
    if mode not in ("ddim", "single_step"):
        raise ValueError(f"unknown sampling mode {mode!r}; expected 'ddim' or 'single_step'")
    if ensemble < 1 or steps < 1:
        raise ValueError(f"ensemble and steps must be >= 1, got {ensemble} and {steps}")
    # Cross-batch attention mixes all items of a group, so one NaN condition makes every output NaN,
    # silently: refuse it here, naming the input and the item.
    _check_finite(cond_latents, "cond_latents")
    _check_finite(encoder_hidden_states, "encoder_hidden_states")
    if null_hidden_states is not None:
        _check_finite(null_hidden_states, "null_hidden_states")
    if noise is not None:
        _check_finite(noise, "noise")
    if not torch.isfinite(torch.as_tensor(cfg_scale)):
        raise ValueError(f"cfg_scale must be finite, got {cfg_scale}")

    if mode == "single_step" and ensemble > 1 and getattr(model, "terminal_timestep", None) is not None:
        warnings.warn(
            f"ensemble={ensemble} with single-step sampling repeats one prediction: the model reads 0, "
            "not the noise, at t = T-1 (schedule.terminal_input: zero); it costs time and changes nothing",
            stacklevel=2,
        )

    device = cond_latents.device
    dtype = next(model.parameters()).dtype
    config = scheduler_config if scheduler_config is not None else make_train_scheduler().config
    scheduler = DDIMScheduler.from_config(
        config,
        prediction_type="v_prediction",
        timestep_spacing=timestep_spacing,
        set_alpha_to_one=True,
        clip_sample=False,
        thresholding=False,
    )

    shape = (ensemble * n, model.latent_channels, h, w)
    if noise is None:
        noise = torch.randn(shape, generator=generator, device=generator.device if generator else device)
    elif tuple(noise.shape) != shape:
        raise ValueError(
            f"noise must have shape {shape} (ensemble x items, latent channels, h, w), got {tuple(noise.shape)}"
        )
    latents = noise.to(device=device, dtype=torch.float32)

    # Per-item inputs tiled over ensemble members, then over (cond, uncond) branches.
    cond = cond_latents.to(dtype).repeat(ensemble, 1, 1, 1)
    ids = domain_ids.repeat(ensemble)
    ehs = encoder_hidden_states.to(dtype).repeat(ensemble, 1, 1)
    guided = cfg_scale != 1.0
    if guided:
        null = null_like(encoder_hidden_states) if null_hidden_states is None else null_hidden_states
        if null.shape != encoder_hidden_states.shape:
            raise ValueError(
                f"null_hidden_states {tuple(null.shape)} must match encoder_hidden_states "
                f"{tuple(encoder_hidden_states.shape)}"
            )
        cond = torch.cat([cond, torch.zeros_like(cond)])
        ids = torch.cat([ids, ids])
        ehs = torch.cat([ehs, null.to(device=device, dtype=dtype).repeat(ensemble, 1, 1)])

    def predict_v(x_t: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        x_in = torch.cat([x_t, x_t]) if guided else x_t
        t_in = t.to(device).long().expand(x_in.shape[0])
        v = model(x_in.to(dtype), cond, t_in, ids, ehs).float()
        if guided:
            v_c, v_u = v.chunk(2)
            v = v_u + cfg_scale * (v_c - v_u)
        return v

    previous_items = model.items_per_sample
    model.set_items_per_sample(items_per_sample)
    try:
        if mode == "single_step":
            t_last = torch.full((latents.shape[0],), scheduler.config.num_train_timesteps - 1, device=device)
            x0 = v_to_x0(latents, predict_v(latents, t_last[0]), scheduler.alphas_cumprod, t_last)
        else:
            scheduler.set_timesteps(steps, device=device)
            for t in scheduler.timesteps:
                latents = scheduler.step(predict_v(latents, t), t, latents, eta=0.0).prev_sample
            x0 = latents
    finally:
        model.set_items_per_sample(previous_items)  # leave the training-time grouping as it was
    return x0.view(ensemble, n, *x0.shape[1:]).mean(0)


def _check_finite(x: torch.Tensor, name: str) -> None:
    bad = ~torch.isfinite(x.flatten(1) if x.ndim > 1 else x[:, None])
    if bool(bad.any()):
        items = bad.any(1).nonzero().flatten().tolist()
        raise ValueError(
            f"sample: {name} holds NaN/Inf in {len(items)} item(s) (first: item {items[0]} of "
            f"{x.shape[0]}); the condition is broken upstream (image, codec or conditioning encoder)"
        )
