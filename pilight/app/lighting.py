"""The app's lights: a pointer on the gray ball picker -> a direction, several lights mixed into the one
ball stage 2 is conditioned on, and the picker's picture with a marker per light.

The picker is the gray ball seen by the camera (orthographic; x right, y up, z toward the camera, as
in pilight.lights). A point (u, v) of its disk, in [-1, 1] from its centre, has the normal
n = (u, v, sqrt(1 - u^2 - v^2)); a light placed there comes from n, so the point it is placed at is
the brightest point of the ball it lights. In pilight.lights' convention n = (cos E sin A, sin E,
cos E cos A), so A = atan2(n_x, n_z) and E = asin(n_y). A point off the disk is taken to the rim
(a light from the side, |A| = 90 deg at E = 0); lights behind the subject (|A| > 90) are set with the
azimuth slider.

Mixing (relative intensity, pilight.relight.intensity): each light's ball is brought to level 1
(its shape and colour kept), weighted by its intensity k_i and summed. Light adds linearly, so the
mix is the light of all of them together, of level sum(k_i).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from pilight.lights import BALL_SIZE, Light, LightError, ball_preview, directional
from pilight.physics.envmap import light_level

MAX_LIGHTS = 8  # mixed lights at once: each costs a ball (cheap); more is a cluttered picker


@dataclass(frozen=True)
class LightSpec:
    """One light of the app: a distant light toward (azimuth, elevation), of relative intensity k and
    an RGB colour in [0, 1] (white is (1, 1, 1))."""

    azimuth: float
    elevation: float
    intensity: float = 1.0
    colour: tuple[float, float, float] = (1.0, 1.0, 1.0)

    def light(self, size: int = BALL_SIZE) -> Light:
        base = directional(self.azimuth, self.elevation, self.intensity, size)
        tint = torch.tensor(self.colour, dtype=base.ball.dtype).view(3, 1, 1)
        return Light(base.name, base.ball * tint, base.description, intensity=self.intensity)

    @property
    def white(self) -> bool:
        return self.colour == (1.0, 1.0, 1.0)


def hex_colour(text: str) -> tuple[float, float, float]:
    """'#rrggbb' (a colour picker's value) -> RGB in [0, 1]. LightError for anything else."""
    t = (text or "").strip().lstrip("#")
    if len(t) != 6 or any(c not in "0123456789abcdefABCDEF" for c in t):
        raise LightError(f"colour {text!r}: expected #rrggbb")
    return tuple(int(t[i : i + 2], 16) / 255 for i in (0, 2, 4))


def picker_direction(x: float, y: float, size: int) -> tuple[float, float]:
    """A pixel (x right, y down) of the ``size``-pixel picker -> (azimuth, elevation) in degrees."""
    u, v = (2 * x + 1) / size - 1, 1 - (2 * y + 1) / size
    r = math.hypot(u, v)
    if r > 1:  # off the disk: the rim
        u, v = u / r, v / r
    n_z = math.sqrt(max(0.0, 1 - u * u - v * v))
    return math.degrees(math.atan2(u, n_z)), math.degrees(math.asin(max(-1.0, min(1.0, v))))


def picker_position(azimuth: float, elevation: float, size: int) -> tuple[float, float] | None:
    """Where a light of (azimuth, elevation) sits on the picker (pixels), or None behind the ball."""
    a, e = math.radians(azimuth), math.radians(elevation)
    n = (math.cos(e) * math.sin(a), math.sin(e), math.cos(e) * math.cos(a))
    if n[2] < 0:
        return None
    return ((n[0] + 1) * size - 1) / 2, ((1 - n[1]) * size - 1) / 2


def mix(lights: list[Light]) -> Light:
    """Several lights -> one: each at level 1 times its intensity, summed (module docstring)."""
    if not lights:
        raise LightError("no light to relight with: place one on the ball")
    if len(lights) > MAX_LIGHTS:
        raise LightError(f"{len(lights)} lights: at most {MAX_LIGHTS} can be mixed")
    if len(lights) == 1:
        return lights[0]
    balls = torch.stack([l.ball.float() for l in lights])
    k = torch.tensor([float(l.intensity) for l in lights]).view(-1, 1, 1, 1)
    total = float(k.sum())
    ball = (balls / light_level(balls) * k).sum(0)
    if total > 0:  # a mix of level sum(k): its shape and colour are what a relative light keeps
        ball = ball / light_level(ball[None])[0] * total
    return Light("mix", ball, " + ".join(l.description for l in lights), intensity=total)


def picker_picture(specs: list[LightSpec], size: int = 256) -> np.ndarray:
    """(size, size, 3) uint8: the gray ball under the mixed lights, a ring where each light is placed."""
    if specs:
        ball = mix([s.light(size) for s in specs]).ball
        ball = ball / max(float(ball.max()), 1e-6) * 0.9  # a preview: the brightest point near white
    else:
        ball = torch.zeros(3, size, size)
    pic = ball_preview(ball).copy()
    yy, xx = np.mgrid[0:size, 0:size]
    disk_edge = np.abs(np.hypot((2 * xx + 1) / size - 1, 1 - (2 * yy + 1) / size) - 1) < 1.5 / size
    pic[disk_edge] = (90, 90, 90)  # the ball's outline, also where no light falls
    for i, s in enumerate(specs):
        at = picker_position(s.azimuth, s.elevation, size)
        if at is None:
            continue
        ring = np.abs(np.hypot(xx - at[0], yy - at[1]) - size / 40) < max(1.0, size / 200)
        colour = (255, 64, 32) if i == len(specs) - 1 else (255, 200, 0)  # the active light stands out
        pic[ring] = colour
    return pic
