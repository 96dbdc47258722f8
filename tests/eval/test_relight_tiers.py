"""The three relighting tiers against values computed by hand, on tiny shards with prediction folders
written by the real writer: the exposure-matched copy is copy x r, the scale-invariant tier forgives a
per-image scale fitted on the mask, the level error is the sd of the per-pair log scales."""

from __future__ import annotations

import json

import pytest
import torch

from fixtures.fake_predictions import LOG_SCALE, fake_relit, write_relit
from fixtures.stage_scripts import tiny_shards
from pilight.data.predictions import read_predictions, write_predictions
from pilight.data.schema import DataError
from pilight.data.shard_reader import eval_dataset, make_loader
from pilight.eval.metrics import PSNR_CAP
from pilight.eval.metrics_files import numbers_only
from pilight.eval.relight import evaluate_relight, relight_report
from pilight.eval.relight_tiers import (
    TIER_METHODS,
    MethodScores,
    Pairs,
    exposure_matched_copy,
    intensity_ratio,
    strongest_baseline,
    tier_image,
)
from pilight.physics.envmap import BALL_ALBEDO


@pytest.fixture(scope="module")
def shards(tmp_path_factory):
    return tiny_shards(tmp_path_factory.mktemp("tiers"))


def _uniform_ball(value: float, size: int = 8) -> torch.Tensor:
    return torch.full((1, 3, size, size), value)


def test_exposure_matched_copy_is_the_copy_times_r():
    # level = mean radiance over the disk / BALL_ALBEDO: uniform balls of 0.25, 0.75 and 0.125 have levels
    # 0.5, 1.5 and 0.25, so r is 3 for the first pair and 0.5 for the second
    ball_a = torch.cat([_uniform_ball(0.25), _uniform_ball(0.25)])
    ball_b = torch.cat([_uniform_ball(0.75), _uniform_ball(0.125)])
    assert BALL_ALBEDO == 0.5
    assert intensity_ratio(ball_a, ball_b).flatten().tolist() == pytest.approx([3.0, 0.5])
    image = torch.rand(2, 3, 16, 16, generator=torch.Generator().manual_seed(0))
    want = image * torch.tensor([3.0, 0.5])[:, None, None, None]
    assert torch.allclose(exposure_matched_copy(image, ball_a, ball_b), want, rtol=1e-6)


def test_scale_invariant_tier_fits_on_the_mask_and_leaves_the_others_alone():
    g = torch.Generator().manual_seed(1)
    target = torch.rand(2, 3, 16, 16, generator=g) + 0.1
    mask = (torch.rand(2, 1, 16, 16, generator=g) > 0.5).float()
    pred = torch.where(mask > 0.5, 4 * target, 1e3 * torch.rand(target.shape, generator=g))
    on = (mask > 0.5).expand_as(target)
    assert torch.allclose(tier_image("scale_invariant", pred, target, mask)[on], target[on], atol=1e-5)
    assert tier_image("absolute", pred, target, mask) is pred and tier_image("relative", pred, target, mask) is pred


def test_copy_scores_zero_change_and_the_truth_one():
    g = torch.Generator().manual_seed(2)
    a, b = torch.rand(4, 3, 16, 16, generator=g), torch.rand(4, 3, 16, 16, generator=g)
    mask, cross = torch.ones(4, 1, 16, 16), torch.tensor([True, True, True, False])
    copy, truth = MethodScores(), MethodScores()
    pairs = Pairs.of(a, b, mask, cross)
    copy.update(a, pairs)
    truth.update(b, pairs)
    c, t = copy.compute(), truth.compute()
    assert c["change_r2_mask"] == 0.0 and t["change_r2_mask"] == 1.0 and t["psnr"] == PSNR_CAP
    assert c["pairs"] == 3 and c["reconstruction_pairs"] == 1 and t["level_sd"] == 0.0


def test_strongest_baseline_is_a_baseline_never_an_oracle():
    figures = {"model": {"psnr": 20.0}, "copy_input": {"psnr": 19.0}, "anchor": {"psnr": 21.0}}
    figures |= {"anchor_gt": {"psnr": 30.0}, "analytic_ad": {"psnr": 40.0}}
    assert strongest_baseline(figures, "absolute", "psnr") == ("anchor", 21.0)
    kinds = {m.name: m.kind for ms in TIER_METHODS.values() for m in ms}
    assert kinds["exposure_matched_copy"] == "baseline" and kinds["model_gt"] == kinds["anchor_gt"] == "oracle"


