"""The evaluate stage's metrics files: numbers only, and a headline of a few short-keyed figures."""

from __future__ import annotations

import json
import math

import pytest

from fixtures.fake_predictions import fake_relit, write_intrinsics_predictions, write_relit
from fixtures.stage_scripts import REPO, params_file, run_stage, tiny_shards
from pilight.eval.metrics_files import STAGE1, TIER_KEYS, headline, numbers_only


def test_numbers_only_drops_missing_figures_and_refuses_notes():
    tree = {"a": 1, "b": None, "c": {"d": 2.5, "e": None}, "f": {"g": None}}
    assert numbers_only(tree) == {"a": 1, "c": {"d": 2.5}}
    with pytest.raises(ValueError, match=r"metrics\.c\.note: str"):
        numbers_only({"c": {"note": "LPIPS needs weights"}})
    for bad in ([1, 2], True, math.nan, math.inf):
        with pytest.raises(ValueError):
            numbers_only({"x": bad})


def test_headline_takes_the_model_and_the_strongest_baseline_of_each_tier():
    intrinsics = {"model": {"albedo_psnr": 13.073862, "normal_mean_deg": 27.8182, "metallic_mae": None}}
    tier = {
        "model": {"psnr": 20.180835, "change_r2_mask": 0.313012},
        "copy_input": {"psnr": 19.357940, "change_r2_mask": 0.0},
        "anchor": {"psnr": 18.0, "change_r2_mask": 0.41},
        "anchor_gt": {"psnr": 30.0, "change_r2_mask": 0.9},  # an oracle: never "the strongest baseline"
    }
    h = headline(intrinsics, {"absolute": tier})
    assert h == {
        "albedo_db": 13.074,
        "normal_deg": 27.818,
        "abs_db": 20.181,
        "abs_base_db": 19.358,
        "abs_r2": 0.313,
        "abs_base_r2": 0.41,
    }
    assert len(STAGE1) + 4 * len(TIER_KEYS) == 19  # the whole headline


def test_the_stage_writes_numbers_only_and_a_headline_beside_them(tmp_path):
    shards = tiny_shards(tmp_path)
    write_intrinsics_predictions(shards, tmp_path / "pred")
    write_relit(shards, tmp_path / "relit", fake_relit)
    metrics = tmp_path / "m" / "evaluate_heldout.json"
    r = run_stage(
        "evaluate.py",
        *("--params", params_file(tmp_path, {}), "--shards", shards, "--pred", tmp_path / "pred"),
        *("--relit", tmp_path / "relit", "--metrics", metrics, "--reports", tmp_path / "reports"),
    )
    assert r.returncode == 0, r.stderr
    result = json.loads(metrics.read_text())
    assert numbers_only(result) == result
    assert {"absolute", "relative", "scale_invariant"} <= set(result["relight"])
    h = json.loads((tmp_path / "m" / "headline_heldout.json").read_text())  # named after its metrics file
    assert len(h) == 19 and h["albedo_db"] == h["albedo_inv"] == 100.0 and h["rel_db"] == 100.0
    assert max(len(k) for k in h) <= 11  # short keys: `dvc exp show` columns stay narrow
    relight_md = (tmp_path / "reports" / "relight.md").read_text()
    assert "evaluate.lpips_backbone" in relight_md and "Scale-invariant" in relight_md
    assert not (REPO / "metrics" / "headline_heldout.json").exists()
