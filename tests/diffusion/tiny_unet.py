"""The tiny UNet the diffusion tests share: as our UNetSpec (build_unet) and as a plain diffusers model."""

from __future__ import annotations

from dataclasses import asdict

import torch
from diffusers import UNet2DConditionModel

from pilight.diffusion.unet import UNetSpec

TINY = UNetSpec(
    sample_size=8,
    block_out_channels=(32, 32),
    layers_per_block=1,
    attention_head_dim=4,
    cross_attention_dim=16,
    norm_num_groups=8,
    down_block_types=("CrossAttnDownBlock2D", "DownBlock2D"),
    up_block_types=("UpBlock2D", "CrossAttnUpBlock2D"),
)


def tiny_diffusers_unet() -> UNet2DConditionModel:
    """A diffusers UNet of TINY's shape, 4 channels in and out, seeded weights."""
    torch.manual_seed(0)
    return UNet2DConditionModel(in_channels=4, out_channels=4, **asdict(TINY))
