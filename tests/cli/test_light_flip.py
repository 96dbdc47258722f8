"""Light from the left versus from the right flips the sign of the relit image's left/right
luminance asymmetry, on a real photograph, with the embedded default's trained models (slow:
needs `dvc repro train_relight`'s models/)."""

from __future__ import annotations

import numpy as np
import pytest

from tests.cli.tiny import REPO

MODELS = REPO / "models"


def lr_asymmetry(rgb: np.ndarray) -> float:
    """(R - L) / (R + L) of the mean luminance of the right and left halves of an (H, W, 3) image."""
    y = rgb @ np.array([0.2126, 0.7152, 0.0722], np.float32)
    half = y.shape[1] // 2
    left, right = float(y[:, :half].mean()), float(y[:, half:].mean())
    return (right - left) / max(right + left, 1e-12)


@pytest.mark.slow
def test_left_versus_right_light_flips_the_relit_asymmetry(astronaut):
    if not (
        (MODELS / "intrinsics" / "model.safetensors").is_file() and (MODELS / "relight" / "model.safetensors").is_file()
    ):
        pytest.skip(f"{MODELS} holds no trained models; run `dvc repro train_relight` first")
    from pilight import lights
    from pilight.photo import as_photo
    from pilight.pipeline import PILightPipeline

    pipe = PILightPipeline.from_pretrained(MODELS, device="cpu", params=REPO / "params.yaml")
    out = pipe.relight(astronaut, [lights.named("left"), lights.named("right")])
    a_left, a_right = lr_asymmetry(out.relit[0]), lr_asymmetry(out.relit[1])
    assert a_left < 0 < a_right, (
        f"relit (R - L) / (R + L): {a_left:+.3f} under the left light, {a_right:+.3f} under "
        f"the right one (the photo itself: {lr_asymmetry(as_photo(astronaut).rgb):+.3f})"
    )
