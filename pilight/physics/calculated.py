"""What physics alone predicts for a pixel under a target light ball: D_calc and S_calc.

Both are lookups of the ball by the pixel's normal (``pilight.physics.envmap`` conventions):

    D_calc(n) = E_diff(n) * (1 - m),   E_diff = unfold(ball) (paper, "Diffuse Shading Loss")

The (1 - m) is our render contract: metals have no diffuse lobe, so their ground-truth D is 0.

    S_calc(n) = F(m, A) * (ball - ball_lambertian)(n)

The gray ball is a Principled BSDF of base 0.5 and roughness 0.5 and the Lambertian ball is the
same ball's pure-diffuse part, so their difference is the specular radiance that a 0.5-rough
dielectric shows where its normal is n (viewed along +z, as the orthographic ball camera sees it;
the scene camera's rays are within its field of view of that). It is a lookup, so it knows nothing
of roughness: a rougher surface spreads the highlight further, a smoother one concentrates it. The
Fresnel factor F is the crude metal one: 1 on dielectrics (F0 = 0.04 as the ball's), and
A / F0_DIELECTRIC * METAL_SPECULAR_SCALE on metals (a metal's F0 is its base colour), blended by m.
Neither knows cast shadows or interreflection. These are the parts the network has to learn.
"""

from __future__ import annotations

import torch

from .envmap import BALL_ALBEDO, ball_to_envmap
from .shading import diffuse_shading

F0_DIELECTRIC = 0.04  # Principled BSDF's specular layer at IOR 1.5, the gray ball's
METAL_SPECULAR_SCALE = 0.5  # measured on the default's test pairs: change_r2 on the mask 0.10 -> 0.29 (README)


def _unfolded_lookup(ball: torch.Tensor, normal: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
    """unfold(ball) read at each pixel's normal: the ball's radiance there / BALL_ALBEDO."""
    env = ball_to_envmap(ball.float())[0]
    return diffuse_shading(env, normal.float(), None if mask is None else mask.float())


def diffuse_calculated(
    ball: torch.Tensor, normal: torch.Tensor, mask: torch.Tensor, metallic: torch.Tensor
) -> torch.Tensor:
    """D_calc = Lambertian lookup of the unfolded ball, times (1 - metallic) (our render contract)."""
    return _unfolded_lookup(ball, normal, mask) * (1.0 - metallic.float())


def metal_fresnel(albedo: torch.Tensor, metallic: torch.Tensor) -> torch.Tensor:
    """F(m, A): 1 on dielectrics, A / 0.04 * METAL_SPECULAR_SCALE on metals, linear in m."""
    m = metallic.float()
    return (1.0 - m) + m * albedo.float() / F0_DIELECTRIC * METAL_SPECULAR_SCALE


def specular_calculated(
    ball: torch.Tensor,
    ball_lambertian: torch.Tensor,
    normal: torch.Tensor,
    mask: torch.Tensor,
    albedo: torch.Tensor,
    metallic: torch.Tensor,
) -> torch.Tensor:
    """S_calc = F(m, A) * lookup(ball - ball_lambertian) (module docstring); >= 0.

    An analytic ball (``ball_from_direction``) is Lambertian itself: pass it as both balls and
    S_calc is 0, which is what such a ball says about highlights."""
    spec_ball = (ball.float() - ball_lambertian.float()).clamp_min(0.0)
    return _unfolded_lookup(spec_ball, normal, mask) * BALL_ALBEDO * metal_fresnel(albedo, metallic)
