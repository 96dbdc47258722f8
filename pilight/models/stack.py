"""params -> codec + UNet + attention + conditioning + schedule (a DiffusionStack), the same code for both stages,
for inference (pilight.models) and training (pilight.train) alike. Its files on disk are
pilight.models.folder's.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from pilight.diffusion.attention import set_cross_batch_attention
from pilight.diffusion.codec import make_codec
from pilight.diffusion.conditioning import make_conditioning, null_like
from pilight.diffusion.model import DomainDiffusion
from pilight.diffusion.sampler import sample
from pilight.diffusion.schedule import make_train_scheduler
from pilight.diffusion.unet import UNetSpec, build_unet, load_pretrained_unet
from pilight.params import SamplingParams

# How the training-time image grids (dvclive) sample: one evaluation at t = T-1, the model's x0
# estimate from pure noise. Four DDIM steps, used before, showed pure noise all through a
# CPU-budget run (DDIM needs every timestep learned), which told the user nothing. The sampler a
# user picks lives in the infer sections, which training must not read: changing them never retrains.
PREVIEW_SAMPLING = SamplingParams(mode="single_step", cfg_scale=1.0)


class ModelError(ValueError):
    """A model cannot be built or loaded as the params describe (paths, channels, sizes)."""


@dataclass
class DiffusionStack:
    codec: object
    model: DomainDiffusion
    scheduler: object
    items_per_sample: int
    cross_batch: bool

    def alphas_cumprod(self, device) -> torch.Tensor:
        return self.scheduler.alphas_cumprod.to(device)

    def encode_condition(self, image: torch.Tensor, drop: torch.Tensor) -> torch.Tensor:
        """Cross-attention states (B, tokens, D); dropped samples get the null (zero) state."""
        return self.model.condition_states(image, drop)

    def null_condition(self, ehs: torch.Tensor) -> torch.Tensor:
        return null_like(ehs)

    def sample(
        self,
        z_cond: torch.Tensor,
        ids: torch.Tensor,
        image: torch.Tensor,
        items_per_sample: int,
        sp: SamplingParams,
        generator: torch.Generator | None = None,
    ) -> torch.Tensor:
        """Clean latents (B * V, C, h, w) of the V = ``items_per_sample`` items of B samples in one batched pass,
        as ``sp`` says (steps, CFG against the null condition, ensemble); ``image``: the B condition images."""
        drop = torch.zeros(image.shape[0], dtype=torch.bool, device=image.device)
        ehs = self.encode_condition(image, drop).repeat_interleave(items_per_sample, 0)
        return sample(
            self.model,
            z_cond,
            ids,
            ehs,
            items_per_sample=items_per_sample,
            steps=sp.steps,
            cfg_scale=sp.cfg_scale,
            timestep_spacing=sp.timestep_spacing,
            mode=sp.mode,
            ensemble=sp.ensemble,
            generator=generator,
            null_hidden_states=self.null_condition(ehs),
            scheduler_config=self.scheduler.config,
        )

    def describe(self) -> dict[str, str]:
        """What each part is, for reports: substitutes are named, never silent."""
        return {
            "codec": self.codec.name,
            "conditioning": self.model.conditioning.name,
            "attention": f"cross-batch over {self.items_per_sample} items"
            if self.cross_batch
            else "vanilla self-attention",
        }


def build_stack(
    p,
    *,
    num_domains: int,
    items_per_sample: int | None = None,
    cond_channels: int | None = None,
    maps_per_item: int = 1,
) -> DiffusionStack:
    """p: a params section with codec, unet, conditioning, cross_batch_attention, schedule.
    ``maps_per_item``: how many maps one UNet item predicts, stacked on channels (stage 1's joint layout:
    the UNet's output is that many codec latents)."""
    items_per_sample = items_per_sample or num_domains
    codec = make_codec(p.codec.kind, factor=p.codec.factor, path=p.codec.path)
    latent = codec.latent_channels
    cond = cond_channels or latent
    if p.unet.init == "pretrained" and maps_per_item != 1:
        raise ModelError(
            f"a pretrained UNet predicts one map per item; {maps_per_item} maps per item need a UNet built from params"
        )
    latent *= maps_per_item
    if p.unet.init == "pretrained":
        unet = load_pretrained_unet(p.unet.path, in_channels=latent + cond, num_domains=num_domains)
        if unet.config.out_channels != latent:
            raise ModelError(
                f"unet.path {p.unet.path}: out_channels {unet.config.out_channels} != codec latent channels {latent} ({codec.name})"
            )
    else:
        n = len(p.unet.block_out_channels)
        # Attention everywhere but the full-resolution level, where its token count is largest.
        down = ("DownBlock2D",) + ("CrossAttnDownBlock2D",) * (n - 1)
        up = ("CrossAttnUpBlock2D",) * (n - 1) + ("UpBlock2D",)
        spec = UNetSpec(
            block_out_channels=tuple(p.unet.block_out_channels),
            layers_per_block=p.unet.layers_per_block,
            attention_head_dim=p.unet.attention_head_dim,
            cross_attention_dim=p.unet.cross_attention_dim,
            down_block_types=down,
            up_block_types=up,
            norm_num_groups=min(32, min(p.unet.block_out_channels)),
        )
        unet = build_unet(spec, in_channels=latent + cond, out_channels=latent, num_domains=num_domains)
    dim = unet.config.cross_attention_dim
    conditioning = make_conditioning(p.conditioning.kind, p.conditioning.clip_path, dim)
    if conditioning.dim != dim:
        raise ModelError(
            f"conditioning {conditioning.name} gives {conditioning.dim}-d states but the UNet's cross_attention_dim is {dim}"
        )
    set_cross_batch_attention(unet, items_per_sample if p.cross_batch_attention else None)
    s = p.schedule
    model = DomainDiffusion(
        unet,
        conditioning,
        num_domains=num_domains,
        cond_channels=cond,
        terminal_timestep=s.num_train_timesteps - 1 if s.terminal_input == "zero" else None,
    )
    scheduler = make_train_scheduler(s.num_train_timesteps, s.beta_schedule, s.rescale_zero_snr, s.timestep_spacing)
    return DiffusionStack(codec, model, scheduler, items_per_sample, p.cross_batch_attention)


def check_image_size(size: tuple[int, int], factor: int, where: str) -> None:
    if size[0] % factor or size[1] % factor:
        raise ModelError(f"{where}: image size {size[0]}x{size[1]} is not divisible by the codec factor {factor}")
