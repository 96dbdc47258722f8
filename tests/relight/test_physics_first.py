"""Physics-first relit output (pilight.relight.physics_first): the identity, the anchors, linearity in
the light, the targets' round trip, and the task's outputs with an untrained tiny model."""

from __future__ import annotations

import pytest
import torch

from fixtures.relight_pairs import ONE_STEP, TINY, physics_pair, tiny_relight_task
from pilight.params import RelightParams
from pilight.physics.calculated import diffuse_calculated
from pilight.relight import physics_first as pf


def test_zero_gain_is_the_physics_anchor_and_gains_round_trip():
    anchor = torch.rand(2, 3, 8, 8) * 4
    eps = torch.full((2, 1, 1, 1), 0.05)
    torch.testing.assert_close(pf.apply_gain(torch.zeros_like(anchor), anchor, eps), anchor)
    value = torch.rand(2, 3, 8, 8) * 4
    torch.testing.assert_close(pf.apply_gain(pf.gain_of(value, anchor, eps), anchor, eps), value, atol=1e-5, rtol=1e-5)


def test_effective_albedo_recovers_the_albedo_of_a_physics_render():
    """Where the input IS A * D_calc_a, A_eff = A (up to the eps blend), so the anchor under light b is
    the physics render under b: the ratio form relights a Lambertian scene exactly."""
    b = physics_pair()
    intr = {k: b[k] for k in ("albedo", "normal", "metallic")}
    anc = pf.anchors(b["image_a"], intr, b["mask"], b["ball_b"], None, ball_a=b["ball_a"])
    lit = (b["mask"] > 0.5) & (diffuse_calculated(b["ball_a"], b["normal"], b["mask"], b["metallic"]) > 0.5)
    torch.testing.assert_close(
        anc.albedo.expand_as(lit)[lit.expand_as(anc.albedo)],
        b["albedo"][lit.expand_as(b["albedo"])],
        atol=1e-5,
        rtol=1e-5,
    )
    relit = pf.compose_relit(anc, torch.zeros_like(b["image_a"]), torch.zeros_like(b["image_a"]))["relit"]
    m = b["mask"].expand_as(relit) > 0.5
    torch.testing.assert_close(relit[m], b["image_b"][m], atol=1e-4, rtol=1e-4)


def test_targets_decode_to_the_target_image_at_full_resolution():
    b = physics_pair()
    intr = {k: b[k] for k in ("albedo", "normal", "metallic")}
    intr["albedo"] = intr["albedo"] * 0.5  # a wrong conditioning albedo: D_eff absorbs it
    anc = pf.anchors(b["image_a"], intr, b["mask"], b["ball_b"], None, albedo_source="conditioning")
    spec = torch.rand_like(b["image_b"]) * 0.05
    image_b = b["image_b"] + spec
    g_d = pf.gain_of(pf.diffuse_target(image_b, spec, anc.albedo), anc.d_calc, anc.eps)
    g_s = pf.gain_of(spec, anc.s_calc, anc.eps)
    relit = pf.compose_relit(anc, g_d, g_s)["relit"]
    m = (b["mask"] > 0.5).expand_as(relit) & (anc.albedo > pf.A_MIN)
    torch.testing.assert_close(relit[m], image_b[m], atol=1e-4, rtol=1e-4)


def test_task_outputs_satisfy_the_identity_on_the_mask(tmp_path):
    task = tiny_relight_task(tmp_path)
    b = physics_pair()
    out = task.predict(b, ONE_STEP, torch.Generator().manual_seed(0))
    assert set(out) == {"relit", "diffuse", "specular", "albedo"}
    m = b["mask"].expand_as(out["relit"]) > 0.5
    composed = out["albedo"] * out["diffuse"] + out["specular"]
    rel = (out["relit"] - composed).abs()[m].sum() / out["relit"].abs()[m].sum()
    assert rel < 1e-6
    assert not torch.equal(out["relit"][m], b["image_a"].expand_as(out["relit"])[m])


def test_relit_is_linear_in_the_target_light(tmp_path):
    """The network sees the target light only divided by its level, and physics carries the level:
    doubling the target ball doubles the relit image on the mask (light transport is linear)."""
    task = tiny_relight_task(tmp_path)
    b = physics_pair()
    one = task.predict(b, ONE_STEP, torch.Generator().manual_seed(0))
    two = task.predict(b | {"ball_b": 2 * b["ball_b"]}, ONE_STEP, torch.Generator().manual_seed(0))
    m = b["mask"].expand_as(one["relit"]) > 0.5
    torch.testing.assert_close(two["relit"][m], 2 * one["relit"][m], atol=1e-4, rtol=1e-4)


def test_loss_trains_every_branch_and_is_finite(tmp_path):
    task = tiny_relight_task(tmp_path, lambda_ds=1.0, lambda_ps=1.0, lambda_rec=0.1)
    task.stack.model.train()
    loss, logs = task.loss(physics_pair(), torch.Generator().manual_seed(0))
    assert torch.isfinite(loss)
    assert logs["l_ps"] == pytest.approx(0.0, abs=1e-6)  # the identity holds by construction (A_x in L_PS)
    loss.backward()
    assert all(
        p.grad is not None and torch.isfinite(p.grad).all()
        for p in task.trainable().parameters()
        if p.requires_grad and p.grad is not None
    )


def test_rendered_source_light_needs_the_input_ball(tmp_path):
    from pilight.data.schema import DataError

    task = tiny_relight_task(tmp_path, form={**TINY["form"], "source_light": "rendered"})
    b = physics_pair()
    del b["ball_a"]
    with pytest.raises(DataError, match="ball_a"):
        task.predict(b, ONE_STEP, torch.Generator().manual_seed(0))


