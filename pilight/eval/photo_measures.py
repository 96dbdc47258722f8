"""What a relit photo is measured by where no ground truth exists (issue 33's flip test and
benchmarks/photo_relight.py): which side the light brightens, how much of the photo's detail is kept,
and its exposure. All on Rec. 709 luminance of (H, W, 3) linear images."""

from __future__ import annotations

import numpy as np

from pilight.data.colour import REC709_LUMINANCE

LUMINANCE = np.array(REC709_LUMINANCE, np.float32)


def halves_asymmetry(rgb: np.ndarray) -> float:
    """(R - L) / (R + L) of the mean luminance of the picture's right and left halves: > 0 when the right is
    brighter (pilight.eval.light_following.lr_asymmetry sides by the normals instead, where they are known)."""
    y = rgb @ LUMINANCE
    half = y.shape[1] // 2
    left, right = float(y[:, :half].mean()), float(y[:, half:].mean())
    return (right - left) / max(right + left, 1e-12)


def detail(rgb: np.ndarray) -> float:
    """Mean absolute luminance gradient, both axes (the detail ratio divides the relit photo's by the photo's)."""
    y = rgb @ LUMINANCE
    return float(np.abs(np.diff(y, axis=0)).mean() + np.abs(np.diff(y, axis=1)).mean())


def exposure(rgb: np.ndarray, photo: np.ndarray) -> float:
    """Mean luminance of ``rgb`` over the photo's (the exposure ratio)."""
    return float((rgb @ LUMINANCE).mean() / max(float((photo @ LUMINANCE).mean()), 1e-12))
