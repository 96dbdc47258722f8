"""benchmarks/branch_level_predictors.py: a predicted level moves a branch's gains there and keeps their
shape, its scoring is stage2_branch_errors's "model + level" mix when the D level is the truth's (and the
truth's own score when both branches' levels are all the model misses), the fits never see the scene they
predict, and the UNet probe pools the blocks it names."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from fixtures.relight_pairs import ONE_STEP, physics_pair, tiny_relight_task
from fixtures.script_modules import load_benchmark
from pilight.relight import physics_first as pf

levels = load_benchmark("branch_level_predictors")
branch_errors = load_benchmark("stage2_branch_errors")


def setup():
    b = physics_pair()
    intr = {k: b[k] for k in ("albedo", "normal", "roughness", "metallic")}
    anc = pf.anchors(b["image_a"], intr, b["mask"], b["ball_b"], None, ball_a=b["ball_a"])
    gen = torch.Generator().manual_seed(1)
    true_g, model_g = (0.3 * torch.randn(2, 3, 3, *b["image_a"].shape[-2:], generator=gen) for _ in range(2))
    return b, anc, true_g, model_g


def test_moved_to_level_sets_the_masked_mean_and_keeps_the_shape():
    b, _, _, g = setup()
    g, mask = g[:, 1], b["mask"]
    target = torch.tensor([0.7, -0.2])
    moved = levels.moved_to_level(g, mask, target)
    m = (mask > 0.5).float().expand_as(g)
    mean = (moved * m).flatten(1).sum(1) / m.flatten(1).sum(1)
    torch.testing.assert_close(mean, target)
    shift = moved - g  # one number per image
    torch.testing.assert_close(shift, shift[:, :1, :1, :1].expand_as(shift))


def test_the_true_level_scores_as_the_branch_errors_model_plus_level_mix():
    """Two codes, one number: the benchmark's scoring with the true gains' level equals
    stage2_branch_errors's "D model + level, S model" change_r2, and its own level the model's."""
    b, anc, true_g, model_g = setup()
    change = {}
    branch_errors.mixed_errors(anc, true_g, model_g, b["image_b"], b["mask"], b["image_a"], change)
    kept = [{"anchors": anc, "g_d": model_g[:, 1], "g_s": model_g[:, 2], "mask": b["mask"]}]
    kept[0] |= {"image_a": b["image_a"], "image_b": b["image_b"]}
    true_level = branch_errors.level_per_image(true_g[:, 1], b["mask"])[:, 0, 0, 0].numpy()
    own_level = branch_errors.level_per_image(model_g[:, 1], b["mask"])[:, 0, 0, 0].numpy()
    assert levels.change_r2_at(kept, true_level) == pytest.approx(change["D model + level, S model"].compute()["mask"])
    assert levels.change_r2_at(kept, own_level) == pytest.approx(change["D model, S model"].compute()["mask"])
    assert levels.change_r2_at(kept, None) == pytest.approx(change["D model, S model"].compute()["mask"])


def test_gains_off_only_by_a_level_per_branch_score_the_truth_when_both_are_moved():
    b, anc, true_g, _ = setup()
    offset = torch.tensor([0.4, -0.3]).view(2, 1, 1, 1)
    model_g = true_g + offset[:, None]  # every branch's gains off by one number per image
    change = {}
    branch_errors.mixed_errors(anc, true_g, model_g, b["image_b"], b["mask"], b["image_a"], change)
    kept = [{"anchors": anc, "g_d": model_g[:, 1], "g_s": model_g[:, 2], "mask": b["mask"]}]
    kept[0] |= {"image_a": b["image_a"], "image_b": b["image_b"]}
    true_levels = [branch_errors.level_per_image(true_g[:, i], b["mask"])[:, 0, 0, 0].numpy() for i in (1, 2)]
    truth = change["D truth, S truth"].compute()["mask"]
    assert levels.change_r2_at(kept, *true_levels) == pytest.approx(truth)
    assert levels.change_r2_at(kept, true_levels[0]) < truth - 1e-3  # S still off
    assert levels.change_r2_at(kept, None, true_levels[1]) < truth - 1e-3  # D still off


def test_scene_folds_hold_whole_scenes_and_refuse_too_few():
    scenes = [f"s{i % 7}" for i in range(40)]
    fold = levels.scene_folds(scenes, 3)
    for s in set(scenes):
        assert len({f for f, x in zip(fold, scenes) if x == s}) == 1
    assert set(fold) == {0, 1, 2}
    with pytest.raises(SystemExit, match="only 7 scenes"):
        levels.scene_folds(scenes, 8)


def test_ridge_recovers_a_linear_law():
    rng = np.random.default_rng(0)
    X = rng.normal(size=(200, 3))
    y = 0.5 + X @ np.array([1.0, -2.0, 0.25])
    np.testing.assert_allclose(levels.ridge(X, y, 1e-9)(X), y, atol=1e-6)


def test_cross_validation_never_predicts_a_scene_from_itself():
    """Levels that are a per-scene constant, and features that only name the scene: nothing carries over to an
    unseen scene, so cross-validated predictions explain nothing (a fit that saw the scene explains all)."""
    rng = np.random.default_rng(0)
    scenes = [f"s{i % 12}" for i in range(96)]
    per_scene = {s: rng.normal() for s in set(scenes)}
    y = np.array([per_scene[s] for s in scenes])
    onehot = np.array([[s == f"s{j}" for j in range(12)] for s in scenes], dtype=float)
    scored = {"true S": y, "model S": np.zeros_like(y), "features": onehot, "probe": onehot, "scene": scenes}
    cv = levels.predict_levels(scored, None, 4, 1e-6, "S")
    assert levels.r2(cv["physics features"], y) < 0.0
    seen = levels.predict_levels(scored, scored, 4, 1e-6, "S")
    assert levels.r2(seen["physics features"], y) == pytest.approx(1.0, abs=1e-4)
    assert cv["truth"] is y


def test_unet_probe_pools_each_probed_block_per_item(tmp_path):
    task = tiny_relight_task(tmp_path)
    unet = task.stack.model.unet
    probe = levels.UNetProbe(unet)
    with pytest.raises(RuntimeError, match="no output captured"):
        probe.pooled(2, task.V)
    task.predict(physics_pair(), ONE_STEP)
    pooled = probe.pooled(2, task.V)
    channels = unet.config.block_out_channels[-1]  # the mid block's and the last down block's width
    assert pooled.shape == (2, len(levels.PROBED) * 2 * task.V * channels)
    assert torch.isfinite(pooled).all()
    probe.remove()
    assert not unet.mid_block._forward_hooks


def test_a_fit_set_fits_and_the_scored_set_is_only_predicted():
    """With a fit set, the regression follows the fit set's law, not the scored pairs' own."""
    rng = np.random.default_rng(1)
    x_fit, x_scored = rng.normal(size=(60, 1)), rng.normal(size=(30, 1))
    pairs = lambda x, y: {
        "true D": y,
        "model D": x[:, 0],
        "features": x,
        "probe": x,
        "scene": [f"s{i}" for i in range(len(y))],
    }
    fit, scored = pairs(x_fit, 2.0 * x_fit[:, 0]), pairs(x_scored, -1.0 * x_scored[:, 0])
    p = levels.predict_levels(scored, fit, 3, 1e-9, "D")
    np.testing.assert_allclose(p["physics features"], 2.0 * x_scored[:, 0], atol=1e-6)
    np.testing.assert_allclose(p["calibrated"], 2.0 * x_scored[:, 0], atol=1e-6)
    assert p["train mean"] == pytest.approx(np.full(30, fit["true D"].mean()))
