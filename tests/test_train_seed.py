"""base.train_seed: the seed of every stage after the shards (null = base.seed), while render and shard
keep base.seed, so a training seed can vary on the same renders and shards (pilight/seeds.py)."""

from __future__ import annotations

import shutil
from pathlib import Path
from types import SimpleNamespace

import pytest
import yaml

from fixtures.script_modules import load_stage
from fixtures.stage_scripts import REPO, params_file
from pilight.params import BaseParams, load_section
from pilight.train.run_identity import run_identity

AFTER_SHARDS = {"train_intrinsics", "infer_intrinsics", "train_relight", "relight", "trade"}


def test_null_train_seed_is_the_base_seed():
    assert BaseParams(seed=42).training_seed == 42
    assert BaseParams(seed=42, train_seed=None).training_seed == 42
    assert BaseParams(seed=42, train_seed=7).training_seed == 7
    assert BaseParams(seed=42, train_seed=0).training_seed == 0  # 0 is a seed, not "unset"
    assert load_section("base", REPO / "params.yaml").train_seed is None  # today's outputs stay as they were


class Seen(Exception):
    """Raised by a stub once the stage has handed over its seeds."""


def _stage(name: str):
    return load_stage(name)


def _stub_task(seen: list | None, factor: int = 4):
    """A stand-in for a training Task (records the seed it is given) or, with ``seen`` None, for an
    inference model (pilight.models: built from the params alone, no seed)."""

    def make(p, shards=None, seed=None, **kw):
        if seen is not None:
            seen.append(("task", seed))
        model = SimpleNamespace(eval=lambda: None)
        stack = SimpleNamespace(model=model, describe=lambda: {}, codec=SimpleNamespace(factor=factor))
        return SimpleNamespace(stack=stack, describe=lambda: {})

    return make


def _seeds_of(stage: str, params: Path, monkeypatch) -> list:
    """The seeds ``stage`` hands to its task, its run identity, sampling and sweeps, with the heavy parts
    stubbed (stages/<stage>.py runs in-process up to the point its seeds are used)."""
    import pilight.base_model as base_model
    import pilight.data.shard_reader as shards
    import pilight.eval.predict_intrinsics as predict
    import pilight.eval.relit_pairs as relit_pairs
    import pilight.eval.trade as trade
    import pilight.models.folder as folder
    import pilight.models.intrinsics as intrinsics_model
    import pilight.models.relight as relight_model
    import pilight.models.stack as stack
    import pilight.relight.conditions as conditions
    import pilight.train.intrinsics as intrinsics
    import pilight.train.relight as relight
    import pilight.train.stage as train_stage

    seen: list = []
    monkeypatch.setattr(intrinsics, "IntrinsicsTask", _stub_task(seen))
    monkeypatch.setattr(relight, "RelightTask", _stub_task(seen))
    monkeypatch.setattr(intrinsics_model, "IntrinsicsModel", _stub_task(None))
    monkeypatch.setattr(relight_model, "RelightModel", _stub_task(None))
    monkeypatch.setattr(folder, "load_model", lambda *a, **k: None)
    monkeypatch.setattr(base_model, "check_saved_params", lambda *a, **k: None)  # reads the model's config.json
    monkeypatch.setattr(stack, "check_image_size", lambda *a, **k: None)
    monkeypatch.setattr(
        shards, "read_index", lambda d: {"splits": {"test": {"shards": ["x"]}}, "sizes": {"image": [16, 16]}}
    )
    monkeypatch.setattr(conditions, "optional_predictions", lambda *a, **k: None)

    def training(name, section, base, p, make_task, **kw):  # what run_training_stage seeds with
        seen.append(("identity", run_identity(base.seed, section, {}, [])["seed"]))
        make_task()
        raise Seen

    def record(position):
        def f(*args, **kw):
            seen.append((position, args[position]))
            raise Seen

        return f

    monkeypatch.setattr(train_stage, "run_training_stage", training)
    monkeypatch.setattr(predict, "predict_intrinsics_splits", record(5))
    monkeypatch.setattr(relit_pairs, "relight_split", record(5))
    monkeypatch.setattr(trade, "sweep_samples", lambda *a: (None, None, None))
    monkeypatch.setattr(trade, "sweep_both", lambda *a: seen.append(("sweep", a[8])) or ([], []))
    monkeypatch.setattr(trade, "lights_grid", record(4))
    with pytest.raises(Seen):
        _stage(stage).main(["--params", str(params)])
    return seen


@pytest.mark.parametrize("stage", sorted(AFTER_SHARDS))
@pytest.mark.parametrize("train_seed, expected", [(None, 42), (7, 7)])
def test_stages_after_the_shards_seed_from_train_seed(stage, train_seed, expected, tmp_path, monkeypatch):
    params = params_file(tmp_path, {"base": {"seed": 42, "train_seed": train_seed}})
    seen = _seeds_of(stage, params, monkeypatch)
    assert seen and all(seed == expected for _, seed in seen), seen
    if stage.startswith("train_"):
        assert ("identity", expected) in seen  # the checkpoints' run identity follows the training seed


def test_a_stage_s_own_train_seed_pins_that_stage_alone():
    """The shipped base's stage 2 was retrained with seed 1002 on its stage 1 of seed 1000: one stage's
    train.seed overrides base.train_seed for that stage, and null leaves it to base.train_seed."""
    from pilight.params import TrainParams

    base = BaseParams(seed=1000, train_seed=None)
    assert base.stage_training_seed(TrainParams(seed=1002)) == 1002
    assert base.stage_training_seed(TrainParams()) == 1000
    assert BaseParams(seed=42, train_seed=7).stage_training_seed(TrainParams(seed=0)) == 0  # 0 is a seed


@pytest.mark.parametrize("stage, expected", [("train_relight", 1002), ("train_intrinsics", 7), ("relight", 7)])
def test_relight_train_seed_seeds_stage_2s_training_and_nothing_else(stage, expected, tmp_path, monkeypatch):
    params = params_file(tmp_path, {"base": {"seed": 42, "train_seed": 7}, "relight": {"train": {"seed": 1002}}})
    seen = _seeds_of(stage, params, monkeypatch)
    assert seen and all(seed == expected for _, seed in seen), seen
    if stage.startswith("train_"):
        assert ("identity", expected) in seen


def _param_values(project: Path) -> dict[str, dict]:
    """Each stage's params deps as DVC reads them from the project's params.yaml."""
    from dvc.dependency.param import ParamsDependency
    from dvc.repo import Repo

    with Repo(str(project)) as repo:
        return {
            s.name: {k: v for d in s.deps if isinstance(d, ParamsDependency) for k, v in d.read_params().items()}
            for s in repo.index.stages
        }


def test_train_seed_changes_the_stages_after_the_shards_not_render_or_shard(tmp_path):
    from dvc.repo import Repo

    shutil.copy(REPO / "dvc.yaml", tmp_path / "dvc.yaml")
    Repo.init(str(tmp_path), no_scm=True).close()
    params = yaml.safe_load((REPO / "params.yaml").read_text())
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(params))
    before = _param_values(tmp_path)
    params["base"]["train_seed"] = 7
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(params))
    after = _param_values(tmp_path)
    changed = {s for s in before if before[s] != after[s]}
    assert changed == AFTER_SHARDS, changed  # render, shard, render_trade and evaluate keep their identity
    assert all(after[s]["base.train_seed"] == 7 for s in AFTER_SHARDS)
