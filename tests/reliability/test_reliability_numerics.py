"""Issue 18: timesteps outside [0, T-1] and NaN conditions are refused, not silently wrapped or spread."""

from __future__ import annotations

import pytest
import torch

from pilight.diffusion.conditioning import LearnedEmbedding
from pilight.diffusion.model import DomainDiffusion
from pilight.diffusion.sampler import sample
from pilight.diffusion.schedule import make_train_scheduler, v_to_eps, v_to_x0
from pilight.diffusion.unet import UNetSpec, build_unet

ALPHAS = make_train_scheduler().alphas_cumprod  # T = 1000


@pytest.mark.parametrize("fn", [v_to_x0, v_to_eps])
@pytest.mark.parametrize("t", [-1, 1000, 5000])
def test_timesteps_outside_the_schedule_are_refused(fn, t):
    x = torch.randn(2, 4, 2, 2)
    # t = -1 used to index from the end: v_to_x0(t=-1) equalled v_to_x0(t=999).
    with pytest.raises(ValueError, match=r"timesteps must lie in \[0, 999\]"):
        fn(x, torch.randn_like(x), ALPHAS, torch.tensor([5, t]))


def test_float_timesteps_are_refused_and_the_edges_accepted():
    x = torch.randn(2, 4, 2, 2)
    with pytest.raises(ValueError, match="integer"):
        v_to_x0(x, x, ALPHAS, torch.tensor([1.5, 2.0]))
    assert torch.isfinite(v_to_x0(x, x, ALPHAS, torch.tensor([0, 999]))).all()


def _tiny_model():
    torch.manual_seed(0)
    spec = UNetSpec(
        sample_size=8,
        block_out_channels=(8, 8),
        layers_per_block=1,
        attention_head_dim=4,
        cross_attention_dim=8,
        norm_num_groups=4,
        down_block_types=("CrossAttnDownBlock2D", "DownBlock2D"),
        up_block_types=("UpBlock2D", "CrossAttnUpBlock2D"),
    )
    unet = build_unet(spec, in_channels=4 + 4, out_channels=4, num_domains=2)
    return DomainDiffusion(unet, LearnedEmbedding(8), 2, 4, items_per_sample=2, cross_batch=True).eval()


@pytest.mark.parametrize("what", ["cond", "ehs"])
def test_sampler_refuses_a_nan_condition(what):
    model = _tiny_model()
    cond, ehs = torch.randn(4, 4, 8, 8), torch.randn(4, 1, 8)
    ids = torch.arange(2).repeat(2)
    out = sample(model, cond, ids, ehs, items_per_sample=2, steps=1, generator=torch.Generator().manual_seed(0))
    assert torch.isfinite(out).all()
    (cond if what == "cond" else ehs)[3].view(-1)[0] = float("nan")
    # Before: exit 0 and an all-NaN output (the NaN spreads through cross-batch attention).
    name = "cond_latents" if what == "cond" else "encoder_hidden_states"
    with pytest.raises(ValueError, match=rf"{name} holds NaN/Inf in 1 item\(s\) \(first: item 3 of 4\)"):
        sample(model, cond, ids, ehs, items_per_sample=2, steps=1, generator=torch.Generator().manual_seed(0))