def test_estimated_source_light_relights_a_physics_render_nearly_exactly():
    """No ball of light a given: it is fitted to the input (pilight.physics.source_light), and the
    anchor under light b is the physics render under b to within the SH fit's error (largest where
    light a barely reached), a quarter of what copying the input misses by at most."""
    b = physics_pair()
    intr = {k: b[k] for k in ("albedo", "normal", "metallic")}
    anc = pf.anchors(b["image_a"], intr, b["mask"], b["ball_b"], None)
    relit = pf.compose_relit(anc, torch.zeros_like(b["image_a"]), torch.zeros_like(b["image_a"]))["relit"]
    m = b["mask"].expand_as(relit) > 0.5
    err, copy_err = (relit - b["image_b"]).abs()[m].mean(), (b["image_a"] - b["image_b"]).abs()[m].mean()
    assert err < 0.15 * b["image_b"][m].mean() and err < 0.25 * copy_err


def test_an_image_whose_light_cannot_be_estimated_keeps_the_conditioning_albedo():
    b = physics_pair()
    intr = {k: b[k] for k in ("albedo", "normal", "metallic")}
    intr["albedo"] = torch.zeros_like(intr["albedo"])  # no usable pixel: nothing to fit the light to
    intr["albedo"][1] = b["albedo"][1]
    anc = pf.anchors(b["image_a"], intr, b["mask"], b["ball_b"], None)
    torch.testing.assert_close(anc.albedo[0], intr["albedo"][0])
    assert not torch.equal(anc.albedo[1], intr["albedo"][1])


@pytest.mark.parametrize("bad", [{"decomposition": False}, {"form": {"kind": "physics_first", "target": "residual"}}])
def test_physics_first_refuses_layouts_it_cannot_form(bad):
    with pytest.raises(ValueError, match="physics_first"):
        RelightParams.model_validate({**TINY, **bad})


def test_ggx_specular_anchor_adds_the_microfacet_highlight_of_the_target_light():
    """specular 'ggx': S_calc_b is the microfacet highlight of the target ball's light (an analytic ball
    is its own Lambertian twin), where the lookup says 0; an unknown kind is refused by name."""
    from pilight.physics.specular_model import specular_from_ball

    b = physics_pair()
    intr = {k: b[k] for k in ("albedo", "normal", "metallic", "roughness")}
    lookup = pf.anchors(b["image_a"], intr, b["mask"], b["ball_b"], None)
    ggx = pf.anchors(b["image_a"], intr, b["mask"], b["ball_b"], None, specular="ggx")
    assert float(lookup.s_calc.abs().sum()) == 0.0
    want = specular_from_ball(b["ball_b"], b["normal"], b["roughness"], b["albedo"], b["metallic"]) * b["mask"]
    torch.testing.assert_close(ggx.s_calc, want)
    assert float(want.sum()) > 0
    relit = pf.compose_relit(ggx, torch.zeros_like(b["image_a"]), torch.zeros_like(b["image_a"]))
    torch.testing.assert_close(relit["relit"], relit["albedo"] * relit["diffuse"] + relit["specular"])
    with pytest.raises(ValueError, match="specular anchor"):
        pf.anchors(b["image_a"], intr, b["mask"], b["ball_b"], None, specular="phong")


def test_relative_intensity_takes_the_level_from_the_level_fit(tmp_path):
    """A relative light is scaled to the input's level as the LEVEL's fit estimates it (first order,
    pilight.physics.source_light), not the shading's nine-term fit, whose ball strays outside the
    image's normals."""
    from pilight.physics.envmap import light_level

    task = tiny_relight_task(tmp_path, intensity="relative")
    b = physics_pair()
    intr = {k: b[k] for k in ("albedo", "normal", "roughness", "metallic")}
    _, _, balls = task._conditions(b, intr, "cpu")
    size = b["ball_b"].shape[-1]
    by_level_fit, _ = pf.source_balls(b["image_a"], intr, b["mask"], size, level=True)
    by_shading_fit, _ = pf.source_balls(b["image_a"], intr, b["mask"], size)
    torch.testing.assert_close(balls["ball_b"], b["ball_b"] * light_level(by_level_fit))
    assert not torch.allclose(light_level(by_level_fit), light_level(by_shading_fit), rtol=1e-3)


@pytest.mark.parametrize(
    ("form", "intensity", "fits"),
    [
        ({}, "relative", [False, True]),  # effective albedo, estimated light: shading fit, then level fit
        ({}, "absolute", [False]),  # no level is estimated
        ({"source_light": "rendered"}, "relative", []),  # ball_a serves both
        ({"albedo_source": "conditioning"}, "relative", [True]),  # no effective albedo: the level only
        ({"albedo_source": "conditioning"}, "absolute", []),
    ],
)
def test_each_form_estimates_the_fits_it_needs(tmp_path, monkeypatch, form, intensity, fits):
    """Which fits of the input's light each form and intensity run (level=True: the level's fit)."""
    calls = []
    original = pf.source_balls

    def recording(*args, level=False, **kw):
        calls.append(level)
        return original(*args, level=level, **kw)

    monkeypatch.setattr(pf, "source_balls", recording)
    task = tiny_relight_task(tmp_path, form={**TINY["form"], **form})
    b = physics_pair()
    intr = {k: b[k] for k in ("albedo", "normal", "roughness", "metallic")}
    task._conditions(b, intr, "cpu", intensity)
    assert calls == fits
