"""Specular radiance from a light ball by a microfacet model: highlights that know the surface's
roughness and Fresnel, which a lookup of the gray ball cannot (pilight.physics.calculated).

The ball's Lambertian part is fitted by one distant light plus a constant environment,

    D_ball(n) = I max(0, n.l) + a        (the units of ball_from_direction: D = ball / BALL_ALBEDO)

(l by a search over 2048 directions of the whole sphere, then I, a per colour channel by least
squares with that l). A distant light of that D has irradiance pi I, so a surface of roughness r
(alpha = r^2, as Blender's Principled BSDF) and normal-incidence reflectance F0 reflects toward the
camera (v = +z, the orthographic ball camera's and nearly the scene camera's view)

    S(n) = pi I D_GGX(n.h) V(n.l, n.v) F(v.h) (n.l)  +  a F0          (Cook-Torrance)

with h = (l + v)/|l + v|, V the height-correlated Smith visibility G / (4 n.l n.v), F Schlick's
Fresnel and F0 = 0.04 (1 - m) + A m (the Principled dielectric layer at IOR 1.5; a metal reflects
its base colour). The a F0 term is the constant environment's reflection. The model knows no
shadows, no interreflection and, for an HDRI-lit ball, no light but the dominant one: those stay
with the network.
"""

from __future__ import annotations

import math

import torch

from .envmap import BALL_ALBEDO, ball_normals
from .precision import in_full_precision

F0_DIELECTRIC = 0.04
N_DIRECTIONS = 2048
ALPHA_MIN = 1e-3  # alpha floor: a perfect mirror's GGX is a delta, which a pixel cannot sample


def sphere_directions(n: int = N_DIRECTIONS) -> torch.Tensor:
    """(n, 3) unit directions spread evenly over the whole sphere (Fibonacci lattice)."""
    i = torch.arange(n, dtype=torch.float64) + 0.5
    y = 1.0 - 2.0 * i / n
    r = torch.sqrt((1.0 - y * y).clamp_min(0.0))
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    return torch.stack([r * torch.cos(phi), y, r * torch.sin(phi)], 1).float()


@in_full_precision
def fit_directional(lambertian_ball: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(l (B, 3) unit, I (B, 3), a (B, 3)): the distant light plus constant environment whose
    Lambertian ball is closest (least squares over the disk) to ``lambertian_ball`` (B x 3 x h x w)."""
    n, disk = ball_normals(*lambertian_ball.shape[-2:], device=lambertian_ball.device)
    inside = disk[0, 0].flatten() > 0
    normals = n[0].flatten(1)[:, inside]  # (3, K)
    d = lambertian_ball.float().flatten(2)[:, :, inside] / BALL_ALBEDO  # (B, 3, K)
    cand = sphere_directions().to(d.device)  # (C, 3)
    cos = (cand @ normals).clamp_min(0.0)  # (C, K)
    k = float(normals.shape[1])
    gray = d.mean(1)  # (B, K)
    # per (candidate, image): min over (I, a) of |I cos + a - gray|^2, in closed form
    s_cc, s_c = (cos * cos).sum(1)[:, None], cos.sum(1)[:, None]  # (C, 1)
    s_cy, s_y = cos @ gray.T, gray.sum(1)[None]  # (C, B), (1, B)
    det = (k * s_cc - s_c * s_c).clamp_min(1e-9)
    i_fit = (k * s_cy - s_c * s_y) / det
    a_fit = (s_cc * s_y - s_c * s_cy) / det
    resid = (gray * gray).sum(1)[None] - i_fit * s_cy - a_fit * s_y  # |y|^2 - theta . X^T y
    resid = torch.where(i_fit > 0, resid, torch.full_like(resid, float("inf")))
    best = resid.argmin(0)  # (B,)
    l = cand[best]
    c = cos[best]  # (B, K)
    # per channel with the chosen l
    cc, c1 = (c * c).sum(1, keepdim=True), c.sum(1, keepdim=True)
    cy, y1 = (c[:, None] * d).sum(-1), d.sum(-1)  # (B, 3)
    det_b = (k * cc - c1 * c1).clamp_min(1e-9)
    intensity = ((k * cy - c1 * y1) / det_b).clamp_min(0.0)
    ambient = ((cc * y1 - c1 * cy) / det_b).clamp_min(0.0)
    return l, intensity, ambient


@in_full_precision
def ggx_specular(
    normal: torch.Tensor,
    roughness: torch.Tensor,
    f0: torch.Tensor,
    light_dir: torch.Tensor,
    intensity: torch.Tensor,
    ambient: torch.Tensor,
) -> torch.Tensor:
    """S (B x 3 x H x W) of the module docstring. normal B x 3 x H x W (0 off the mask gives 0),
    roughness B x 1 x H x W, f0 B x 3|1 x H x W, light_dir / intensity / ambient (B, 3)."""
    n = normal.float()
    l = light_dir.float()[:, :, None, None]
    v = torch.tensor([0.0, 0.0, 1.0], device=n.device)[None, :, None, None]
    h = l + v
    h = h / h.norm(dim=1, keepdim=True).clamp_min(1e-6)
    nl = (n * l).sum(1, keepdim=True).clamp_min(0.0)
    nv = n[:, 2:3].clamp_min(1e-4)
    nh = (n * h).sum(1, keepdim=True).clamp_min(0.0)
    vh = h[:, 2:3].clamp_min(0.0)
    alpha = (roughness.float() ** 2).clamp_min(ALPHA_MIN)
    a2 = alpha * alpha
    d = a2 / (math.pi * (nh * nh * (a2 - 1.0) + 1.0) ** 2)
    vis = 0.5 / (nl * torch.sqrt(nv * nv * (1.0 - a2) + a2) + nv * torch.sqrt(nl * nl * (1.0 - a2) + a2)).clamp_min(
        1e-6
    )
    fres = f0 + (1.0 - f0) * (1.0 - vh) ** 5
    direct = math.pi * intensity[:, :, None, None] * d * vis * fres * nl
    lit = (n.abs().sum(1, keepdim=True) > 0).float()
    return (direct + ambient[:, :, None, None] * f0) * lit


def principled_f0(albedo: torch.Tensor, metallic: torch.Tensor) -> torch.Tensor:
    """F0 = 0.04 (1 - m) + A m."""
    m = metallic.float()
    return F0_DIELECTRIC * (1.0 - m) + albedo.float() * m


def specular_from_ball(
    lambertian_ball: torch.Tensor,
    normal: torch.Tensor,
    roughness: torch.Tensor,
    albedo: torch.Tensor,
    metallic: torch.Tensor,
) -> torch.Tensor:
    """S of each pixel under the light of ``lambertian_ball`` (module docstring)."""
    l, i, a = fit_directional(lambertian_ball)
    return ggx_specular(normal, roughness, principled_f0(albedo, metallic), l, i, a)
