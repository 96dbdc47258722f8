"""Image <-> latent codecs.  Every domain is a 3-channel image in [-1, 1]
(1-channel maps such as roughness/metallic are replicated to 3 by the caller).

Two implementations of one interface (``name``, ``factor``, ``latent_channels``,
``encode(x)``, ``decode(z, checkpoint=False)``):

* ``PixelCodec`` -- lossless pixel-unshuffle, for training from scratch on CPU.
* ``VaeCodec``   -- a frozen diffusers ``AutoencoderKL`` (Stable Diffusion 2's VAE in
  the paper: latents of 4 x H/8 x W/8), loaded from a local directory only.
"""

from __future__ import annotations

import os
from typing import Protocol

import torch
import torch.nn.functional as F
from torch import nn
from torch.utils.checkpoint import checkpoint as _checkpoint


class Codec(Protocol):
    name: str
    factor: int
    latent_channels: int

    def encode(self, x: torch.Tensor) -> torch.Tensor: ...

    def decode(self, z: torch.Tensor, checkpoint: bool = False) -> torch.Tensor: ...


def cell_mean(x: torch.Tensor, cell: int) -> torch.Tensor:
    """Each cell x cell block replaced by its mean (a target that is one value per codec cell)."""
    return F.interpolate(F.avg_pool2d(x, cell), scale_factor=cell, mode="nearest") if cell > 1 else x


def cell_smooth(x: torch.Tensor, cell: int) -> torch.Tensor:
    """Cell means, bilinearly interpolated back to pixels: smooth by construction, no structure
    inside a cell (what the targets of ``cell_mean`` decode to)."""
    if cell == 1:
        return x
    return F.interpolate(F.avg_pool2d(x, cell), scale_factor=cell, mode="bilinear", align_corners=False)


def _check_divisible(x: torch.Tensor, factor: int) -> None:
    h, w = x.shape[-2:]
    if h % factor or w % factor:
        raise ValueError(f"image size {h}x{w} is not divisible by the codec factor {factor}")


class PixelCodec(nn.Module):
    """B x 3 x H x W  <->  B x 3f^2 x H/f x W/f by pixel (un)shuffle; exact and parameter-free."""

    def __init__(self, factor: int):
        super().__init__()
        if factor < 1:
            raise ValueError(f"pixel codec factor must be >= 1, got {factor}")
        self.factor = int(factor)
        self.latent_channels = 3 * self.factor**2
        self.name = f"pixel-unshuffle-{self.factor}"

    def encode(self, x: torch.Tensor) -> torch.Tensor:
        _check_divisible(x, self.factor)
        return F.pixel_unshuffle(x, self.factor)

    def decode(self, z: torch.Tensor, checkpoint: bool = False) -> torch.Tensor:
        # ``checkpoint`` is accepted for interface parity; pixel_shuffle stores nothing worth freeing.
        return F.pixel_shuffle(z, self.factor)


class VaeCodec(nn.Module):
    """Frozen AutoencoderKL.  ``encode`` returns ``latent_dist.mean`` (deterministic targets,
    as Marigold/GeoWizard do) unless a ``generator`` is given, then a posterior sample;
    the result is ``(z - shift_factor) * scaling_factor`` with both read from the VAE config.

    The encoder runs in ``dtype``; the decoder (and post_quant_conv) is kept in fp32 and
    always runs in fp32 with autocast disabled: bf16 decodes of SD VAEs band and clip,
    and Stage 2 backpropagates image-space losses through ``decode``.
    """

    def __init__(self, path: str | os.PathLike, dtype: torch.dtype = torch.float32):
        super().__init__()
        from diffusers import AutoencoderKL

        path = os.fspath(path)
        if not os.path.isdir(path):
            raise FileNotFoundError(
                f"VAE directory not found: {path!r} (expected a diffusers "
                "AutoencoderKL saved with save_pretrained; nothing is downloaded)"
            )
        vae = AutoencoderKL.from_pretrained(path, local_files_only=True, torch_dtype=torch.float32)
        vae.requires_grad_(False).eval()
        vae.encoder.to(dtype)
        if vae.quant_conv is not None:
            vae.quant_conv.to(dtype)
        self.vae = vae
        self.encode_dtype = dtype
        cfg = vae.config
        self.scaling_factor = float(cfg.scaling_factor)
        self.shift_factor = float(getattr(cfg, "shift_factor", None) or 0.0)
        self.factor = 2 ** (len(cfg.block_out_channels) - 1)
        self.latent_channels = int(cfg.latent_channels)
        self.name = f"vae:{os.path.basename(os.path.normpath(path))}"

    def train(self, mode: bool = True):  # frozen: never switch the VAE to train mode
        super().train(mode)
        self.vae.eval()
        return self

    @torch.no_grad()
    def encode(self, x: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
        _check_divisible(x, self.factor)
        dist = self.vae.encode(x.to(self.encode_dtype)).latent_dist
        z = dist.mean if generator is None else dist.sample(generator)
        return (z.float() - self.shift_factor) * self.scaling_factor

    def _decode_fp32(self, z: torch.Tensor) -> torch.Tensor:
        with torch.autocast(device_type=z.device.type, enabled=False):
            z = z.float() / self.scaling_factor + self.shift_factor
            return self.vae.decode(z).sample

    def decode(self, z: torch.Tensor, checkpoint: bool = False) -> torch.Tensor:
        """fp32 image in ~[-1, 1]; differentiable w.r.t. ``z``.  ``checkpoint=True`` recomputes the
        decoder in backward instead of storing its activations (Stage 2 memory bound)."""
        if checkpoint and torch.is_grad_enabled() and z.requires_grad:
            return _checkpoint(self._decode_fp32, z, use_reentrant=False)
        return self._decode_fp32(z)


def make_codec(kind: str, factor: int = 4, path: str | None = None) -> PixelCodec | VaeCodec:
    """``kind`` = "pixel" (PixelCodec(factor)) or "vae" (VaeCodec(path); ``factor`` is then the VAE's)."""
    if kind == "pixel":
        return PixelCodec(factor)
    if kind == "vae":
        if not path:
            raise ValueError("codec kind 'vae' needs a local VAE directory: set params key `codec.path`")
        return VaeCodec(path)
    raise ValueError(f"unknown codec kind {kind!r}; expected 'pixel' or 'vae'")
