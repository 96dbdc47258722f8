"""benchmarks/fit_level_prior.py: one (estimated, rendered) level per distinct input of the split's pairs,
the line fitted through their logs, and a clear refusal where there is nothing to fit."""

from __future__ import annotations

import json

import numpy as np
import pytest

from fixtures.script_modules import load_benchmark
from fixtures.stage_scripts import tiny_shards
from pilight.data.shard_reader import eval_dataset, make_loader
from pilight.relight.level_prior import fit_level_prior

fit_script = load_benchmark("fit_level_prior")


def _distinct_inputs(shards, split: str) -> int:
    keys = set()
    for b in make_loader(eval_dataset(shards, split, "relight"), 8):
        keys |= {tuple(json.loads(m)[k] for k in ("scene", "view", "light")) for m in b["meta_a"]}
    return len(keys)


def test_each_input_counts_once_and_the_printed_fit_is_the_library_fit(tmp_path, capsys):
    shards = tiny_shards(tmp_path)
    est, rendered, lost = fit_script.input_levels(shards, "train", None)
    assert len(est) + lost == _distinct_inputs(shards, "train")  # an input of several pairs counts once
    assert len(est) >= 3
    assert (est > 0).all() and (rendered > 0).all()
    out = tmp_path / "fit.json"
    assert fit_script.main(["--shards", str(shards), "--json", str(out)]) == 0
    fit = json.loads(out.read_text())
    want = fit_level_prior(est, rendered)
    assert fit["alpha"] == pytest.approx(want["alpha"]) and fit["beta"] == pytest.approx(want["beta"])
    assert fit["inputs"] == len(est) and fit["not_found"] == lost
    assert f"level_prior: {{alpha: {want['alpha']:.4f}, beta: {want['beta']:.4f}}}" in capsys.readouterr().out


def test_too_few_inputs_is_a_clear_exit(tmp_path, monkeypatch):
    shards = tiny_shards(tmp_path)
    monkeypatch.setattr(fit_script, "input_levels", lambda *a: (np.array([1.0, 2.0]), np.array([1.0, 2.0]), 0))
    with pytest.raises(SystemExit, match="shards.*at least 3"):
        fit_script.main(["--shards", str(shards)])
