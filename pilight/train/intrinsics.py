"""Stage 1, inverse neural rendering: one image -> albedo, normal, roughness, metallic together.

Each sample becomes V = 4 batch items (one per domain, sample-major), all conditioned on the same
image latent, at the same timestep, told apart by one-hot domain labels; cross-batch attention
lets the four outputs see each other (paper, Sec. "Stage 1: Inverse Neural Rendering").
Loss (paper, L_stage1): MSE(v_pred * m_z, v_target * m_z), m_z = the mask on the latent grid.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from pilight.data import schema
from pilight.data.colour import linear_to_srgb, srgb_to_linear, to_uint8
from pilight.data.shards import intrinsics_dataset, make_loader
from pilight.diffusion.schedule import sample_timesteps
from pilight.eval.grids import labelled_grid
from pilight.params import DOMAINS, IntrinsicsParams, SamplingParams
from pilight.train.build import PREVIEW_SAMPLING, Stack, build_stack


def domain_targets(batch: dict, domains: tuple[str, ...] = DOMAINS, albedo_space: str = "linear") -> torch.Tensor:
    """(B, V, 3, H, W) in [-1, 1]; 1-channel maps are replicated to 3 so every domain has one latent shape.
    albedo_space "srgb": the albedo is predicted in sRGB (decoded back to linear by targets_to_maps)."""
    maps = []
    for d in domains:
        x = batch[d]
        x = schema.to_model(d, linear_to_srgb(x.clamp(0, 1)) if d == "albedo" and albedo_space == "srgb" else x)
        maps.append(x.expand(-1, 3, -1, -1) if x.shape[1] == 1 else x)
    return torch.stack(maps, dim=1)


def targets_to_maps(x: torch.Tensor, domains: tuple[str, ...], albedo_space: str = "linear") -> dict[str, torch.Tensor]:
    """Inverse of `domain_targets` for predictions (B, V, 3, H, W) -> linear maps in their ranges."""
    out = {}
    for i, d in enumerate(domains):
        y = x[:, i].clamp(-1, 1)
        if d == "normal":
            out[d] = F.normalize(y, dim=1, eps=1e-6)
        elif d in ("roughness", "metallic"):
            out[d] = schema.from_model(d, y.mean(dim=1, keepdim=True)).clamp(0, 1)
        else:
            a = schema.from_model(d, y).clamp(0, 1)  # in [0, 1]: the sRGB curve's domain
            out[d] = srgb_to_linear(a) if albedo_space == "srgb" else a
    return out


def latent_mask(mask: torch.Tensor, factor: int) -> torch.Tensor:
    """The mask on the latent grid: a latent cell counts when most of its pixels are reliable."""
    return (F.avg_pool2d(mask, factor) >= 0.5).to(mask.dtype) if factor > 1 else mask


def masked_latent_mse(v_pred: torch.Tensor, v_tgt: torch.Tensor, m: torch.Tensor) -> torch.Tensor:
    """Paper L_stage1 = MSE(v_pred * m_z, v_target * m_z); 0 (not NaN) for an empty mask."""
    return F.mse_loss(v_pred * m, v_tgt * m)


class IntrinsicsTask:
    """The stage-1 Task for pilight.train.loop.train."""

    def __init__(self, p: IntrinsicsParams, shard_dir: Path, *, seed: int, device: str = "cpu"):
        self.p, self.shard_dir, self.seed, self.device = p, Path(shard_dir), seed, device
        self.stack: Stack = build_stack(p, num_domains=len(DOMAINS), cond_channels=None)
        self.samples_per_batch = p.train.batch_size
        self.preview = PREVIEW_SAMPLING

    def trainable(self) -> torch.nn.Module:
        return self.stack.model

    def batches(self, epoch: int) -> Iterable[Any]:
        ds = intrinsics_dataset(self.shard_dir, "train", shuffle=True, seed=self.seed)
        ds.set_epoch(epoch)
        return make_loader(ds, self.p.train.batch_size, num_workers=self.p.train.num_workers, drop_last=True)

    def loss(
        self, batch: dict, generator: torch.Generator, model: torch.nn.Module | None = None
    ) -> tuple[torch.Tensor, dict[str, float]]:
        """``model``: what the loop prepared (a DDP wrapper under several processes); default the stack's."""
        s, V = self.stack, len(DOMAINS)
        model = s.model if model is None else model
        dev = next(s.model.parameters()).device
        image = schema.to_model("image", batch["image"]).to(dev)
        B = image.shape[0]
        with torch.no_grad():
            z0 = s.codec.encode(domain_targets(batch, DOMAINS, self.p.albedo_space).flatten(0, 1).to(dev))
            z_cond = s.codec.encode(image).repeat_interleave(V, 0)
        m = latent_mask(batch["mask"].to(dev), s.codec.factor).repeat_interleave(V, 0)
        # One timestep per sample, shared by its V domains: they denoise together.
        t = sample_timesteps(
            B, s.scheduler.config.num_train_timesteps, self.p.train.terminal_fraction, generator
        ).repeat_interleave(V)
        noise = torch.randn(z0.shape, generator=generator).to(dev)
        drop = (torch.rand(B, generator=generator) < self.p.train.cond_dropout).to(
            dev
        )  # CFG needs an unconditional model
        t = t.to(dev)
        x_t = s.scheduler.add_noise(z0, noise, t)
        z_cond = z_cond * (~drop).repeat_interleave(V).to(z_cond.dtype)[:, None, None, None]
        domain_ids = torch.arange(V, device=dev).repeat(B)
        v = model(x_t, z_cond, t, domain_ids, condition_images=image, drop=drop)
        loss = masked_latent_mse(v.float(), s.scheduler.get_velocity(z0, noise, t).float(), m)
        return loss, {"mask_fraction": float(m.mean())}

    @torch.no_grad()
    def predict(
        self,
        image: torch.Tensor,
        domains: tuple[str, ...],
        sp: SamplingParams,
        generator: torch.Generator | None = None,
    ) -> dict[str, torch.Tensor]:
        """Linear HDR image batch (B, 3, H, W) -> predicted maps for `domains`, all in one batched pass."""
        s = self.stack
        dev = next(s.model.parameters()).device
        x = schema.to_model("image", image).to(dev)
        B, V = x.shape[0], len(domains)
        z_cond = s.codec.encode(x).repeat_interleave(V, 0)
        ids = torch.tensor([DOMAINS.index(d) for d in domains], device=dev).repeat(B)
        z0 = s.sample(z_cond, ids, x, V, sp, generator)
        pred = s.codec.decode(z0).float().unflatten(0, (B, V))
        return targets_to_maps(pred, domains, self.p.albedo_space)

    @torch.no_grad()
    def images(self, batch: dict) -> dict[str, np.ndarray]:
        """input | ground truth | prediction, one row per intrinsic, for the first sample."""
        pred = self.predict(batch["image"][:1], DOMAINS, self.preview, torch.Generator().manual_seed(0))
        rows = []
        for d in DOMAINS:
            gt, pr = batch[d][0], pred[d][0].cpu()
            if d == "normal":
                gt, pr = (gt + 1) / 2, (pr + 1) / 2
            rows.append([to_uint8(batch["image"][0], hdr=True), to_uint8(gt, False), to_uint8(pr, False)])
        return {"intrinsics_grid": labelled_grid(rows, ["input", "truth", "model"], row_labels=list(DOMAINS))}
