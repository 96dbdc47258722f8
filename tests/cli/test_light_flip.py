"""Light from the left versus from the right flips the sign of the relit image's left/right
luminance asymmetry, on a real photograph, with the embedded default's trained models (models/, after
`dvc repro`) or, in a fresh clone, the shipped base. At k = 1 (relative intensity, the default) the
relit photo keeps the photo's detail (mean luminance gradient, ratio >= 0.6) and its exposure (mean
luminance, ratio in [0.67, 1.5]) under both lights (slow)."""

from __future__ import annotations

import numpy as np
import pytest

from tests.cli.tiny import REPO

MODELS = REPO / "models"
LUMINANCE = np.array([0.2126, 0.7152, 0.0722], np.float32)


def lr_asymmetry(rgb: np.ndarray) -> float:
    """(R - L) / (R + L) of the mean luminance of the right and left halves of an (H, W, 3) image."""
    y = rgb @ LUMINANCE
    half = y.shape[1] // 2
    left, right = float(y[:, :half].mean()), float(y[:, half:].mean())
    return (right - left) / max(right + left, 1e-12)


def detail(rgb: np.ndarray) -> float:
    """Mean absolute luminance gradient (both axes) of an (H, W, 3) linear image."""
    y = rgb @ LUMINANCE
    return float(np.abs(np.diff(y, axis=0)).mean() + np.abs(np.diff(y, axis=1)).mean())


@pytest.mark.slow
@pytest.mark.xfail(
    strict=True,  # an unexpected pass fails CI too: whoever makes it pass removes this marker
    reason="issue #33, open: with pilight-base (ea6a7b9) and the default fine-tuned from it (bd934e0) the relit "
    "asymmetry is -0.32 / -0.24 and -0.20 / -0.11 under left / right light (moves, does not flip: stage 1 reads "
    "the portrait as a room, normals n_y +0.81 in the bottom half as a floor's); detail and exposure pass since "
    "exposure: photo (detail 1.41-1.45, exposure 1.00); benchmarks/photo_relight.py prints them",
)
def test_left_versus_right_light_flips_the_relit_asymmetry(astronaut):
    from pilight.base_model import default_models

    models, _ = default_models(MODELS)
    if not (
        (models / "intrinsics" / "model.safetensors").is_file() and (models / "relight" / "model.safetensors").is_file()
    ):
        pytest.skip(f"{MODELS} holds no trained models and no base is shipped; run `dvc repro` first")
    from pilight import lights
    from pilight.photo import as_photo
    from pilight.pipeline import PILightPipeline

    pipe = PILightPipeline.from_pretrained(models, device="cpu", params=REPO / "params.yaml")
    out = pipe.relight(astronaut, [lights.named("left"), lights.named("right")])
    photo = as_photo(astronaut).rgb
    a_left, a_right = lr_asymmetry(out.relit[0]), lr_asymmetry(out.relit[1])
    assert a_left < 0 < a_right, (
        f"relit (R - L) / (R + L) with {models}: {a_left:+.3f} under the left light, {a_right:+.3f} under "
        f"the right one (the photo itself: {lr_asymmetry(photo):+.3f})"
    )
    for name, relit in zip(("left", "right"), out.relit):
        kept = detail(relit) / detail(photo)
        exposure = float((relit @ LUMINANCE).mean() / (photo @ LUMINANCE).mean())
        assert kept >= 0.6, f"{name}: the relit photo keeps {kept:.2f} of the photo's detail"
        assert 0.67 <= exposure <= 1.5, f"{name}: the relit photo's exposure is {exposure:.2f}x the photo's at k = 1"
