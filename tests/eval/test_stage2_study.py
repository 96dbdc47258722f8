"""benchmarks/stage2_study.py --score-pred: the test pairs scored again with stage-1 predictions as the
conditions. Predictions equal to the ground truth score what the ground truth scores; predictions with
mirrored normals score otherwise (the anchors read the normals; the albedo's level alone would cancel in
the effective-albedo form)."""

from __future__ import annotations

import pytest
import torch

from fixtures.script_modules import load_benchmark
from fixtures.stage_scripts import TINY_NETWORK, tiny_shards
from pilight.data.predictions import write_predictions
from pilight.data.shard_reader import intrinsics_dataset, make_loader
from pilight.params import DOMAINS, RelightParams
from pilight.relight.conditions import load_condition_predictions
from pilight.train.relight import RelightTask

study = load_benchmark("stage2_study")
# the default's form: gains on physics anchors (the study's gain_r2 reads them)
RELIGHT = {**TINY_NETWORK, "conditions": "gt", "form": {"kind": "physics_first"}}


def _predictions(shards, out, mirror_normals: bool):
    def items():
        for b in make_loader(intrinsics_dataset(shards, "test", shuffle=False), 4):
            for i, key in enumerate(b["key"]):
                maps = {d: b[d][i].numpy().transpose(1, 2, 0).copy() for d in DOMAINS}
                if mirror_normals:
                    maps["normal"][..., 0] *= -1.0
                yield key, maps, b["meta"][i]

    write_predictions(out, {"test": items()}, {"domains": list(DOMAINS)})
    return load_condition_predictions(shards, out, "test", "test_stage2_study")


def test_scoring_with_predictions_conditions_on_them(tmp_path):
    shards = tiny_shards(tmp_path)
    torch.manual_seed(0)
    task = RelightTask(RelightParams.model_validate(RELIGHT), shards, seed=0)
    task.stack.model.eval()
    same_preds = _predictions(shards, tmp_path / "same", mirror_normals=False)
    mirrored_preds = _predictions(shards, tmp_path / "mirror", mirror_normals=True)

    def score(preds):  # the sampler draws its starting noise from torch's global generator
        torch.manual_seed(1)
        return study.score(task, shards, preds=preds)

    truth, same, mirrored = score(None), score(same_preds), score(mirrored_preds)
    for k in ("model_rel_change_r2_mask", "anchor_rel_change_r2_mask", "model_abs_psnr", "gain_r2"):
        assert same[k] == pytest.approx(truth[k], rel=1e-5, abs=1e-6), k
    assert mirrored["anchor_rel_change_r2_mask"] != pytest.approx(truth["anchor_rel_change_r2_mask"], abs=1e-3)
    assert "model_rel_change_r2_pair_median" in truth
