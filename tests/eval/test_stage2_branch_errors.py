"""benchmarks/stage2_branch_errors.py: mixing predicted and true gains. A model whose gains are the
truth's scores the truth's error, one whose gains are zero scores the anchor's, and the explained share
is 1 for perfect gains and 0 for the target's own mean."""

from __future__ import annotations

import pytest
import torch

from fixtures.relight_pairs import physics_pair
from fixtures.script_modules import load_benchmark
from pilight.relight import physics_first as pf

branch_errors = load_benchmark("stage2_branch_errors")


def setup():
    b = physics_pair()
    intr = {k: b[k] for k in ("albedo", "normal", "roughness", "metallic")}
    anc = pf.anchors(b["image_a"], intr, b["mask"], b["ball_b"], None, ball_a=b["ball_a"])
    true_g = 0.3 * torch.randn(2, 3, 3, *b["image_a"].shape[-2:], generator=torch.Generator().manual_seed(1))
    return b, anc, true_g


def test_perfect_gains_score_the_truth_and_zero_gains_the_anchor():
    b, anc, true_g = setup()
    perfect = branch_errors.mixed_errors(anc, true_g, true_g, b["image_b"], b["mask"])
    assert perfect["D model, S model"] == perfect["D truth, S truth"]
    assert perfect["D model, S truth"] == perfect["D truth, S truth"]
    none = branch_errors.mixed_errors(anc, true_g, torch.zeros_like(true_g), b["image_b"], b["mask"])
    assert none["D model, S model"] == none["D anchor, S anchor"]
    assert none["D model, S model"] != none["D truth, S truth"]


def test_explained_share_is_one_for_perfect_gains_and_zero_for_the_mean():
    b, _, true_g = setup()
    share = lambda g: {
        k: 1 - e / (s2 - s1 * s1 / w) for k, (e, s1, s2, w) in branch_errors.explained(true_g, g, b["mask"]).items()
    }
    assert all(v == pytest.approx(1.0) for v in share(true_g).values())
    m = (b["mask"][:, :1] > 0.5).float()
    diffuse_mean = (true_g[:, 1] * m).sum() / m.expand_as(true_g[:, 1]).sum()
    mean_g = true_g.clone()
    mean_g[:, 1] = diffuse_mean
    assert share(mean_g)["diffuse"] == pytest.approx(0.0, abs=1e-6)


def test_each_mix_gets_its_change_r2_and_perfect_gains_score_the_truths():
    """change_r2 per mix: the model's equals the truth's when its gains are the truth's, and the anchor's when
    they are zero; a gain the truth does not have lowers it."""
    b, anc, true_g = setup()
    scores = {}
    for name, g in (("perfect", true_g), ("zero", torch.zeros_like(true_g)), ("off", true_g + 0.5)):
        change = {}
        branch_errors.mixed_errors(anc, true_g, g, b["image_b"], b["mask"], b["image_a"], change)
        scores[name] = {k: c.compute()["mask"] for k, c in change.items()}
    assert scores["perfect"]["D model, S model"] == scores["perfect"]["D truth, S truth"]
    assert scores["zero"]["D model, S model"] == scores["zero"]["D anchor, S anchor"]
    # each branch reads its own source: the model's zero S beside the true D is the anchor's S, not the truth's
    assert scores["zero"]["D truth, S model"] == scores["zero"]["D truth, S anchor"]
    assert scores["zero"]["D truth, S model"] != scores["zero"]["D truth, S truth"]
    assert scores["off"]["D model, S model"] < scores["off"]["D truth, S truth"]


def test_the_specular_share_splits_by_metal():
    """The specular branch's share on metal and on dielectric pixels: the two parts' sums are the whole's."""
    b, _, true_g = setup()
    metallic = torch.zeros_like(b["mask"][:, :1])
    metallic[..., : metallic.shape[-1] // 2] = 1.0
    parts = branch_errors.explained(true_g, 0.5 * true_g, b["mask"], metallic)
    whole, metal, dielectric = parts["specular"], parts["specular, metal"], parts["specular, dielectric"]
    assert metal[3] > 0 and dielectric[3] > 0
    for i in range(4):
        assert metal[i] + dielectric[i] == pytest.approx(whole[i], rel=1e-5)


def test_the_level_mixes_take_the_true_gains_mean_per_image():
    """D from the true gains' level alone equals the truth where the truth is one level per image; the model's
    gains moved to the true level equal the truth when they differ from it by a constant."""
    b, anc, true_g = setup()
    flat = true_g.clone()
    flat[:, 1] = torch.tensor([0.2, -0.4]).view(2, 1, 1, 1)  # one diffuse level per image
    mixes = branch_errors.mixed_errors(anc, flat, flat + 0.3, b["image_b"], b["mask"])
    truth = mixes["D truth, S truth"][0]
    assert mixes["D level, S truth"][0] == pytest.approx(truth, rel=1e-5)
    assert mixes["D model + level, S truth"][0] == pytest.approx(truth, rel=1e-5)
    assert mixes["D model, S truth"][0] != pytest.approx(truth, rel=1e-3)
    shaped = branch_errors.mixed_errors(anc, true_g, true_g + 0.3, b["image_b"], b["mask"])
    truth = shaped["D truth, S truth"][0]
    assert shaped["D model + level, S truth"][0] == pytest.approx(truth, rel=1e-5)
    assert shaped["D level, S truth"][0] != pytest.approx(truth, rel=1e-3)


def test_pair_gains_are_what_inference_composes(tmp_path):
    """The benchmarks' model gains, composed into A_x D + S, are the relit image the model's own predict
    returns on the mask; the true gains are the training targets (zero where the pair is the identity)."""
    from fixtures.relight_pairs import ONE_STEP, tiny_relight_task
    from pilight.relight.intensity import relative_pair

    task = tiny_relight_task(tmp_path)
    b = relative_pair(physics_pair())
    intr = {k: b[k] for k in ("albedo", "normal", "roughness", "metallic")}
    torch.manual_seed(3)  # single-step sampling starts from noise drawn from the global generator
    _, anc, _, true_g, model_g = branch_errors.pair_gains(task, b, intr, "relative")
    assert model_g.shape == true_g.shape == (2, task.V, 3, *b["image_a"].shape[-2:])
    composed = pf.compose_relit(anc, model_g[:, 1], model_g[:, 2])["relit"]
    torch.manual_seed(3)
    predicted = task.predict(b, ONE_STEP, intr=intr, intensity="relative")["relit"]
    on = (b["mask"] > 0.5).expand_as(composed)
    torch.testing.assert_close(composed[on], predicted[on].float(), rtol=1e-4, atol=1e-5)
    assert not torch.allclose(true_g[:, 1], torch.zeros_like(true_g[:, 1]))
