"""Physics-first relit output (pilight.relight.physics_first): the identity, the anchors, linearity in
the light, the targets' round trip, and the task's outputs with an untrained tiny model."""

from __future__ import annotations

import json

import pytest
import torch

from pilight.params import RelightParams, SamplingParams
from pilight.physics.calculated import diffuse_calculated
from pilight.physics.shading import ball_from_direction
from pilight.relight import physics_first as pf
from pilight.train.relight import RelightTask

H = 16
TINY = {
    "unet": {"block_out_channels": [32, 32], "layers_per_block": 1, "attention_head_dim": 8, "cross_attention_dim": 32},
    "codec": {"kind": "pixel", "factor": 4},
    "conditions": "gt",
    "relit_target": "gain",
    "relit_resolution": "cell",
    "physics_first": True,
    "d_calc_condition": [],
}
ONE_STEP = SamplingParams(mode="single_step", cfg_scale=1.0)


def _sphere(b: int = 2, h: int = H) -> tuple[torch.Tensor, torch.Tensor]:
    """Normals of a sphere filling the frame, and its mask (B x 3|1 x h x h)."""
    y, x = torch.meshgrid(1 - 2 * (torch.arange(h) + 0.5) / h, 2 * (torch.arange(h) + 0.5) / h - 1, indexing="ij")
    inside = (x**2 + y**2) < 0.95
    z = (1 - x**2 - y**2).clamp_min(0).sqrt()
    n = torch.stack([x, y, z]) * inside
    return n.expand(b, 3, h, h).clone(), inside.float().expand(b, 1, h, h).clone()


def _ball(direction, intensity=2.0, ambient=0.1, b=2):
    return ball_from_direction(torch.tensor(direction, dtype=torch.float32), intensity, ambient, size=16).expand(
        b, -1, -1, -1
    )


def _pair(b: int = 2) -> dict:
    """A Lambertian sphere rendered BY PHYSICS under light a, and the same under light b."""
    n, mask = _sphere(b)
    g = torch.Generator().manual_seed(0)
    albedo = (0.2 + 0.6 * torch.rand(b, 3, H, H, generator=g)) * mask
    metallic = torch.zeros(b, 1, H, H)
    ball_a, ball_b = _ball([-0.6, 0.5, 0.6], b=b), _ball([0.7, 0.3, 0.6], intensity=3.0, b=b)
    image = lambda ball: albedo * diffuse_calculated(ball, n, mask, metallic)
    meta = lambda light: [json.dumps({"scene": f"s{i}", "view": 0, "light": light}) for i in range(b)]
    return {
        "image_a": image(ball_a),
        "image_b": image(ball_b),
        "ball_a": ball_a,
        "ball_b": ball_b,
        "albedo": albedo,
        "normal": n,
        "mask": mask,
        "metallic": metallic,
        "roughness": torch.full((b, 1, H, H), 0.5),
        "diffuse_b": diffuse_calculated(ball_b, n, mask, metallic),
        "specular_b": torch.zeros(b, 3, H, H),
        "key": [f"s{i}_v00_l00_to_l01" for i in range(b)],
        "meta_a": meta(0),
        "meta_b": meta(1),
    }


def _task(tmp_path, **kw) -> RelightTask:
    torch.manual_seed(0)
    task = RelightTask(RelightParams.model_validate({**TINY, **kw}), tmp_path, seed=0)
    task.stack.model.eval()
    return task


def test_zero_gain_is_the_physics_anchor_and_gains_round_trip():
    anchor = torch.rand(2, 3, 8, 8) * 4
    eps = torch.full((2, 1, 1, 1), 0.05)
    torch.testing.assert_close(pf.apply_gain(torch.zeros_like(anchor), anchor, eps), anchor)
    value = torch.rand(2, 3, 8, 8) * 4
    torch.testing.assert_close(pf.apply_gain(pf.gain_of(value, anchor, eps), anchor, eps), value, atol=1e-5, rtol=1e-5)


def test_effective_albedo_recovers_the_albedo_of_a_physics_render():
    """Where the input IS A * D_calc_a, A_eff = A (up to the eps blend), so the anchor under light b is
    the physics render under b: the ratio form relights a Lambertian scene exactly."""
    b = _pair()
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
    b = _pair()
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
    task = _task(tmp_path)
    b = _pair()
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
    task = _task(tmp_path)
    b = _pair()
    one = task.predict(b, ONE_STEP, torch.Generator().manual_seed(0))
    two = task.predict(b | {"ball_b": 2 * b["ball_b"]}, ONE_STEP, torch.Generator().manual_seed(0))
    m = b["mask"].expand_as(one["relit"]) > 0.5
    torch.testing.assert_close(two["relit"][m], 2 * one["relit"][m], atol=1e-4, rtol=1e-4)


def test_loss_trains_every_branch_and_is_finite(tmp_path):
    task = _task(tmp_path, lambda_ds=1.0, lambda_ps=1.0, lambda_rec=0.1)
    task.stack.model.train()
    loss, logs = task.loss(_pair(), torch.Generator().manual_seed(0))
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

    task = _task(tmp_path, source_light="rendered")
    b = _pair()
    del b["ball_a"]
    with pytest.raises(DataError, match="ball_a"):
        task.predict(b, ONE_STEP, torch.Generator().manual_seed(0))


def test_estimated_source_light_relights_a_physics_render_nearly_exactly():
    """No ball of light a given: it is fitted to the input (pilight.physics.source_light), and the
    anchor under light b is the physics render under b to within the SH fit's error (largest where
    light a barely reached), a quarter of what copying the input misses by at most."""
    b = _pair()
    intr = {k: b[k] for k in ("albedo", "normal", "metallic")}
    anc = pf.anchors(b["image_a"], intr, b["mask"], b["ball_b"], None)
    relit = pf.compose_relit(anc, torch.zeros_like(b["image_a"]), torch.zeros_like(b["image_a"]))["relit"]
    m = b["mask"].expand_as(relit) > 0.5
    err, copy_err = (relit - b["image_b"]).abs()[m].mean(), (b["image_a"] - b["image_b"]).abs()[m].mean()
    assert err < 0.15 * b["image_b"][m].mean() and err < 0.25 * copy_err


def test_an_image_whose_light_cannot_be_estimated_keeps_the_conditioning_albedo():
    b = _pair()
    intr = {k: b[k] for k in ("albedo", "normal", "metallic")}
    intr["albedo"] = torch.zeros_like(intr["albedo"])  # no usable pixel: nothing to fit the light to
    intr["albedo"][1] = b["albedo"][1]
    anc = pf.anchors(b["image_a"], intr, b["mask"], b["ball_b"], None)
    torch.testing.assert_close(anc.albedo[0], intr["albedo"][0])
    assert not torch.equal(anc.albedo[1], intr["albedo"][1])


@pytest.mark.parametrize("bad", [{"decomposition": False}, {"relit_target": "residual", "relit_resolution": "full"}])
def test_physics_first_refuses_layouts_it_cannot_form(bad):
    with pytest.raises(ValueError, match="physics_first"):
        RelightParams.model_validate({**TINY, **bad})


def test_ggx_specular_anchor_adds_the_microfacet_highlight_of_the_target_light():
    """specular 'ggx': S_calc_b is the microfacet highlight of the target ball's light (an analytic ball
    is its own Lambertian twin), where the lookup says 0; an unknown kind is refused by name."""
    from pilight.physics.specular_model import specular_from_ball

    b = _pair()
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
