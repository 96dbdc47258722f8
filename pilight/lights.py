"""Lights a user can name, as the light balls stage 2 is conditioned on.

Every light becomes a gray ball (base colour 0.5, orthographic, tangent to the borders, camera
frame: x right, y up, z toward the camera; ``pilight.physics.envmap``), the form the model was
trained with. Zero outside the disk, as in the rendered balls.

* **Direction** (``--azimuth A --elevation E``, degrees): a distant light toward
  ``(cos E sin A, sin E, cos E cos A)``. Azimuth 0 is the camera's side (light from behind the
  camera), +90 the right of the picture, -90 the left, 180 behind the subject; elevation 0 is
  level with the camera, +90 straight above, -90 straight below.
* **Named** (``--light``): left = (-90, 30), right = (90, 30), top = (0, 90), bottom = (0, -90),
  front = (0, 0), as (azimuth, elevation).
* **Ball file** (``--ball``): a rendered or photographed gray ball, cropped square and tangent to
  the borders; PNG/JPEG are sRGB, EXR/HDR linear. A ball whose disk holds no light is refused; a
  picture without a round silhouette along the borders (``silhouette_ratio`` below
  ``MIN_SILHOUETTE``: any other square picture) is used with a ``LightWarning`` saying so.
* **HDRI** (``--hdri``): an equirectangular (lat-long, exactly 2:1) panorama in Blender's layout,
  the horizon across the middle row. Its centre column lies straight ahead of the camera (behind
  the subject), its left quarter to the camera's left. ``--rotate DEG`` turns it about the
  vertical axis, clockwise seen from above: with +90 the light that came from the left comes
  from straight ahead.
* ``--intensity`` k. By default (relative intensity, pilight.relight.intensity) only the light's shape
  and colour are kept and its level becomes k times the photo's own estimated light: k = 1 keeps the
  exposure. With ``--absolute`` it multiplies the light as made here: 1 means, for a direction, a
  surface facing the light gets diffuse shading DIRECT_LEVEL (the middle of the training lights) plus
  an ambient AMBIENT; for a ball or an HDRI, its values as stored (a calibrated plate).
"""

from __future__ import annotations

import math
import re
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from pilight.photo import PhotoError, as_photo, read_photo

# Training lights: irradiance strength x irradiance_scale = U[5, 20] x 0.5 at the scene centre, so a
# white surface facing the light has radiance 12.5 x 0.5 / pi ~ 2.0 in the middle of the range.
DIRECT_LEVEL = 2.0
AMBIENT = 0.03  # the middle of render.light.ambient [0.01, 0.05]: shadowed sides are not pitch black
NAMED = {"left": (-90.0, 30.0), "right": (90.0, 30.0), "top": (0.0, 90.0), "bottom": (0.0, -90.0), "front": (0.0, 0.0)}
# Lights are made at this size and area-averaged (antialiased) down to the model's ball size by the
# pipeline, as Cycles' pixel filter averages the rendered training balls; the previews stay smooth.
BALL_SIZE = 128


class LightError(ValueError):
    """A light cannot be made: unknown name, bad file, an HDRI that is not 2:1."""


class LightWarning(UserWarning):
    """A light was made from a file that does not look like what it should be (a --ball without a ball)."""


# A ball's silhouette: the mean log-radiance step across the inscribed circle over the larger of the steps
# across two control circles (r = 0.7 inside the ball, 1.25 in the corners). Rendered balls (zero
# outside): 1.9-22 over the 304 balls of the default's renders; square crops of 20 scikit-image photos:
# 0.24-1.31 (two pictures of a disk on black, retina and logo, 21 and 4); a rendered ball composited onto a
# busy photo background, as a photographed ball might be: 1.36-4.1, so this warns, never refuses.
MIN_SILHOUETTE = 1.5


def silhouette_ratio(ball: torch.Tensor, size: int = 64) -> float:
    """How much more the picture ``ball`` (3, H, W), linear, changes across the circle tangent to its borders
    than across concentric circles inside and outside it (see MIN_SILHOUETTE)."""
    b = F.interpolate(ball[None].float().clamp_min(0), size=(size, size), mode="bilinear", antialias=True)[0]
    log = torch.log(b + 1e-3 * float(b.mean()) + 1e-8)[None]
    angle = torch.linspace(0, 2 * math.pi, 257)[:-1]

    def ring(r: float) -> torch.Tensor:
        grid = torch.stack([r * torch.cos(angle), r * torch.sin(angle)], -1)[None, None]
        return F.grid_sample(log, grid, mode="bilinear", padding_mode="border", align_corners=False)[0, :, 0]

    step = lambda r, d=0.08: float((ring(r - d) - ring(r + d)).abs().mean())
    return step(1.0) / max(step(0.7), step(1.25), 1e-6)


