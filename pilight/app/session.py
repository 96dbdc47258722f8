"""One photo in the app: read and decomposed once, then relit for every light the user places.

Everything that does not depend on the light is kept between changes of light: the photo, its
processing-size tensors and stage 1's maps (``DecompositionOutput.conditions``), so a change of light
costs one stage-2 pass and the full-size detail transfer (pilight.pipeline.relight with
``intrinsics=``), about 0.1 s for a 512^2 photo on 2 cores (benchmarks/app_latency.py).

Every user-facing failure is an ``AppError`` whose message the page shows as it is.
"""

from __future__ import annotations

import shlex
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from PIL import Image

from pilight.data.exr import write_exr
from pilight.lights import BALL_SIZE, Light, LightError, ball_preview
from pilight.photo import Photo, PhotoError, check_size, probe, read_photo
from pilight.physics.source_light import estimate_source_balls
from pilight.pictures import linear_to_srgb8, normal_preview
from pilight.pipeline import DecompositionOutput, MemoryLimitError, PILightPipeline, PipelineError

MAX_PIXELS = 40_000_000  # larger uploads are refused before decoding (a 40 MP photo is 0.5 GB as float32)
MAPS = ("albedo", "normal", "roughness", "metallic")


class AppError(ValueError):
    """What the page says instead of a stack trace: bad upload, a light that cannot be made, no photo yet."""


@dataclass
class Relit:
    """One relighting as the page shows it: 8-bit sRGB pictures, and the linear maps for downloads."""

    pictures: dict[str, np.ndarray]  # relit, diffuse, specular (H, W, 3) uint8
    linear: dict[str, np.ndarray]  # the same, linear float32
    light: Light
    seconds: float


@dataclass
class PhotoSession:
    """A decomposed photo, ready to be relit (module docstring)."""

    pipe: PILightPipeline
    photo: Photo
    path: Path
    decomposition: DecompositionOutput
    source_ball: np.ndarray  # (S, S, 3) uint8: the light the photo was lit by, as estimated
    resolution: int | None = None  # processing size of the longer side (None: the models' own; 0: the photo's)
    last: Relit | None = field(default=None, repr=False)

    @classmethod
    def open(cls, pipe: PILightPipeline, path: str | Path | None, resolution: int | None = None) -> PhotoSession:
        """Read, check and decompose an uploaded file at the processing ``resolution`` (the CLI's
        --resolution). AppError for anything a user can fix."""
        if path is None:
            raise AppError("no photo: upload a picture (PNG, JPEG, TIFF, WebP, BMP, EXR or HDR)")
        path = Path(path)
        try:
            h, w = probe(path)  # the header only: nothing is decoded before the size is known
            if h * w > MAX_PIXELS:
                raise AppError(
                    f"{path.name}: {w}x{h} pixels is over the app's limit of {MAX_PIXELS / 1e6:.0f} megapixels; "
                    "scale it down, or use `pilight relight` with --resolution"
                )
            check_size(h, w, path.name)
            pipe.check_memory(h, w, 1, name=path.name, resolution=resolution)
            photo = read_photo(path)
        except (PhotoError, MemoryLimitError) as exc:
            raise AppError(str(exc).replace(str(path), path.name)) from None
        try:
            decomposition = pipe.decompose(photo, name=path.name, resolution=resolution)
        except (PhotoError, PipelineError) as exc:
            raise AppError(str(exc)) from None
        return cls(pipe, photo, path, decomposition, _source_ball(pipe, decomposition), resolution)

    def maps(self) -> dict[str, np.ndarray]:
        """Stage 1's maps as 8-bit pictures, and the estimated light as a ball."""
        d = self.decomposition
        return {
            "albedo": linear_to_srgb8(d.albedo),
            "normal": normal_preview(d.normal),
            "roughness": linear_to_srgb8(d.roughness),
            "metallic": linear_to_srgb8(d.metallic),
            "estimated light": self.source_ball,
        }

    def relight(self, light: Light, *, keep_exposure: bool = True) -> Relit:
        """The photo under ``light`` (relative intensity; ``keep_exposure``: the CLI's --exposure photo)."""
        t0 = time.perf_counter()
        try:
            out = self.pipe.relight(
                self.photo,
                light,
                intrinsics=self.decomposition,
                resolution=self.resolution,
                name=self.path.name,
                exposure="photo" if keep_exposure else "light",
            )
        except (PipelineError, LightError) as exc:
            raise AppError(str(exc)) from None
        linear = {k: v[0] for k in ("relit", "diffuse", "specular") if (v := getattr(out, k)) is not None}
        pictures = {k: linear_to_srgb8(v) for k, v in linear.items()}
        self.last = Relit(pictures, linear, light, time.perf_counter() - t0)
        return self.last

    def export(self, command: str) -> list[Path]:
        """The last relighting's files in a new folder: relit, D, S, the four maps (EXR and PNG), the
        mixed light as a ball (light.exr, which ``command`` reads) and the command itself."""
        if self.last is None:
            raise AppError("nothing to download yet: place a light on the ball first")
        folder = Path(tempfile.mkdtemp(prefix="pilight-app-"))
        d = self.decomposition
        linear = {**self.last.linear, **{m: getattr(d, m) for m in MAPS}}
        files = []
        for name, arr in linear.items():
            write_exr(folder / f"{name}.exr", arr, half=False)
            picture = normal_preview(arr) if name == "normal" else linear_to_srgb8(arr)
            Image.fromarray(picture).save(folder / f"{name}.png")
            files += [folder / f"{name}.exr", folder / f"{name}.png"]
        write_exr(folder / "light.exr", self.last.light.ball.permute(1, 2, 0).numpy(), half=False)
        Image.fromarray(ball_preview(self.last.light.ball)).save(folder / "light.png")
        (folder / "command.txt").write_text(command + "\n", encoding="utf-8")
        return [*files, folder / "light.exr", folder / "light.png", folder / "command.txt"]


def _source_ball(pipe: PILightPipeline, d: DecompositionOutput) -> np.ndarray:
    """The photo's own light as the effective albedo's fit estimates it (pilight.physics.source_light; the
    relative mode takes its level from a first-order fit), normalised to its maximum, 8-bit."""
    c = d.conditions
    balls, found = estimate_source_balls(c["image"], c["albedo"], c["normal"], c["mask"], BALL_SIZE, c["metallic"])
    if not bool(found[0]):
        return np.zeros((BALL_SIZE, BALL_SIZE, 3), np.uint8)
    ball = balls[0].clamp_min(0)
    return ball_preview(ball / max(float(ball.max()), 1e-6) * 0.9)


def relight_command(
    photo_name: str, light: Light, *, keep_exposure: bool, direction=None, extra: list[str] | None = None
) -> str:
    """The `pilight relight` command that reproduces a relighting: the direction itself for one white
    distant light (``direction`` = (azimuth, elevation)), else the mixed light as a ball file; ``extra``:
    the model options the app runs with."""
    parts = ["pilight", "relight", photo_name]
    if direction is not None:
        parts += ["--azimuth", f"{direction[0]:.6g}", "--elevation", f"{direction[1]:.6g}"]
    else:
        parts += ["--ball", "light.exr"]
    parts += ["--intensity", f"{light.intensity:.6g}", "--exposure", "photo" if keep_exposure else "light"]
    return shlex.join([*parts, *(extra or []), "-o", "relit"])