def test_three_tiers_on_prediction_folders_known_by_construction(shards, tmp_path):
    relit = write_relit(shards, tmp_path / "relit", fake_relit)
    out = evaluate_relight(shards, relit, "test", grid_pairs=2)
    grid = out.pop("grid")
    assert grid.ndim == 3 and grid.dtype.name == "uint8"
    assert numbers_only(out) == out  # nothing but numbers, no None
    assert (out["pairs"], out["cross_light_pairs"], out["identity_pairs"]) == (8, 4, 4)
    ab, rel, si = out["absolute"], out["relative"], out["scale_invariant"]
    assert set(ab) == {"model", "model_gt", "anchor", "anchor_gt", "copy_input", "analytic_ad"}
    assert set(rel) == {"model", "model_gt", "anchor", "anchor_gt", "copy_input", "exposure_matched_copy"}
    # relative: the exact model; the anchor written as copy x r scores what the evaluation's own
    # exposure-matched copy scores (to the float16 EXRs' rounding)
    assert rel["model"]["psnr"] == PSNR_CAP and rel["model"]["change_r2_mask"] == 1.0
    for k in ("psnr", "ssim", "change_r2_mask", "level_sd"):
        assert rel["anchor"][k] == pytest.approx(rel["exposure_matched_copy"][k], rel=2e-3, abs=2e-3), k
    # absolute: the model off by exp(+-0.3) per pair: level sd 0.3 over the 4 cross-light pairs;
    # scale-invariant: the same images x s* are the target again (float16 rounding left), level sd ~0
    assert ab["model"]["level_sd"] == pytest.approx(LOG_SCALE, abs=2e-3) and ab["model"]["psnr"] < 40
    assert si["model"]["psnr"] > 60 and si["model"]["change_r2_mask"] > 0.999 and si["model"]["level_sd"] < 2e-3
    assert ab["copy_input"]["change_r2_mask"] == 0.0 and ab["copy_input"]["reconstruction_psnr"] == PSNR_CAP
    assert "reconstruction_psnr" not in ab["model_gt"]  # the `_gt` splits hold cross-light pairs only
    # the model's checks read its absolute split, written with the truth's D and S (its relit image is
    # exp(+-0.3) x the truth, so I - A D - S is not 0 for it; it is for the ground truth)
    assert out["components_psnr"]["diffuse"] > 60 and out["residual_abs_mean"]["ground_truth"] < 1e-2


def test_report_has_a_table_per_tier_and_says_its_space(shards, tmp_path):
    write_relit(shards, tmp_path / "relit", fake_relit)
    metrics, md, _ = relight_report(shards, tmp_path / "relit")
    assert md.count("| method | kind | PSNR") == 3 and "exposure-matched copy: input x r" in md
    assert "linear HDR on the mask" in md and "Strongest baseline" in md
    assert relight_report(shards, tmp_path / "absent") == ({}, None, None)


def test_only_the_model_splits_are_required(shards, tmp_path):
    write_relit(shards, tmp_path / "relit", fake_relit, splits=("", "_abs"))
    out = evaluate_relight(shards, tmp_path / "relit", "test")
    assert set(out["relative"]) == {"model", "copy_input", "exposure_matched_copy"}
    write_relit(shards, tmp_path / "old", fake_relit, splits=("", "_gt"))  # a folder from before relative intensity
    with pytest.raises(DataError, match="no `test_abs` split"):
        evaluate_relight(shards, tmp_path / "old", "test")


def test_a_split_short_of_a_cross_light_pair_is_an_error(shards, tmp_path):
    write_relit(shards, tmp_path / "short", fake_relit, cross_only=("_anchor",))  # identity pairs all absent: fine
    assert "reconstruction_psnr" not in evaluate_relight(shards, tmp_path / "short", "test")["relative"]["anchor"]
    relit = write_relit(shards, tmp_path / "relit", fake_relit)
    splits = {s: read_predictions(relit, s) for s in json.loads((relit / "index.json").read_text())["splits"]}
    keys = [k for b in make_loader(eval_dataset(shards, "test", "relight"), 8) for k in b["key"]]
    cross = next(k for k in keys if k.split("_to_")[0][-3:] != k.split("_to_")[1])  # ..._l00_to_l01
    del splits["test_anchor"][cross]
    write_predictions(
        tmp_path / "damaged",
        {s: [(k, v, "{}") for k, v in preds.items()] for s, preds in splits.items()},
        {"sampling": {"split": "test"}},
    )
    with pytest.raises(DataError, match=f"no `test_anchor` prediction for cross-light pair.*{cross}"):
        evaluate_relight(shards, tmp_path / "damaged", "test")
    splits["test_anchor"] = read_predictions(relit, "test_anchor")
    identity = [k for k in keys if k.split("_to_")[0][-3:] == k.split("_to_")[1]]
    del splits["test_anchor"][identity[0]]  # some identity pairs but not all
    write_predictions(
        tmp_path / "partial",
        {s: [(k, v, "{}") for k, v in preds.items()] for s, preds in splits.items()},
        {"sampling": {"split": "test"}},
    )
    with pytest.raises(DataError, match="holds 3 of the 4 identity pairs"):
        evaluate_relight(shards, tmp_path / "partial", "test")
