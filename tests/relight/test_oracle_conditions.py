"""The oracle's condition settings (benchmarks/oracle_relight.py --per-map): which map comes from
stage 1, and the albedo rescaled to the ground truth's level, so the README's attribution of the
stage-1 gap to each map measures what it says."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from pilight.params import DOMAINS
from pilight.relight.conditions import oracle_conditions

CHANNELS = {"albedo": 3, "normal": 3, "roughness": 1, "metallic": 1}


@pytest.fixture
def batch_and_preds():
    g = torch.Generator().manual_seed(0)
    b = {d: torch.rand(2, c, 8, 8, generator=g) for d, c in CHANNELS.items()}
    b["mask"] = torch.zeros(2, 1, 8, 8)
    b["mask"][..., 2:6, 2:6] = 1.0
    b["meta_a"] = [json.dumps({"scene": f"s{i}", "view": 0, "light": 0}) for i in range(2)]
    keys = ["s0_v00_l00", "s1_v00_l00"]
    preds = {
        k: {d: np.random.default_rng(i).random((8, 8, c), np.float32) for d, c in CHANNELS.items()}
        for i, k in enumerate(keys)
    }
    return b, preds


def _pred(preds, d):
    return torch.stack([torch.from_numpy(preds[k][d]).permute(2, 0, 1) for k in ("s0_v00_l00", "s1_v00_l00")])


@pytest.mark.parametrize("one", DOMAINS)
def test_one_map_from_stage_one_the_rest_ground_truth(batch_and_preds, one):
    b, preds = batch_and_preds
    c = oracle_conditions(b, preds, only=one)
    for d in DOMAINS:
        torch.testing.assert_close(c[d], _pred(preds, d) if d == one else b[d])


def test_albedo_at_ground_truth_level_keeps_the_pattern_and_takes_the_level(batch_and_preds):
    b, preds = batch_and_preds
    inside = b["mask"] > 0.5
    for only, others_from_pred in (("albedo", False), (None, True)):
        c = oracle_conditions(b, preds, only=only, at_gt_level=True)
        mean = lambda x: (x * inside).sum((2, 3)) / inside.sum((2, 3))
        torch.testing.assert_close(mean(c["albedo"]), mean(b["albedo"]))
        ratio = c["albedo"] / _pred(preds, "albedo")  # one factor per image and channel
        torch.testing.assert_close(ratio, ratio[..., :1, :1].expand_as(ratio))
        torch.testing.assert_close(c["normal"], _pred(preds, "normal") if others_from_pred else b["normal"])


def test_gt_and_pred_settings(batch_and_preds):
    b, preds = batch_and_preds
    gt, pred = oracle_conditions(b, None), oracle_conditions(b, preds)
    for d in DOMAINS:
        torch.testing.assert_close(gt[d], b[d])
        torch.testing.assert_close(pred[d], _pred(preds, d))
