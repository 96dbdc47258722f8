"""Physics-first relit output (ours; `relight.form: {kind: physics_first}`): physics carries the light, the network
learns only what physics lacks.

On the mask the relit image is FORMED by the paper's own identity (eq. ADS),

    I_relit = A_x * D_pred + S_pred,

so the identity holds to float precision, and each of D and S is predicted as a gain on what physics
alone says under the target light b (pilight.physics.calculated):

    D_pred = (D_calc_b + eps_b) exp(GAIN * g_D) - eps_b        D_calc_b = lookup(unfold(ball_b), N) (1 - m)
    S_pred = (S_calc_b + eps_b) exp(GAIN * g_S) - eps_b        S_calc_b: `form.specular_anchor`

S_calc_b is ``lookup``: F(m, A) lookup(ball_b - lambertian_b, N), the gray ball's own highlight (a
0.5-rough dielectric's) read at the normal; or ``ggx``: the microfacet highlight of ball_b's dominant
light with the conditioning roughness R and F0 = lerp(0.04, A, m) (pilight.physics.specular_model).

g_D and g_S are the diffuse and specular branches' outputs (zero = pure physics); eps_b = EPS_LEVEL *
level(ball_b) keeps the log finite where physics says 0 and scales with the light, so the whole form
is linear in the target light's strength when the network sees the light only through maps divided
by its level (pilight.relight.branches): doubling the ball doubles I_relit on the mask.

A_x (`form.albedo_source`) is the albedo the composition uses:

* ``effective``: the albedo that explains the INPUT under its own light a, with the same physics,

      A_eff = ((I_a - S_calc_a)+ + eps_a A_c) / (D_calc_a + eps_a),

  so I_relit = I_a (A_eff D_pred + S_pred) / (A_eff D_calc_a + S_calc_a) on lit diffuse pixels: the
  ratio form. The input's texture passes through exactly, and stage-1 albedo errors (12.8 dB) cancel;
  where light a barely reaches a pixel (D_calc_a << eps_a) A_eff falls back to the conditioning
  albedo A_c. Light a is what the input shows of it: ``form.source_light: estimated`` fits its
  Lambertian ball to the input and the conditioning albedo and normals (pilight.physics.source_light),
  the same for the shards and for a photo, so the model needs no more inputs than the paper's; on the
  test pairs that anchor beats the one from the rendered ball (README). ``rendered`` uses the
  shards' own ball of light a (ball_a). An image with too few usable pixels to estimate its light
  keeps A_c.
* ``conditioning``: A_c, the albedo the model is conditioned on (stage-1 predictions at test time).

The D branch's target is the shading this A_x needs, D_eff = (I_b - S_b)+ / max(A_x, A_MIN): with
ground-truth albedo it is the true D_b; otherwise it absorbs what A_x gets wrong, which is what makes
I_relit = I_b when g_D and g_S are right. Off the mask (backdrop, glass, emitters) the relit
branch's own output is used, as the display-space gain on the input (pilight.relight.encoding); on
the mask its target is 0.

With ``smooth_cell`` > 1 (form.resolution: cell) every lookup is cell-smoothed before use. A lookup
with stage-1 normals has pixel-scale errors that the input does not have; smoothed, the ratio
A_eff D_calc_b = I_a D_calc_b / D_calc_a keeps the INPUT's texture, and the relit image's fine
structure is the input's (oracle SSIM 0.865 against 0.706 unsmoothed, stage-1 conditions).

Oracles (benchmarks/oracle_relight.py) pick the form; the README gives their table.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from pilight.diffusion.codec import cell_smooth
from pilight.physics.calculated import diffuse_calculated, specular_calculated
from pilight.physics.envmap import light_level
from pilight.physics.source_light import estimate_source_balls
from pilight.physics.specular_model import specular_from_ball

EPS_LEVEL = 0.05  # eps_b / level(ball_b): 5% of the light's mean shading
GAIN = 2.0  # g = log ratio / GAIN, so |g| stays near the range of the other targets
G_MAX = 3.0  # |g| clamp when decoding: a factor of e^6 either way
A_MIN = 0.02  # albedo floor of the D_eff division (a black pixel needs no shading)


@dataclass
class Anchors:
    """What physics says, per pixel (linear HDR, B x 3 x H x W), and the units of the gains."""

    d_calc: torch.Tensor  # D_calc_b
    s_calc: torch.Tensor  # S_calc_b
    albedo: torch.Tensor  # A_x
    eps: torch.Tensor  # eps_b, (B, 1, 1, 1)
    level: torch.Tensor  # level(ball_b), (B, 1, 1, 1)


def _specular(ball, lambertian, intr, mask, kind: str):
    """S_calc of one light. lookup: (gray - Lambertian ball) read at the normal, 0 when the light has no
    Lambertian twin (an analytic or SH-fitted ball is Lambertian already); ggx: the microfacet highlight
    of the ball's dominant light (its Lambertian twin, or the ball itself when it has none)."""
    n, m, a_c = intr["normal"].float(), intr["metallic"].float(), intr["albedo"].float()
    if kind == "ggx":
        lamb = ball if lambertian is None else lambertian
        return specular_from_ball(lamb, n, intr["roughness"], a_c, m) * mask.float()
    if kind != "lookup":
        raise ValueError(f"specular anchor must be 'lookup' or 'ggx', got {kind!r}")
    if lambertian is None:
        return torch.zeros_like(n)
    return specular_calculated(ball, lambertian, n, mask, a_c, m)


