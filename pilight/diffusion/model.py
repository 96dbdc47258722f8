"""``DomainDiffusion``: the Stage 1 (and Stage 2 branch) denoiser around the UNet.

One batched call predicts v for ``samples x V`` items (sample-major).  Item i gets
``[noisy latent_i, condition latent_i]`` on channels (paper Sec. Stage 1) and a one-hot
domain label (paper: "four one-hot labels L ... control which batch outputs which
intrinsic component"); the items of a sample talk to each other through cross-batch
self-attention (``attention.py``).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from .attention import CrossBatchAttnProcessor, set_cross_batch_attention
from .conditioning import null_like


class DomainDiffusion(nn.Module):
    """unet + conditioning + domain labels.

    ``cond_channels`` is the width of the condition part of the UNet input
    (``unet.in_channels - unet.out_channels``).  Condition latents narrower than that are
    zero-padded on channels: the Stage 2 branches concatenate different numbers of
    condition maps (e.g. the shading branch has fewer inputs than the final composer),
    so one UNet shape serves them all and missing inputs read as zero (the same value
    classifier-free guidance uses for "no condition").

    Cross-batch attention is whatever ``set_cross_batch_attention`` installed on the UNet
    (``cross_batch=None``, the default, keeps it); ``cross_batch=True/False`` installs it
    here.  ``items_per_sample`` is the number of consecutive batch items that form one sample
    (default: the installed processors' value, else ``num_domains``); ``set_items_per_sample``
    changes it in place on the installed processors, so a later V = 1 call (one domain)
    does not switch cross-batch attention off for good.  Without cross-batch processors
    (the ablation) ``items_per_sample`` only validates the batch layout.

    ``terminal_timestep`` (schedule.terminal_input: zero, set to T-1): items at that timestep
    read a zero latent instead of x_t; None (the paper) = every item reads x_t.
    """

    def __init__(
        self,
        unet: nn.Module,
        conditioning: nn.Module,
        num_domains: int,
        cond_channels: int,
        items_per_sample: int | None = None,
        cross_batch: bool | None = None,
        terminal_timestep: int | None = None,
    ):
        super().__init__()
        cfg = unet.config
        if cfg.in_channels != cfg.out_channels + cond_channels:
            raise ValueError(
                f"UNet input has {cfg.in_channels} channels but latent ({cfg.out_channels}) "
                f"+ condition ({cond_channels}) = {cfg.out_channels + cond_channels}"
            )
        if cfg.class_embed_type != "projection" or cfg.projection_class_embeddings_input_dim != num_domains:
            raise ValueError(
                f"UNet needs class_embed_type='projection' with {num_domains} inputs, has "
                f"{cfg.class_embed_type!r} with {cfg.projection_class_embeddings_input_dim}"
            )
        if cfg.cross_attention_dim != conditioning.dim:
            raise ValueError(
                f"conditioning {conditioning.name!r} gives {conditioning.dim}-dim embeddings but "
                f"the UNet's cross_attention_dim is {cfg.cross_attention_dim}"
            )
        self.unet = unet
        self.conditioning = conditioning
        self.num_domains = int(num_domains)
        self.cond_channels = int(cond_channels)
        self.latent_channels = int(cfg.out_channels)
        if items_per_sample is None:
            installed = {p.items_per_sample for p in self._cross_batch_processors()}
            items_per_sample = installed.pop() if len(installed) == 1 else num_domains
        if cross_batch is not None:
            # V = 1 would install plain processors; install V >= 2 and set V in place below.
            set_cross_batch_attention(unet, max(2, items_per_sample) if cross_batch else None)
        self.set_items_per_sample(items_per_sample)
        # Items at this timestep read a zero latent instead of x_t (schedule.terminal_input: zero);
        # None = they read x_t. Both training and sampling go through forward().
        self.terminal_timestep = terminal_timestep

    def _cross_batch_processors(self) -> list[CrossBatchAttnProcessor]:
        return [p for p in self.unet.attn_processors.values() if isinstance(p, CrossBatchAttnProcessor)]

    @property
    def cross_batch(self) -> bool:
        return bool(self._cross_batch_processors())

    def set_items_per_sample(self, items_per_sample: int) -> None:
        """Group every ``items_per_sample`` consecutive items into one sample (cross-batch attention)."""
        if items_per_sample < 1:
            raise ValueError(f"items_per_sample must be >= 1, got {items_per_sample}")
        for processor in self._cross_batch_processors():
            processor.items_per_sample = int(items_per_sample)
        self.items_per_sample = int(items_per_sample)

    def embed(self, images: torch.Tensor) -> torch.Tensor:
        """Cross-attention tokens for [-1, 1] condition images (B x T x D)."""
        return self.conditioning(images)

    def condition_states(self, images: torch.Tensor, drop: torch.Tensor | None = None) -> torch.Tensor:
        """embed(images), with the samples flagged in ``drop`` given the null (zero) state: classifier-free
        guidance's dropout in training, and its unconditional branch when sampling."""
        ehs = self.embed(images)
        return ehs if drop is None else torch.where(drop[:, None, None], null_like(ehs), ehs)

    def forward(
        self,
        noisy_latents: torch.Tensor,
        cond_latents: torch.Tensor,
        timesteps: torch.Tensor,
        domain_ids: torch.Tensor,
        encoder_hidden_states: torch.Tensor | None = None,
        *,
        condition_images: torch.Tensor | None = None,
        drop: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """v for every item. The cross-attention states are either given (``encoder_hidden_states``,
        one per item: the sampler's path) or embedded here from ``condition_images`` (one per sample,
        [-1, 1]), with the samples flagged in ``drop`` given the null state (classifier-free guidance
        dropout). Training takes the second path so that every trainable parameter, the conditioning's
        included, is used inside this forward: a DDP wrapper (accelerate.prepare) only sees that."""
        n = noisy_latents.shape[0]
        if (encoder_hidden_states is None) == (condition_images is None):
            raise ValueError("give exactly one of encoder_hidden_states and condition_images")
        if encoder_hidden_states is None:
            ehs = self.condition_states(condition_images, drop)
            if n % ehs.shape[0]:
                raise ValueError(f"{ehs.shape[0]} condition images for a batch of {n} items")
            encoder_hidden_states = ehs.repeat_interleave(n // ehs.shape[0], 0)
        if noisy_latents.shape[1] != self.latent_channels:
            raise ValueError(
                f"noisy latents have {noisy_latents.shape[1]} channels, the UNet predicts "
                f"{self.latent_channels} (codec/UNet channel mismatch)"
            )
        if cond_latents.shape[0] != n or cond_latents.shape[2:] != noisy_latents.shape[2:]:
            raise ValueError(
                f"cond latents {tuple(cond_latents.shape)} do not match noisy latents "
                f"{tuple(noisy_latents.shape)} in batch/spatial size"
            )
        if cond_latents.shape[1] > self.cond_channels:
            raise ValueError(
                f"cond latents have {cond_latents.shape[1]} channels, the UNet takes at most {self.cond_channels}"
            )
        if domain_ids.shape != (n,) or domain_ids.dtype != torch.long:
            raise ValueError(
                f"domain_ids must be a long tensor of shape ({n},), got {domain_ids.dtype} {tuple(domain_ids.shape)}"
            )
        if n % self.items_per_sample:
            raise ValueError(f"batch {n} is not samples x items_per_sample ({self.items_per_sample})")
        if encoder_hidden_states.shape[0] != n:
            raise ValueError(f"encoder_hidden_states has batch {encoder_hidden_states.shape[0]}, expected {n}")
        if int(domain_ids.min()) < 0 or int(domain_ids.max()) >= self.num_domains:
            raise ValueError(f"domain_ids must lie in [0, {self.num_domains}), got {domain_ids.tolist()}")

        if timesteps.ndim == 0:
            timesteps = timesteps.expand(n)
        if self.terminal_timestep is not None:
            # Zero-SNR x_T is pure noise, independent of x0: feed its mean so the x0 estimate there
            # is a deterministic function of the condition (E2E-FT). The sampler still steps from
            # the real x_T, so DDIM stays exact: at a_T = 0 its eps estimate is x_T itself.
            at_end = (timesteps == self.terminal_timestep).view(-1, 1, 1, 1)
            noisy_latents = torch.where(at_end, torch.zeros_like(noisy_latents), noisy_latents)
        pad = self.cond_channels - cond_latents.shape[1]
        if pad:
            cond_latents = F.pad(cond_latents, (0, 0, 0, 0, 0, pad))
        sample = torch.cat([noisy_latents, cond_latents.to(noisy_latents.dtype)], dim=1)
        onehot = F.one_hot(domain_ids, self.num_domains).to(noisy_latents.dtype)
        return self.unet(sample, timesteps, encoder_hidden_states=encoder_hidden_states, class_labels=onehot).sample