@dataclass(frozen=True)
class Light:
    """A light as stage 2 sees it. ``name`` is file-name safe and unique per light spec."""

    name: str
    ball: torch.Tensor  # (3, S, S) linear gray ball
    description: str = ""
    intensity: float = 1.0  # k: relative to the photo's own light in relative mode (pilight.relight.intensity)


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9._+-]+", "_", name).strip("_") or "light"


def _suffix(intensity: float) -> str:
    return "" if intensity == 1.0 else f"_x{intensity:g}"


def _check_intensity(intensity: float) -> None:
    if not (math.isfinite(intensity) and intensity >= 0):
        raise LightError(f"--intensity must be a finite number >= 0, got {intensity}")


def direction(azimuth_deg: float, elevation_deg: float) -> torch.Tensor:
    """Unit vector toward the light in camera space (module docstring for the convention)."""
    a, e = math.radians(azimuth_deg), math.radians(elevation_deg)
    return torch.tensor([math.cos(e) * math.sin(a), math.sin(e), math.cos(e) * math.cos(a)], dtype=torch.float32)


def directional(
    azimuth_deg: float, elevation_deg: float, intensity: float = 1.0, size: int = BALL_SIZE, name: str | None = None
) -> Light:
    from pilight.physics import ball_from_direction

    _check_intensity(intensity)
    if not (math.isfinite(azimuth_deg) and math.isfinite(elevation_deg)):
        raise LightError(f"azimuth/elevation must be finite, got {azimuth_deg}, {elevation_deg}")
    ball = ball_from_direction(
        direction(azimuth_deg, elevation_deg),
        intensity=DIRECT_LEVEL * intensity,
        ambient=AMBIENT * intensity,
        size=size,
    )[0]
    label = name or f"az{azimuth_deg:g}_el{elevation_deg:g}"
    return Light(
        _safe(label + _suffix(intensity)),
        ball,
        f"distant light, azimuth {azimuth_deg:g} deg, elevation {elevation_deg:g} deg, intensity {intensity:g}",
        intensity=intensity,
    )


def named(name: str, intensity: float = 1.0, size: int = BALL_SIZE) -> Light:
    if name not in NAMED:
        raise LightError(
            f"unknown light {name!r}; choose one of {'|'.join(NAMED)}, or give --azimuth/--elevation, "
            "--ball FILE or --hdri FILE"
        )
    return directional(*NAMED[name], intensity=intensity, size=size, name=name)


def _disk(size: int) -> torch.Tensor:
    from pilight.physics import ball_normals

    return ball_normals(size, size)[1][0]


def from_ball(ball, intensity: float = 1.0, size: int = BALL_SIZE, name: str = "ball") -> Light:
    """A gray-ball picture (anything ``photo.as_photo`` takes) -> Light; it must be square."""
    _check_intensity(intensity)
    photo = as_photo(ball, name)
    h, w = photo.size
    if h != w:
        raise LightError(f"{name}: the light ball is {w}x{h}; crop it square, the ball touching all four borders")
    t = torch.from_numpy(photo.rgb).permute(2, 0, 1)[None]
    t = F.interpolate(t, size=(size, size), mode="bilinear", align_corners=False, antialias=True)[0]
    if not float((t * _disk(size)).sum()) > 0:
        raise LightError(f"{name}: the light ball's disk is black: it carries no light to relight with")
    ratio = silhouette_ratio(torch.from_numpy(photo.rgb).permute(2, 0, 1))
    if ratio < MIN_SILHOUETTE:
        warnings.warn(
            f"{name}: no round silhouette touching the four borders is visible (edge ratio {ratio:.2f}, a ball "
            f"shows >= {MIN_SILHOUETTE}); is it a gray ball cropped square? Its disk is used as the light anyway",
            LightWarning,
            stacklevel=2,
        )
    return Light(
        _safe(f"ball-{Path(name).stem}{_suffix(intensity)}"),
        (t * _disk(size) * intensity).contiguous(),
        f"light ball {name}, intensity {intensity:g}",
        intensity=intensity,
    )


def from_ball_file(path: str | Path, intensity: float = 1.0, size: int = BALL_SIZE) -> Light:
    try:
        photo = read_photo(path)
    except PhotoError as exc:
        raise LightError(f"--ball {exc}") from None
    return from_ball(photo, intensity, size, name=str(path))


# Camera looking along world +x with world +z up (Blender's equirect centre column faces +x):
# camera right = world -y, camera up = world +z, camera z (toward the camera) = world -x.
_WORLD_TO_CAMERA = torch.tensor([[0.0, -1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, 0.0, 0.0]])


