"""Light tokens (ours, stage 2's `conditioning.kind: ball_tokens`): the target light as cross-attention
tokens, so that every position of the UNet can read where the light comes from.

Why: stage 2 reads the target ball only as a condition IMAGE, resized onto the scene's frame and
concatenated on channels (pilight.relight.branches). A ball pixel there has nothing to do with the
scene pixel under it, so the light's direction reaches a scene position only through the UNet's own
spatial mixing; and the cross-attention, the one global path, read a learned constant (`learned`)
that carries no information. A cast shadow lies away from its caster along the light's direction, so
the diffuse gains that physics lacks (shadows; perfect cell gains reach change_r2 0.97 against the
anchor's 0.53, docs: stage 2) need that direction everywhere.

Each token is one cell of the ball pooled to ``grid x grid``: its mean colour (the ball as the branches
read it: divided by its level and tone-mapped, so a token does not change with the light's strength),
the ball's unit normal at the cell's centre (x right, y up, z to the camera, as the normal maps), and
whether that centre lies on the ball. A linear map takes the 7 numbers to the UNet's
cross_attention_dim and adds one learned embedding shared by every token:

    token_k = e + W [rgb_k, n_k, inside_k] + b

W and b start at zero, so at initialisation every token equals e and the attention returns exactly
what a model conditioned on the learned embedding e alone returns: a model trained with
`conditioning.kind: learned` (the shipped base) loads into this one and computes the same thing until
training moves W.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

FEATURES = 7  # rgb (3) + normal (3) + inside the disc (1)


def ball_geometry(grid: int) -> torch.Tensor:
    """(grid * grid, 4): the unit normal of an orthographic unit ball at each cell's centre and 1 where
    that centre lies on the ball (row-major, top row first; off the ball the normal is 0)."""
    c = (torch.arange(grid, dtype=torch.float32) + 0.5) / grid * 2.0 - 1.0
    y, x = torch.meshgrid(-c, c, indexing="ij")  # image rows run down, the normal's y runs up
    r2 = x * x + y * y
    inside = (r2 < 1.0).float()
    z = (1.0 - r2).clamp_min(0.0).sqrt()
    n = torch.stack([x, y, z], dim=-1) * inside[..., None]
    return torch.cat([n, inside[..., None]], dim=-1).reshape(grid * grid, 4)


class BallTokens(nn.Module):
    """[-1, 1] ball images B x 3 x H x W -> B x grid^2 x dim tokens (module docstring)."""

    def __init__(self, dim: int, grid: int = 8):
        super().__init__()
        if grid < 1:
            raise ValueError(f"ball_tokens grid must be >= 1, got {grid}")
        self.dim = int(dim)
        self.grid = int(grid)
        self.name = f"ball-tokens-{self.grid}x{self.grid}"
        # the same name and shape as LearnedEmbedding's, so a `learned` model's embedding loads here
        self.embedding = nn.Parameter(torch.randn(1, self.dim))
        self.proj = nn.Linear(FEATURES, self.dim)
        nn.init.zeros_(self.proj.weight)
        nn.init.zeros_(self.proj.bias)
        self.register_buffer("geometry", ball_geometry(self.grid), persistent=False)

    def forward(self, balls: torch.Tensor) -> torch.Tensor:
        if balls.ndim != 4 or balls.shape[1] != 3:
            raise ValueError(f"ball_tokens expects ball images B x 3 x H x W in [-1, 1], got {tuple(balls.shape)}")
        rgb = F.adaptive_avg_pool2d(balls.float(), self.grid).flatten(2).transpose(1, 2)  # B x g^2 x 3
        geo = self.geometry.to(rgb.device).expand(rgb.shape[0], -1, -1)
        feats = torch.cat([rgb, geo], dim=-1).to(self.proj.weight.dtype)
        return self.embedding[None] + self.proj(feats)
