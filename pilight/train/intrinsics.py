"""Stage 1, inverse neural rendering: one image -> albedo, normal, roughness, metallic together.

Two layouts (`intrinsics.layout`):
- ``domains`` (the paper): each sample becomes V = 4 batch items (one per domain, sample-major), all
  conditioned on the same image latent, at the same timestep, told apart by one-hot domain labels;
  cross-batch attention lets the four outputs see each other (paper, Sec. "Stage 1").
- ``joint``: one item per sample whose UNet output is the four maps' latents stacked on channels: a
  quarter of the UNet work per sample, which on a CPU buys four times the samples.

Two objectives (`intrinsics.objective`):
- ``diffusion`` (the paper, L_stage1): MSE(v_pred * m_z, v_target * m_z) at sampled timesteps,
  m_z = the mask on the latent grid.
- ``task`` (E2E-FT): every sample at t = T-1 from a zero latent, the one evaluation single-step
  inference makes; the prediction x0 = -v is decoded and graded map by map in pixel space
  (pilight.train.map_losses). No training sample is spent on timesteps inference never visits.

Augmentations exact for renders (`intrinsics.augment`): a horizontal flip (normals' x negated) and
square crops.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from pilight.data import schema
from pilight.data.colour import linear_to_srgb, srgb_to_linear
from pilight.data.mirror import mirrored
from pilight.data.shard_reader import intrinsics_dataset, make_loader
from pilight.diffusion.schedule import sample_timesteps, v_to_x0
from pilight.eval.grids import labelled_grid
from pilight.models.intrinsics import IntrinsicsModel
from pilight.models.stack import PREVIEW_SAMPLING
from pilight.params import DOMAINS, IntrinsicsParams
from pilight.pictures import to_uint8
from pilight.train.grad_shares import grad_shares
from pilight.train.map_losses import summed, weighted_terms


def domain_targets(batch: dict, domains: tuple[str, ...] = DOMAINS, albedo_space: str = "linear") -> torch.Tensor:
    """(B, V, 3, H, W) in [-1, 1]; 1-channel maps are replicated to 3 so every domain has one latent shape.
    albedo_space "srgb": the albedo is predicted in sRGB (decoded back to linear by pilight.models.intrinsics.targets_to_maps)."""
    maps = []
    for d in domains:
        x = batch[d]
        x = schema.to_model(d, linear_to_srgb(x.clamp(0, 1)) if d == "albedo" and albedo_space == "srgb" else x)
        maps.append(x.expand(-1, 3, -1, -1) if x.shape[1] == 1 else x)
    return torch.stack(maps, dim=1)


def latent_mask(mask: torch.Tensor, factor: int) -> torch.Tensor:
    """The mask on the latent grid: a latent cell counts when most of its pixels are reliable."""
    return (F.avg_pool2d(mask, factor) >= 0.5).to(mask.dtype) if factor > 1 else mask


def masked_latent_mse(v_pred: torch.Tensor, v_tgt: torch.Tensor, m: torch.Tensor) -> torch.Tensor:
    """Paper L_stage1 = MSE(v_pred * m_z, v_target * m_z); 0 (not NaN) for an empty mask."""
    return F.mse_loss(v_pred * m, v_tgt * m)


def augment(batch: dict, aug, generator: torch.Generator) -> dict:
    """Flip and crop every map of a batch alike (intrinsics.augment); the flipped normals' x is negated,
    so the truth stays the truth of the flipped image. Draws from ``generator`` only what it uses."""
    keys = ("image", "mask", *DOMAINS)
    out = dict(batch)
    if aug.flip:
        flip = torch.rand(batch["image"].shape[0], generator=generator) < 0.5
        for k in keys:
            x = batch[k]
            out[k] = torch.where(flip.view(-1, 1, 1, 1).to(x.device), mirrored(k, x), x)
    if aug.crop is not None:
        h, w = batch["image"].shape[-2:]
        if aug.crop > min(h, w):
            raise ValueError(f"intrinsics.augment.crop {aug.crop} is larger than the images ({h}x{w})")
        top = int(torch.randint(0, h - aug.crop + 1, (), generator=generator))
        left = int(torch.randint(0, w - aug.crop + 1, (), generator=generator))
        for k in keys:
            out[k] = out[k][..., top : top + aug.crop, left : left + aug.crop]
    return out


def decoded_maps(pred: torch.Tensor, domains: tuple[str, ...], albedo_space: str) -> dict[str, torch.Tensor]:
    """Decoded predictions (B, V, 3, H, W) in [-1, 1] -> linear maps, differentiable (for the task loss):
    no clamp, normals not normalised (the angular loss does it), 1-channel maps the mean of their three."""
    out = {}
    for i, d in enumerate(domains):
        y = pred[:, i]
        if d in ("roughness", "metallic"):
            out[d] = schema.from_model(d, y.mean(dim=1, keepdim=True))
        elif d == "albedo":
            a = schema.from_model(d, y)
            out[d] = srgb_to_linear(a.clamp(0, 1)) if albedo_space == "srgb" else a
        else:
            out[d] = y
    return out


class IntrinsicsTask(IntrinsicsModel):
    """The stage-1 Task for pilight.train.loop.train: the inference model (pilight.models.intrinsics) and
    what training adds to it (batches, augmentations, the loss, the previews)."""

    def __init__(self, p: IntrinsicsParams, shard_dir: Path, *, seed: int, device: str = "cpu"):
        super().__init__(p)
        self.shard_dir, self.seed, self.device = Path(shard_dir), seed, device
        self.samples_per_batch = p.train.batch_size
        self.preview = PREVIEW_SAMPLING
        self._calls = 0  # loss() calls, for train.grad_share_every (logging only: no effect on the weights)

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
        batch = augment(batch, self.p.augment, generator)
        image = schema.to_model("image", batch["image"]).to(dev)
        B = image.shape[0]
        per_item = 1 if self.joint else V
        with torch.no_grad():
            z_cond = s.codec.encode(image).repeat_interleave(per_item, 0)
        ids = self._ids(B, dev)
        if self.p.objective == "task":
            return self._task_loss(batch, model, image, z_cond, ids, dev)
        with torch.no_grad():
            z0 = self._items(
                s.codec.encode(domain_targets(batch, DOMAINS, self.p.albedo_space).flatten(0, 1).to(dev)), B
            )
        m = latent_mask(batch["mask"].to(dev), s.codec.factor).repeat_interleave(per_item, 0)
        # One timestep per sample, shared by its V domains: they denoise together.
        t = sample_timesteps(
            B, s.scheduler.config.num_train_timesteps, self.p.train.terminal_fraction, generator
        ).repeat_interleave(per_item)
        noise = torch.randn(z0.shape, generator=generator).to(dev)
        drop = (torch.rand(B, generator=generator) < self.p.train.cond_dropout).to(
            dev
        )  # CFG needs an unconditional model
        t = t.to(dev)
        x_t = s.scheduler.add_noise(z0, noise, t)
        z_cond = z_cond * (~drop).repeat_interleave(per_item).to(z_cond.dtype)[:, None, None, None]
        v = model(x_t, z_cond, t, ids, condition_images=image, drop=drop)
        loss = masked_latent_mse(v.float(), s.scheduler.get_velocity(z0, noise, t).float(), m)
        return loss, {"mask_fraction": float(m.mean())}

    def _task_loss(self, batch, model, image, z_cond, ids, dev) -> tuple[torch.Tensor, dict[str, float]]:
        """objective: task: one evaluation at t = T-1 from a zero latent, x0 = -v decoded, task losses."""
        s, B = self.stack, image.shape[0]
        n = z_cond.shape[0]
        t = torch.full((n,), s.scheduler.config.num_train_timesteps - 1, dtype=torch.long, device=dev)
        x_t = torch.zeros(n, s.model.latent_channels, *z_cond.shape[-2:], device=dev, dtype=z_cond.dtype)
        v = model(x_t, z_cond, t, ids, condition_images=image, drop=None)
        x0 = v_to_x0(x_t, v.float(), s.alphas_cumprod(dev), t)
        pred = s.codec.decode(self._domains(x0, B)).float().unflatten(0, (B, len(DOMAINS)))
        maps = decoded_maps(pred, DOMAINS, self.p.albedo_space)
        gt = {d: batch[d].to(dev).float() for d in DOMAINS}
        mask = (batch["mask"].to(dev) > 0.5).float()
        weighted, parts = weighted_terms(maps, gt, mask, self.p.task_loss)
        terms = {k: float(v.detach()) for k, v in parts.items()}
        self._calls += 1
        every = self.p.train.grad_share_every
        if every and self._calls % every == 0:  # each map's share of the gradient: which map the run learns from
            terms |= grad_shares(weighted, [prm for prm in s.model.parameters() if prm.requires_grad])
        return summed(weighted), terms | {"mask_fraction": float(mask.mean())}

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
