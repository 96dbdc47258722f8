"""reports/relit_lights.png: several test images, one row each, relit under the same analytic lights
swept around them (camera-left to camera-right at 30 degrees elevation); above each column, its light
ball. The picture that shows at a glance whether the relit image follows the light."""

from __future__ import annotations

import numpy as np
import torch

from pilight.eval.grids import labelled_grid
from pilight.lights import direction
from pilight.physics import ball_from_light
from pilight.pictures import to_uint8

SWEEP_AZIMUTH_DEG = 120.0  # the lights run from -120 (camera-left, behind) to +120 (camera-right)
SWEEP_ELEVATION_DEG = 30.0
HEADER_PEAK = 0.9  # the header balls' brightest pixel (display), whatever each row's exposure


def sweep_directions(count: int) -> tuple[torch.Tensor, list[float]]:
    """(count, 3) camera-space unit vectors toward the lights, and their azimuths in degrees."""
    az = torch.linspace(-SWEEP_AZIMUTH_DEG, SWEEP_AZIMUTH_DEG, count).tolist()
    return torch.stack([direction(a, SWEEP_ELEVATION_DEG) for a in az]), az


def sweep_balls(pair: dict, count: int) -> torch.Tensor:
    """The sweep's balls for one pair, exposed like its own target ball (the data's ball peak is
    0.5 (intensity + ambient))."""
    size = pair["ball_b"].shape[-1]
    intensity = 2 * float(pair["ball_b"].amax()) / 1.03
    dirs, _ = sweep_directions(count)
    return ball_from_light(direction=dirs, intensity=intensity, ambient=0.03 * intensity, size=size)


def relit_lights_grid(predict, pairs: list[tuple[dict, dict]], count: int) -> np.ndarray:
    """``pairs``: (one-pair batch, its conditioning intrinsics); ``predict(batch, intr)`` -> the task's
    outputs. Rows: input | relit under each light; a header row of the lights' balls."""
    dirs, az = sweep_directions(count)
    h = pairs[0][0]["image_a"].shape[-2]
    header = ball_from_light(direction=dirs, intensity=1.0, ambient=0.03, size=h)
    header = header * HEADER_PEAK / header.amax()
    rows: list[list[np.ndarray | None]] = [[None] + [to_uint8(b, hdr=True) for b in header]]
    for pair, intr in pairs:
        balls = sweep_balls(pair, count)
        rep = {k: (v.expand(count, *v.shape[1:]) if torch.is_tensor(v) else v * count) for k, v in pair.items()}
        rep["ball_b"] = balls
        rep["ball_lambertian_b"] = balls  # analytic balls have no highlight: they are their own Lambertian twin
        out = predict(rep, {k: v.expand(count, *v.shape[1:]) for k, v in intr.items()})
        rows.append(
            [to_uint8(pair["image_a"][0], hdr=True)] + [to_uint8(out["relit"][i], hdr=True) for i in range(count)]
        )
    labels = ["input"] + [f"light {a:+.0f} deg" for a in az]
    return labelled_grid(rows, labels, row_labels=["light"] + [f"test {i + 1}" for i in range(len(pairs))])
