"""Image conditioning for the UNet's cross-attention (paper Sec. Stage 1: "The CLIP image
embedding of the condition inputs go into the cross-attention layers as well").

``ClipImageEmbedding`` -- a frozen CLIP vision tower with projection (local weights only).
``LearnedEmbedding``   -- the explicit no-CLIP alternative for scratch runs: one learned
                          token sequence returned for every image (it carries no image
                          information; the image still enters through the concatenated
                          condition latent).
``null_like``          -- the zero embedding used as the unconditional branch of CFG.
"""

from __future__ import annotations

import os

import torch
import torch.nn.functional as F
from torch import nn

from pilight.optional import require

# CLIP's preprocessing constants (transformers' OPENAI_CLIP_MEAN / OPENAI_CLIP_STD).
CLIP_MEAN = (0.48145466, 0.4578275, 0.40821073)
CLIP_STD = (0.26862954, 0.26130258, 0.27577711)


class ClipImageEmbedding(nn.Module):
    """[-1, 1] images B x 3 x H x W -> ``image_embeds[:, None, :]`` (B x 1 x D), frozen.

    Preprocessing: map to [0, 1], bicubic (antialiased) resize straight to
    image_size x image_size (no centre crop: the whole frame is the condition), then
    normalise with CLIP mean/std.
    """

    def __init__(self, path: str | os.PathLike):
        super().__init__()
        CLIPVisionModelWithProjection = require("transformers", "conditioning.kind: clip").CLIPVisionModelWithProjection

        path = os.fspath(path)
        if not os.path.isdir(path):
            raise FileNotFoundError(
                f"CLIP vision model directory not found: {path!r} (expected a "
                "CLIPVisionModelWithProjection saved with save_pretrained; nothing is downloaded)"
            )
        self.model = CLIPVisionModelWithProjection.from_pretrained(path, local_files_only=True)
        self.model.requires_grad_(False).eval()
        self.image_size = int(self.model.config.image_size)
        self.dim = int(self.model.config.projection_dim)
        self.name = f"clip:{os.path.basename(os.path.normpath(path))}"
        self.register_buffer("mean", torch.tensor(CLIP_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(CLIP_STD).view(1, 3, 1, 1), persistent=False)

    def train(self, mode: bool = True):  # frozen: never switch CLIP to train mode
        super().train(mode)
        self.model.eval()
        return self

    @torch.no_grad()
    def forward(self, images: torch.Tensor) -> torch.Tensor:
        if images.ndim != 4 or images.shape[1] != 3:
            raise ValueError(f"expected images B x 3 x H x W in [-1, 1], got {tuple(images.shape)}")
        x = (images.float() + 1.0) / 2.0
        x = F.interpolate(
            x, size=(self.image_size, self.image_size), mode="bicubic", align_corners=False, antialias=True
        ).clamp(0.0, 1.0)
        x = (x - self.mean) / self.std
        dtype = next(self.model.parameters()).dtype
        return self.model(pixel_values=x.to(dtype)).image_embeds[:, None, :]


class LearnedEmbedding(nn.Module):
    """A trainable B x tokens x dim embedding, the same for every image."""

    def __init__(self, dim: int, tokens: int = 1):
        super().__init__()
        self.dim = int(dim)
        self.tokens = int(tokens)
        self.name = "learned-embedding"
        self.embedding = nn.Parameter(torch.randn(self.tokens, self.dim))

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self.embedding[None].expand(images.shape[0], -1, -1)


def make_conditioning(kind: str, path: str | None = None, dim: int | None = None) -> nn.Module:
    """``kind`` = "clip" (ClipImageEmbedding(path)), "learned" (LearnedEmbedding(dim)) or "ball_tokens"
    (pilight.diffusion.light_tokens.BallTokens(dim): stage 2's target light as tokens)."""
    if kind == "clip":
        if not path:
            raise ValueError(
                "conditioning kind 'clip' needs a local CLIP vision model: set params key `model.clip_path`"
            )
        return ClipImageEmbedding(path)
    if kind == "learned":
        if dim is None:
            raise ValueError("conditioning kind 'learned' needs dim (the UNet's cross_attention_dim)")
        return LearnedEmbedding(dim)
    if kind == "ball_tokens":
        if dim is None:
            raise ValueError("conditioning kind 'ball_tokens' needs dim (the UNet's cross_attention_dim)")
        from pilight.diffusion.light_tokens import BallTokens

        return BallTokens(dim)
    raise ValueError(f"unknown conditioning kind {kind!r}; expected 'clip', 'learned' or 'ball_tokens'")


def null_like(embeds: torch.Tensor) -> torch.Tensor:
    """The unconditional (null) embedding for classifier-free guidance: zeros of the same shape."""
    return torch.zeros_like(embeds)
