"""Light intensity relative to the photo's own light (`relight.intensity: relative`, the default), or
absolute (a calibrated plate).

A single photo cannot tell albedo level from light power: twice the albedo under half the light is the
same picture. So the product's question is "this photo, lit from the left, at the same exposure", not
"under 12.5 W/m^2". In relative mode a target light is a RELATIVE ball: its shape and colour say where
the light comes from, and its level k (pilight.physics.envmap.light_level) how strong it is relative to
the input's own light, k = 1 keeping the photo's exposure. The model then uses

    ball_b = relative ball x level(estimated light of the input)

with the input's light estimated from the input and its conditioning intrinsics
(pilight.physics.source_light): the level from a first-order fit, while the effective albedo A_eff
uses the nine-term one (their levels differ where a photo shows a narrow cone of normals, so the photo
relit under its own estimated light at k = 1 comes back scaled by their ratio; the photo API's
``exposure: photo`` removes it, and on the test pairs the split won the relative tier,
docs/pipeline/stage2.md). In the
physics-first ratio form I_relit = I_a (A_eff D_b + S_b) / (A_eff D_a + S_a) the albedo's level then
cancels on diffuse pixels: albedo x 2 halves the estimated light, doubles A_eff and halves ball_b.
What does not cancel is the dielectric highlight: F0 = 0.04 whatever the albedo, so S_b follows the
estimated light's level (tests/relight/test_intensity.py measures both).

A photo relit under a light from the side at the photo's own light level is darker than the photo: the
light reaches less of what the camera sees (the astronaut at k = 1 from the left: 0.31 of its mean
luminance with pilight-base, 0.50 with the physics anchor alone). A photographer would keep the
exposure, so the photo API does too by default (``exposure: photo``): each relit image is scaled so
that its mean luminance on the mask is k times the photo's (``exposure_gain``). As relighting is linear
in the light, that is the same light made brighter or dimmer by the gain, the same for D, S and the
relit image, and it is computed once per light, so k still scales the result linearly.
``exposure: light`` keeps the light's level as the relit image's exposure (a fixed camera).

For rendered pairs (shards) the truth's k is r = level(ball_b) / level(ball_a), so the relative ball is
ball_b / level(ball_a) (``relative_pair``). For a user's light of intensity k, it is the light's ball
scaled to level k (``relative_light``). An input whose light cannot be estimated (too few usable
pixels) keeps the relative ball as an absolute one, and its conditioning albedo (physics_first).
"""

from __future__ import annotations

import torch

from pilight.data.colour import REC709_LUMINANCE
from pilight.physics.envmap import light_level
from pilight.relight.level_prior import shrink_level

INTENSITIES = ("relative", "absolute")
EXPOSURES = ("photo", "light")  # what k = 1 keeps in the photo API: the photo's exposure, or its light's level
MAX_EXPOSURE_GAIN = 4.0  # two stops either way: a light from behind leaves the visible side in shadow, and
# brightening that further only magnifies the anchor's eps floor (EPS_LEVEL) and the gains' noise
BALL_KEYS = ("ball_b", "ball_lambertian_b")  # the target light's balls in a pairs batch


def relative_pair(batch: dict) -> dict:
    """A pairs batch with its target balls made relative to the input's rendered light: ball_b / level(ball_a)."""
    if "ball_a" not in batch:
        raise KeyError("relative intensity of a rendered pair needs the input's own ball (ball_a) in the shards")
    unit = light_level(batch["ball_a"])
    return batch | {k: batch[k] / unit.to(batch[k].dtype) for k in BALL_KEYS if k in batch}


def relative_light(ball: torch.Tensor, k: float | torch.Tensor) -> torch.Tensor:
    """A user's light (B, 3, S, S) as a relative ball of level ``k`` (its shape and colour kept)."""
    return ball / light_level(ball).to(ball.dtype) * torch.as_tensor(k, dtype=ball.dtype).reshape(-1, 1, 1, 1)


def to_source_level(
    balls: dict[str, torch.Tensor], source: torch.Tensor, found: torch.Tensor, prior: tuple[float, float] | None = None
) -> dict:
    """Relative balls -> balls at the input's estimated light level (``source``: its estimated ball), or at
    that level shrunk by ``prior`` = (alpha, beta) (pilight.relight.level_prior); inputs not ``found`` keep
    them as they are."""
    level = light_level(source)
    if prior is not None:
        level = shrink_level(level, *prior)
    scale = torch.where(found[:, None, None, None], level, torch.ones_like(level))
    return {k: v * scale.to(v.dtype) for k, v in balls.items()}


def mean_luminance(image: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """(B, 3, H, W) linear RGB and a (1 or B, 1, H, W) mask -> (B,) Rec. 709 luminance averaged on the mask."""
    y = (image * image.new_tensor(REC709_LUMINANCE).view(1, 3, 1, 1)).sum(1)
    m = (mask[:, 0] > 0.5).float().expand_as(y)
    return (y * m).sum((-1, -2)) / m.sum((-1, -2)).clamp_min(1)


def exposure_gain(relit: torch.Tensor, photo: torch.Tensor, mask: torch.Tensor, k: torch.Tensor) -> torch.Tensor:
    """(B,) the factor that makes each relit image's mean luminance on the mask k times the photo's
    (``exposure: photo``; module docstring), within [1 / MAX_EXPOSURE_GAIN, MAX_EXPOSURE_GAIN]. ``relit``
    (B, 3, H, W) is the relit image under lights of relative level k (B,), ``photo`` (1, 3, H, W) the input,
    both at the processing size."""
    target = k.float() * mean_luminance(photo.float(), mask)
    gain = target / mean_luminance(relit.float(), mask).clamp_min(1e-12)
    return gain.clamp(1 / MAX_EXPOSURE_GAIN, MAX_EXPOSURE_GAIN)
