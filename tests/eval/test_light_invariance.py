"""Albedo light-invariance against values computed by hand: the truth scores the clamp value."""

from __future__ import annotations

import math

import pytest
import torch

from pilight.eval.light_invariance import light_invariance, same_view_pairs
from pilight.eval.metrics import PSNR_CAP


def _metas(views_lights):
    return [{"scene": s, "view": v, "light": light} for s, v, light in views_lights]


def test_pairs_are_the_lightings_of_one_view():
    metas = _metas([("a", 0, 2), ("a", 0, 0), ("a", 1, 0), ("b", 0, 0), ("a", 0, 1), ("b", 0, 3)])
    # view (a, 0) under lights 0, 1, 2: three pairs, lower light first; (a, 1) alone: none; (b, 0): one
    assert sorted(same_view_pairs(metas)) == sorted([(1, 4), (1, 0), (4, 0), (3, 5)])


def test_the_truth_scores_the_clamp_value():
    g = torch.Generator().manual_seed(0)
    view_albedo = torch.rand(2, 3, 16, 16, generator=g)
    albedo = view_albedo[[0, 0, 1, 1]]  # the truth: one albedo per view, whatever the light
    mask = (torch.rand(2, 1, 16, 16, generator=g) > 0.3).float()[[0, 0, 1, 1]]
    metas = _metas([("s", 0, 0), ("s", 0, 1), ("s", 1, 0), ("s", 1, 1)])
    assert light_invariance(albedo, mask, metas) == {"psnr": PSNR_CAP, "si_psnr": PSNR_CAP, "pairs": 2}


def test_an_albedo_whose_level_follows_the_light_loses_raw_psnr_not_si_psnr():
    albedo = torch.full((2, 3, 8, 8), 0.4)
    albedo[1] = 0.2  # the second lighting's albedo is half the first's: every pixel off by 0.2
    mask = torch.ones(2, 1, 8, 8)
    out = light_invariance(albedo, mask, _metas([("s", 0, 0), ("s", 0, 1)]))
    assert out["psnr"] == pytest.approx(10 * math.log10(1 / 0.2**2), abs=1e-6)  # 13.98 dB
    assert out["si_psnr"] == PSNR_CAP and out["pairs"] == 1


def test_no_view_under_two_lights_gives_no_number():
    out = light_invariance(torch.rand(2, 3, 8, 8), torch.ones(2, 1, 8, 8), _metas([("s", 0, 0), ("s", 1, 0)]))
    assert out == {"psnr": None, "si_psnr": None, "pairs": 0}
