"""Stage-1 grading on tiny shards with predictions known by construction: the truth scores the clamp
value and LMSE 0, light-invariance sees a level that follows the light, the training median is exact."""

from __future__ import annotations

import json

import pytest
import torch

from fixtures.fake_predictions import write_intrinsics_predictions
from fixtures.stage_scripts import tiny_shards
from pilight.data.shard_reader import intrinsics_dataset, make_loader
from pilight.eval.intrinsics import MEDIAN_BINS, evaluate_intrinsics, median_from_counts, train_constants
from pilight.eval.metrics import PSNR_CAP


@pytest.fixture(scope="module")
def shards(tmp_path_factory):
    return tiny_shards(tmp_path_factory.mktemp("intrinsics"))


def test_median_from_counts_is_numpys_median():
    for values in ([0, 0, 0, 1], [0.25, 0.5, 1.0], [0.0, 0.0, 1.0, 1.0], [0.75]):
        bins = (torch.tensor(values) * (MEDIAN_BINS - 1)).round().long()
        counts = torch.bincount(bins, minlength=MEDIAN_BINS)
        assert median_from_counts(counts) == pytest.approx(float(torch.tensor(values).double().quantile(0.5)))


def test_train_constants_are_the_mean_and_median_of_masked_training_pixels(shards):
    pixels = {"roughness": [], "metallic": []}
    for b in make_loader(intrinsics_dataset(shards, "train", shuffle=False), 8):
        m = b["mask"] > 0.5
        for k in pixels:
            pixels[k].append(b[k][m].double())
    c = train_constants(shards)
    for k, v in pixels.items():
        v = torch.cat(v)
        assert c["mean"][k] == pytest.approx(float(v.mean()), rel=1e-9)
        assert c["median"][k] == pytest.approx(float(v.quantile(0.5)), abs=1 / (MEDIAN_BINS - 1))


def test_the_truth_scores_the_clamp_value_and_lmse_zero(shards, tmp_path):
    out = evaluate_intrinsics(shards, write_intrinsics_predictions(shards, tmp_path / "pred"))
    m = out["model"]
    assert m["albedo_psnr"] == m["albedo_si_psnr"] == PSNR_CAP and m["albedo_lmse"] == 0.0
    assert m["albedo_light_invariance_psnr"] == m["albedo_light_invariance_si_psnr"] == PSNR_CAP
    assert out["light_invariance_pairs"] == 2  # two test views, two lights each
    base = out["baselines"]
    assert set(base) == {"input_image", "facing_camera", "train_mean", "train_median"}
    assert base["input_image"]["albedo_si_psnr"] >= base["input_image"]["albedo_psnr"]
    assert base["input_image"]["albedo_light_invariance_psnr"] < PSNR_CAP  # the image follows the light


def test_an_albedo_whose_level_follows_the_light(shards, tmp_path):
    """Light 1's albedo at half the truth: si-PSNR and LMSE forgive it, raw PSNR and light-invariance do not."""
    half = lambda b, i: b["albedo"][i] * (0.5 if json.loads(b["meta"][i])["light"] == 1 else 1.0)
    out = evaluate_intrinsics(shards, write_intrinsics_predictions(shards, tmp_path / "pred", albedo=half))
    m = out["model"]
    assert m["albedo_psnr"] < 30 and m["albedo_light_invariance_psnr"] < 30
    assert m["albedo_si_psnr"] > 60 and m["albedo_light_invariance_si_psnr"] > 60 and m["albedo_lmse"] < 1e-5
