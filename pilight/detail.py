"""A relit photo at the input's full resolution with the input's own detail (pilight.pipeline).

The models run at the processing size (128^2 by default); upsampling their relit image blurs a 512^2
photo to a quarter of its sharpness. But relighting changes shading, which is smooth, far more than
it changes the texture the photo already shows. So the pipeline carries the CHANGE at the
processing size and applies it to the full-resolution input:

    relit_full = up(relit - S) * (I_full + eps) / (up(I_proc) + eps) + up(S)

I_proc is the input at the processing size, up() bilinear; (I_full + eps) / (up(I_proc) + eps) is the
input's detail that the processing size lost (1 where there is none), the relit image's diffuse part
A_x D gets it back, and the specular part S, which the light adds rather than scales, is added
unchanged. eps keeps pitch-black input pixels (no detail to tell) from dividing by 0. At the
processing size itself it is the identity: relit_full = relit.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

DETAIL_EPS = 1e-3  # linear radiance; far below the training images' shadows (ambient 0.01-0.05)


def resize(x: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """Bilinear, antialiased when shrinking; the identity at the same size (bit-exact round trips)."""
    if tuple(x.shape[-2:]) == tuple(size):
        return x
    return F.interpolate(x.float(), size=size, mode="bilinear", align_corners=False, antialias=True)


def with_input_detail(
    relit: torch.Tensor, specular: torch.Tensor | None, proc_input: torch.Tensor, full_input: torch.Tensor
) -> torch.Tensor:
    """(B, 3, h, w) relit and specular at the processing size, the input there (1 or B, 3, h, w) and at full
    size (1 or B, 3, H, W) -> (B, 3, H, W) relit at full size with the input's detail (module docstring)."""
    size = tuple(full_input.shape[-2:])
    s = torch.zeros_like(relit) if specular is None else specular
    detail = (full_input.float() + DETAIL_EPS) / (resize(proc_input, size) + DETAIL_EPS)
    return (resize(relit - s, size) * detail + resize(s, size)).clamp_min(0)