def hdri_world_to_camera(rotate_deg: float) -> torch.Tensor:
    """The rotation for ``ball_from_hdri``: the base camera after turning the world by -rotate about z."""
    r = math.radians(-rotate_deg)
    rz = torch.tensor([[math.cos(r), -math.sin(r), 0.0], [math.sin(r), math.cos(r), 0.0], [0.0, 0.0, 1.0]])
    return _WORLD_TO_CAMERA @ rz


def check_panorama(h: int, w: int, name: str) -> None:
    """LightError unless h x w is an equirectangular (lat-long) panorama, exactly 2:1."""
    if w != 2 * h:
        raise LightError(
            f"{name}: {w}x{h} is not an equirectangular (lat-long) panorama; its width must be exactly "
            "twice its height (2:1)"
        )


def from_hdri(
    hdri, rotate_deg: float = 0.0, intensity: float = 1.0, size: int = BALL_SIZE, name: str = "hdri"
) -> Light:
    """An equirectangular panorama (H, W, 3) linear (or anything ``photo.as_photo`` takes) -> Light."""
    from pilight.physics import ball_from_hdri

    _check_intensity(intensity)
    if not math.isfinite(rotate_deg):
        raise LightError(f"--rotate must be finite, got {rotate_deg}")
    photo = as_photo(hdri, name)
    check_panorama(*photo.size, name)
    t = torch.from_numpy(photo.rgb).permute(2, 0, 1) * intensity
    ball = ball_from_hdri(t, hdri_world_to_camera(rotate_deg), size=size)[0]
    rot = "" if rotate_deg == 0 else f"_rot{rotate_deg:g}"
    return Light(
        _safe(f"hdri-{Path(name).stem}{rot}{_suffix(intensity)}"),
        ball.contiguous(),
        f"HDRI {name}, rotated {rotate_deg:g} deg, intensity {intensity:g}",
        intensity=intensity,
    )


def from_hdri_file(path: str | Path, rotate_deg: float = 0.0, intensity: float = 1.0, size: int = BALL_SIZE) -> Light:
    try:
        photo = read_photo(path)
    except PhotoError as exc:
        raise LightError(f"--hdri {exc}") from None
    return from_hdri(photo, rotate_deg, intensity, size, name=str(path))


def _pair(values: list[float], others: list, what: str, other: str) -> list[float]:
    """Broadcast one value over ``others`` or require one per item."""
    if len(values) == len(others):
        return values
    if len(values) == 1:
        return values * len(others)
    raise LightError(f"{len(values)} {what} value(s) for {len(others)} {other}: give one for all, or one each")


def parse_lights(
    names=(), azimuths=(), elevations=(), balls=(), hdris=(), rotates=(), intensity: float = 1.0, size: int = BALL_SIZE
) -> list[Light]:
    """The CLI's light options -> lights, in the order: names, directions, balls, HDRIs.

    One --hdri with several --rotate gives one light per rotation (a turning environment)."""
    names, azimuths, elevations = list(names or ()), list(azimuths or ()), list(elevations or ())
    balls, hdris, rotates = list(balls or ()), list(hdris or ()), list(rotates or ())
    lights = [named(n, intensity, size) for n in names]
    if azimuths or elevations:
        if not azimuths or not elevations:
            raise LightError("--azimuth and --elevation go together (degrees; see --help for the convention)")
        for a, e in zip(azimuths, _pair(elevations, azimuths, "--elevation", "--azimuth")):
            lights.append(directional(a, e, intensity, size))
    lights += [from_ball_file(b, intensity, size) for b in balls]
    if rotates and not hdris:
        raise LightError("--rotate turns an --hdri; no --hdri was given")
    if hdris:
        rotates = rotates or [0.0]
        if len(hdris) == 1:
            pairs = [(hdris[0], r) for r in rotates]
        else:
            pairs = list(zip(hdris, _pair(rotates, hdris, "--rotate", "--hdri")))
        panoramas = {}
        for path, r in pairs:
            if path not in panoramas:
                try:
                    panoramas[path] = read_photo(path)
                except PhotoError as exc:
                    raise LightError(f"--hdri {exc}") from None
            lights.append(from_hdri(panoramas[path], r, intensity, size, name=str(path)))
    if not lights:
        raise LightError(
            "no light given: use --light left|right|top|bottom|front, --azimuth/--elevation, --ball FILE or --hdri FILE"
        )
    seen: dict[str, int] = {}
    for light in lights:
        seen[light.name] = seen.get(light.name, 0) + 1
    twice = [n for n, c in seen.items() if c > 1]
    if twice:
        raise LightError(f"light(s) {twice} given more than once (their outputs would overwrite each other)")
    return lights


def ball_preview(ball: torch.Tensor) -> np.ndarray:
    """(3, S, S) linear ball -> sRGB uint8 (S, S, 3) for PNGs and contact sheets."""
    from pilight.pictures import linear_to_srgb8

    return linear_to_srgb8(ball.permute(1, 2, 0).cpu().numpy())
