"""Light from the left versus from the right flips the sign of the relit image's left/right
luminance asymmetry, on a real photograph, with the embedded default's trained models (models/, after
`dvc repro`) or, in a fresh clone, the shipped base. At k = 1 (relative intensity, the default) the
relit photo keeps the photo's detail (mean luminance gradient, ratio >= 0.6) and its exposure (mean
luminance, ratio in [0.67, 1.5]) under both lights (slow)."""

from __future__ import annotations

import pytest

from fixtures.tiny_models import REPO
from pilight.eval.photo_measures import detail, exposure, halves_asymmetry

MODELS = REPO / "models"


@pytest.mark.slow
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
    a_left, a_right = halves_asymmetry(out.relit[0]), halves_asymmetry(out.relit[1])
    assert a_left < 0 < a_right, (
        f"relit (R - L) / (R + L) with {models}: {a_left:+.3f} under the left light, {a_right:+.3f} under "
        f"the right one (the photo itself: {halves_asymmetry(photo):+.3f})"
    )
    for name, relit in zip(("left", "right"), out.relit):
        kept = detail(relit) / detail(photo)
        ratio = exposure(relit, photo)
        assert kept >= 0.6, f"{name}: the relit photo keeps {kept:.2f} of the photo's detail"
        assert 0.67 <= ratio <= 1.5, f"{name}: the relit photo's exposure is {ratio:.2f}x the photo's at k = 1"
