"""Relative light intensity (pilight.relight.intensity): what the albedo's level does and does not do to a
relative relight, and a photo relit under its own estimated light at k = 1 returning itself."""

from __future__ import annotations

import pytest
import torch

from fixtures.relight_pairs import ONE_STEP, TINY, physics_pair, tiny_relight_task
from pilight.physics.calculated import diffuse_calculated
from pilight.physics.envmap import light_level
from pilight.relight import physics_first as pf
from pilight.relight.intensity import relative_light, relative_pair, to_source_level


def _relit(task, batch, albedo_scale: float, intensity: str) -> dict:
    intr = {k: batch[k] for k in ("albedo", "normal", "metallic", "roughness")}
    intr["albedo"] = intr["albedo"] * albedo_scale
    given = relative_pair(batch) if intensity == "relative" else batch
    return task.predict(given, ONE_STEP, None, intr, intensity=intensity, zero_gains=True)


def _diffuse_lit(batch) -> torch.Tensor:
    """Masked pixels the input's light reaches well (the ratio form's domain; shadows keep A_c's eps blend)."""
    d_a = diffuse_calculated(batch["ball_a"], batch["normal"], batch["mask"], batch["metallic"])
    return ((batch["mask"] > 0.5) & (d_a.mean(1, keepdim=True) > 0.3)).expand(-1, 3, -1, -1)


@pytest.mark.parametrize("specular, mean_tol", [("lookup", 1e-6), ("ggx", 0.03)])
def test_albedo_level_cancels_in_relative_mode_on_diffuse_pixels(tmp_path, specular, mean_tol):
    """Twice the conditioning albedo halves the estimated light and doubles A_eff, so the diffuse part A_x D
    of the relative relight stays. Exactly with the `lookup` anchor (an estimated light has no highlight of
    its own). With `ggx` the input's own estimated highlight S_a (F0 = 0.04 whatever the albedo, at the
    estimated light's level) is subtracted before A_eff and does not cancel: 2.3% of A_x D on average over
    the lit pixels of this 0.5-rough sphere. The absolute relight doubles in both."""
    task = tiny_relight_task(tmp_path, form={**TINY["form"], "specular_anchor": specular})
    b = physics_pair()
    lit = _diffuse_lit(b)
    diffuse_part = lambda out: out["relit"] - out["specular"]  # A_x D on the mask
    rel1, rel2 = (diffuse_part(_relit(task, b, s, "relative")) for s in (1.0, 2.0))
    assert float(((rel2 - rel1).abs()[lit] / rel1[lit]).mean()) < mean_tol
    abs1, abs2 = (diffuse_part(_relit(task, b, s, "absolute")) for s in (1.0, 2.0))
    ratio = (abs2[lit] / abs1[lit].clamp_min(1e-8)).median()
    assert float(ratio) == pytest.approx(2.0, rel=0.03)  # absolute: the albedo's level passes into the relit image


def test_the_dielectric_highlight_does_not_cancel(tmp_path):
    """S_calc (GGX, F0 = 0.04 whatever the albedo) follows the estimated light's level: with twice the albedo
    the relative relight's specular part halves while its diffuse part stays."""
    task = tiny_relight_task(tmp_path, form={**TINY["form"], "specular_anchor": "ggx"})
    b = physics_pair()
    b["roughness"] = torch.full_like(b["roughness"], 0.2)  # a visible highlight
    one, two = _relit(task, b, 1.0, "relative"), _relit(task, b, 2.0, "relative")
    m = (b["mask"] > 0.5).expand(-1, 3, -1, -1) & (one["specular"] > 1e-3)
    assert int(m.sum()) > 0
    ratio = (two["specular"][m] / one["specular"][m]).median()
    assert float(ratio) == pytest.approx(0.5, rel=0.02)


def test_relative_pair_tells_the_model_r():
    b = physics_pair()
    rel = relative_pair(b)
    r = light_level(b["ball_b"]) / light_level(b["ball_a"])
    torch.testing.assert_close(light_level(rel["ball_b"]), r)
    with pytest.raises(KeyError, match="ball_a"):
        relative_pair({k: v for k, v in b.items() if k != "ball_a"})


def test_relative_light_keeps_shape_and_colour_and_sets_the_level():
    ball = physics_pair()["ball_b"] * torch.tensor([1.0, 0.8, 0.6]).view(1, 3, 1, 1)
    rel = relative_light(ball, torch.tensor([1.0, 2.5]))
    torch.testing.assert_close(light_level(rel).flatten(), torch.tensor([1.0, 2.5]))
    torch.testing.assert_close(rel[0] / rel[0].amax(), ball[0] / ball[0].amax())  # shape and colour kept
    # an input whose light was not found keeps the relative ball as it is
    out = to_source_level({"ball_b": rel}, ball * 3, torch.tensor([True, False]))["ball_b"]
    torch.testing.assert_close(out[1], rel[1])
    torch.testing.assert_close(light_level(out[:1]), light_level(ball[:1] * 3))


def test_own_light_at_k1_returns_the_photo(tmp_path):
    """Relit under its own estimated light at k = 1, a physics render of a Lambertian sphere is itself, to the
    tolerance the anchor achieves: the mean error is 1.1% of the mean on the mask, the largest 5.8% of a
    lit pixel's value. Not exact because A_eff blends in eps_a A_c, and A_c D_a (the SH estimate) differs
    from the render by the estimate's misfit. Off the mask the photo is untouched."""
    task = tiny_relight_task(tmp_path, form={**TINY["form"], "specular_anchor": "ggx"})
    b = physics_pair()
    intr = {k: b[k] for k in ("albedo", "normal", "metallic", "roughness")}
    own, found = pf.source_balls(b["image_a"], intr, b["mask"], b["ball_b"].shape[-1])
    assert bool(found.all())
    batch = b | {"ball_b": relative_light(own, 1.0)}
    batch.pop("ball_a")  # a photo has no ball of its own light
    relit = task.predict(batch, ONE_STEP, None, intr, intensity="relative", zero_gains=True)["relit"]
    image, lit, m = b["image_a"], _diffuse_lit(b), (b["mask"] > 0.5).expand(-1, 3, -1, -1)
    err = (relit - image).abs()
    assert float(err[m].mean() / image[m].mean()) < 0.015
    assert float((err[lit] / image[lit]).max()) < 0.07
    assert torch.equal(relit[~m], image[~m])
    # twice the light (k = 2) is twice the photo on the same pixels, to the same tolerance
    batch["ball_b"] = relative_light(own, 2.0)
    twice = task.predict(batch, ONE_STEP, None, intr, intensity="relative", zero_gains=True)["relit"]
    assert float(((twice - 2 * image).abs()[m]).mean() / (2 * image[m]).mean()) < 0.015
