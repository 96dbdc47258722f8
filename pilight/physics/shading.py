"""Diffuse shading lookup, image formation, and light balls made without rendering.

Conventions: see ``pilight.physics.envmap``.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from .envmap import BALL_ALBEDO, ball_normals, normal_to_uv

_LOW = (torch.float16, torch.bfloat16)


def diffuse_shading(envmap: torch.Tensor, normals: torch.Tensor, mask: torch.Tensor | None = None):
    """``D_calculated = grid_sample(E_diff, UV(N))`` (paper, Diffuse Shading Loss), ``B x C x H x W``.

    ``envmap`` is ``B x C x 16 x 32`` (batch 1 broadcasts); ``normals``
    ``B x 3 x H x W``.  No cast shadows (the paper says so too).  Border
    padding: rows beyond the pole texel centres reuse the pole rows.  Half
    precision inputs are computed in fp32 and cast back.
    """
    out_dtype = torch.promote_types(envmap.dtype, normals.dtype)
    grid = normal_to_uv(normals)
    env = envmap.to(grid.dtype)
    if env.shape[0] == 1 and grid.shape[0] > 1:
        env = env.expand(grid.shape[0], *env.shape[1:])
    d = F.grid_sample(env, grid, mode="bilinear", padding_mode="border", align_corners=False)
    if mask is not None:
        d = d * mask.to(d.dtype)
    return d.to(out_dtype)


def compose(albedo: torch.Tensor, diffuse: torch.Tensor, specular: torch.Tensor) -> torch.Tensor:
    """Intrinsic image formation ``I = A (.) D + S`` (paper eq. ADS)."""
    return albedo * diffuse + specular


def _per_batch(x, b: int, ref: torch.Tensor) -> torch.Tensor:
    """Scalar, ``(B,)`` or ``(B, C)`` -> ``B x C|1 x 1 x 1`` for broadcasting over a ball image."""
    t = torch.as_tensor(x, device=ref.device, dtype=ref.dtype)
    if t.dim() == 0:
        t = t.reshape(1, 1)
    elif t.dim() == 1:
        t = t.reshape(-1, 1) if t.shape[0] == b and b > 1 else t.reshape(1, -1)
    return t[..., None, None]


def ball_from_direction(
    direction, intensity=1.0, ambient=0.0, size: int = 256, dtype=torch.float32, device=None
) -> torch.Tensor:
    """Gray ball lit by a distant light: ``ball = 0.5 * (intensity * max(0, n.l) + ambient)``.

    ``direction`` (``3`` or ``B x 3``, camera space, pointing *toward* the
    light, normalised here); ``intensity``/``ambient``: scalar, ``(B,)`` or
    colour ``(B, 3)``/``(3,)`` (a 1-D tensor of length B > 1 is read as per-sample).  ``ambient`` is a constant environment radiance,
    so it adds ``ambient`` to ``D``.  Zero outside the disk.  Returns ``B x 3 x size x size``.
    """
    l = torch.as_tensor(direction, dtype=dtype, device=device)
    l = l.reshape(-1, 3)
    l = l / l.norm(dim=1, keepdim=True).clamp_min(1e-12)
    n, inside = ball_normals(size, size, l.device, dtype)
    cos = torch.einsum("bc,xchw->bhw", l, n).clamp_min(0.0)[:, None]
    b = l.shape[0]
    d = _per_batch(intensity, b, cos) * cos + _per_batch(ambient, b, cos)
    return (BALL_ALBEDO * d * inside).expand(b, 3, size, size).contiguous()


def hdri_directions(height: int, width: int, device=None, dtype=torch.float32):
    """World directions ``3 x H x W`` and solid angles ``H x 1`` of Blender equirect texels.

    Cycles (``direction_to_equirectangular``): ``u = 0.5 - atan2(d_y, d_x)/(2 pi)``,
    ``v = 0.5 + asin(d_z)/pi``, image row 0 = ``v = 1`` = zenith, so texel
    column ``c`` has azimuth ``atan2(d_y, d_x) = pi (1 - 2 (c+0.5)/W)``: the
    image centre faces +x, the quarter column faces +y.
    """
    c = torch.arange(width, device=device, dtype=torch.float64)
    r = torch.arange(height + 1, device=device, dtype=torch.float64)
    az = math.pi * (1.0 - 2.0 * (c + 0.5) / width)
    el_edges = math.pi / 2 - math.pi * r / height
    el = 0.5 * (el_edges[1:] + el_edges[:-1])
    e, a = torch.meshgrid(el, az, indexing="ij")
    d = torch.stack([e.cos() * a.cos(), e.cos() * a.sin(), e.sin()], 0)
    # exact solid angle of a lat-long band cell: dphi * (sin el_top - sin el_bottom)
    dw = (2 * math.pi / width) * (el_edges[:-1].sin() - el_edges[1:].sin())
    return d.to(dtype), dw[:, None].to(dtype)


def ball_from_hdri(
    hdri: torch.Tensor,
    world_to_camera: torch.Tensor,
    size: int = 256,
    env_res: tuple[int, int] = (32, 64),
    chunk: int = 8192,
) -> torch.Tensor:
    """Gray ball under a Blender world HDRI, by brute-force irradiance over a downsampled HDRI.

    ``hdri``: ``B x 3 x H x W`` (or ``3 x H x W``) linear radiance in Cycles'
    equirectangular layout (see ``hdri_directions``).  ``world_to_camera``:
    ``3 x 3`` or ``B x 3 x 3`` rotation with ``d_cam = R @ d_world`` (for a
    Blender camera: ``cam.matrix_world.to_3x3().transposed()``).

    ``D(n) = sum_k L_k c_k / sum_k c_k`` with ``c_k = max(0, n.w_k) dw_k``:
    the discrete form of ``1/pi integral L max(0, n.w) dw`` with the
    normaliser replaced by its discrete sum, so a constant HDRI gives
    ``D = L`` exactly.  The HDRI is area-averaged (sin-weighted) to
    ``env_res`` first; irradiance is a cosine-smoothed signal, so a 32x64
    grid (5.6 degree texels) loses little even for a sun.
    """
    if hdri.dim() == 3:
        hdri = hdri[None]
    dtype = torch.float32 if hdri.dtype in _LOW else hdri.dtype
    hdri = hdri.to(dtype)
    b, ch, h, w = hdri.shape
    R = torch.as_tensor(world_to_camera, dtype=dtype, device=hdri.device).reshape(-1, 3, 3)
    # sin-weighted area average, so each coarse texel holds its mean radiance per solid angle
    _, dw_fine = hdri_directions(h, w, hdri.device, dtype)
    num = F.adaptive_avg_pool2d(hdri * dw_fine, env_res)
    den = F.adaptive_avg_pool2d(dw_fine.expand(1, 1, h, w), env_res)
    rad = (num / den).flatten(2)  # B x C x K
    dirs, dw = hdri_directions(*env_res, hdri.device, dtype)
    dirs_cam = torch.einsum("bij,jk->bik", R, dirs.flatten(1))  # B|1 x 3 x K
    dw = dw.expand(*env_res).flatten()
    n, inside = ball_normals(size, size, hdri.device, dtype)
    n = n.flatten(2)[0].T  # P x 3
    bb = max(b, R.shape[0])
    out = []
    for s in range(0, n.shape[0], chunk):
        c = torch.einsum("pi,bik->bpk", n[s : s + chunk], dirs_cam.expand(bb, 3, -1))
        c = c.clamp_min(0.0) * dw
        out.append(torch.einsum("bpk,bck->bcp", c, rad.expand(bb, ch, -1)) / c.sum(-1)[:, None].clamp_min(1e-12))
    d = torch.cat(out, -1).reshape(bb, ch, size, size)
    return BALL_ALBEDO * d * inside


def ball_from_light(*, direction=None, hdri=None, world_to_camera=None, **kw) -> torch.Tensor:
    """Light ball without rendering: a distant light (``direction=``, see
    ``ball_from_direction``) or a world HDRI (``hdri=``, ``world_to_camera=``,
    see ``ball_from_hdri``).  Exactly one of ``direction``/``hdri``."""
    if (direction is None) == (hdri is None):
        raise ValueError("ball_from_light: pass exactly one of direction= or hdri=")
    if hdri is not None:
        if world_to_camera is None:
            raise ValueError("ball_from_light(hdri=...) needs world_to_camera (3x3 rotation)")
        return ball_from_hdri(hdri, world_to_camera, **kw)
    return ball_from_direction(direction, **kw)