def anchors(
    image_a: torch.Tensor,
    intr: dict[str, torch.Tensor],
    mask: torch.Tensor,
    ball_b: torch.Tensor,
    lambertian_b: torch.Tensor | None,
    *,
    albedo_source: str = "effective",
    ball_a: torch.Tensor | None = None,
    lambertian_a: torch.Tensor | None = None,
    smooth_cell: int = 1,
    specular: str = "lookup",
    found: torch.Tensor | None = None,
) -> Anchors:
    """The physics anchors of the target light b and the albedo A_x (module docstring). ``ball_a`` given
    with ``found`` (B,) bool: an estimate made by the caller (pilight.relight.intensity needs it first);
    images not found keep the conditioning albedo."""
    n, m, a_c = intr["normal"].float(), intr["metallic"].float(), intr["albedo"].float()
    level = light_level(ball_b)
    sm = lambda x: cell_smooth(x, smooth_cell)
    d_b = sm(diffuse_calculated(ball_b, n, mask, m))
    s_b = sm(_specular(ball_b, lambertian_b, intr, mask, specular))
    if albedo_source == "conditioning":
        a_x = a_c
    elif albedo_source == "effective":
        if ball_a is None:  # the input's light, estimated from it (pilight.physics.source_light)
            ball_a, found = source_balls(image_a, intr, mask, ball_b.shape[-1])
            lambertian_a = None
        elif found is None:
            found = torch.ones(image_a.shape[0], dtype=torch.bool, device=image_a.device)
        eps_a = EPS_LEVEL * light_level(ball_a)
        d_a = sm(diffuse_calculated(ball_a, n, mask, m))
        s_a = sm(_specular(ball_a, lambertian_a, intr, mask, specular))
        a_x = ((image_a.float() - s_a).clamp_min(0) + eps_a * a_c) / (d_a + eps_a)
        # off the mask, and for an image whose light could not be estimated, the conditioning albedo
        a_x = torch.where((mask > 0.5) & found[:, None, None, None], a_x, a_c)
    else:
        raise ValueError(f"albedo_source must be 'effective' or 'conditioning', got {albedo_source!r}")
    return Anchors(d_b, s_b, a_x, EPS_LEVEL * level, level)


def source_balls(
    image_a: torch.Tensor, intr: dict[str, torch.Tensor], mask: torch.Tensor, size: int, *, level: bool = False
) -> tuple[torch.Tensor, torch.Tensor]:
    """The input's own light, estimated from it and the conditioning albedo, normals and metallic
    (pilight.physics.source_light): (balls (B, 3, size, size), found (B,)) on the input's device.
    ``level``: the fit for the light's level (relative intensity), not for the shading."""
    n, m, a_c = intr["normal"].float(), intr["metallic"].float(), intr["albedo"].float()
    ball_a, found = estimate_source_balls(
        image_a.float().cpu(), a_c.cpu(), n.cpu(), mask.float().cpu(), size, m.cpu(), level=level
    )
    return ball_a.to(image_a.device), found.to(image_a.device)


def gain_of(value: torch.Tensor, anchor: torch.Tensor, eps: torch.Tensor) -> torch.Tensor:
    """g = log((value + eps) / (anchor + eps)) / GAIN: the network's target for ``value``."""
    return torch.log((value.float().clamp_min(0) + eps) / (anchor.float().clamp_min(0) + eps)) / GAIN


def apply_gain(g: torch.Tensor, anchor: torch.Tensor, eps: torch.Tensor) -> torch.Tensor:
    """Inverse of gain_of: (anchor + eps) exp(GAIN g) - eps, >= 0."""
    return ((anchor.float() + eps) * torch.exp(GAIN * g.float().clamp(-G_MAX, G_MAX)) - eps).clamp_min(0)


def diffuse_target(image_b: torch.Tensor, specular_b: torch.Tensor, albedo_x: torch.Tensor) -> torch.Tensor:
    """D_eff = (I_b - S_b)+ / max(A_x, A_MIN): the shading that A_x needs to form I_b."""
    return (image_b.float() - specular_b.float()).clamp_min(0) / albedo_x.clamp_min(A_MIN)


def compose_relit(anc: Anchors, g_d: torch.Tensor, g_s: torch.Tensor) -> dict[str, torch.Tensor]:
    """Branch gains -> {relit (on the mask), diffuse, specular, albedo}: I = A_x D + S exactly."""
    d = apply_gain(g_d, anc.d_calc, anc.eps)
    s = apply_gain(g_s, anc.s_calc, anc.eps)
    a = anc.albedo.clamp_min(A_MIN)
    return {"relit": a * d + s, "diffuse": d, "specular": s, "albedo": a}
