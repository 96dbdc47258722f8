"""base/shipped scores the shipped weights on the base's two test splits without the base's training data: its
params are the splits' own with fewer training scenes, so its test scenes must be exactly the base's, and it
is a DVC project of its own that neither the root's nor base/'s `dvc repro` collects."""

from __future__ import annotations

from pathlib import Path

import pytest

from pilight.params import RenderParams, read_params
from pilight.profiles import compose
from pilight.render.spec import scene_spec

REPO = Path(__file__).resolve().parents[1]
SHIPPED = REPO / "base" / "shipped"
# each scoring split: (its params here, the params of the split it must reproduce)
SPLITS = {"test": "base/params.yaml", "heldout": "base/heldout.yaml"}


@pytest.mark.parametrize("split", SPLITS)
def test_the_scoring_params_are_the_profile_composed_on_the_splits_own(split):
    overlay = read_params(SHIPPED / "scoring_profile.yaml")
    assert compose(read_params(REPO / SPLITS[split]), overlay) == read_params(SHIPPED / f"{split}.yaml")


@pytest.mark.parametrize("split", SPLITS)
def test_its_test_scenes_are_the_splits_own(split):
    mine, theirs = (read_params(p) for p in (SHIPPED / f"{split}.yaml", REPO / SPLITS[split]))
    assert mine["base"]["seed"] == theirs["base"]["seed"]
    r_mine, r_theirs = (RenderParams.model_validate(p["render"]) for p in (mine, theirs))
    assert r_mine.scenes.test == r_theirs.scenes.test > 0
    seed = mine["base"]["seed"]
    for i in range(r_mine.scenes.test):
        assert scene_spec(r_mine, seed, "test", i) == scene_spec(r_theirs, seed, "test", i), f"test scene {i}"


def test_it_scores_the_shipped_weights_and_no_dvc_repro_elsewhere_collects_it():
    from dvc.repo import Repo

    with Repo(str(SHIPPED)) as repo:
        stages = list(repo.index.stages)
    deps = {str(d.def_path) for s in stages for d in s.deps}
    assert {"../../weights/pilight-base/intrinsics", "../../weights/pilight-base/relight"} <= deps
    assert {s.name for s in stages} >= {"evaluate@test", "evaluate@heldout"}
    for project in (REPO, REPO / "base"):
        with Repo(str(project)) as repo:
            paths = {stage.path for stage in repo.index.stages}
        assert paths and all(not p.startswith(str(SHIPPED)) for p in paths), (project, paths)


def _stages(dvc_yaml: Path) -> dict:
    import yaml

    return yaml.safe_load(dvc_yaml.read_text(encoding="utf-8"))["stages"]


def _keys(params: list) -> set[str]:
    """dvc.yaml params entries (a key, or {file: [keys]}) -> the keys."""
    return {k for p in params for k in ([p] if isinstance(p, str) else next(iter(p.values())))}


def _covered(name: str, by: set[str], sep: str) -> bool:
    """``name`` is one of ``by`` or lies under one: a file in a declared folder (sep "/"), a key in a
    declared section (sep ".")."""
    return any(name == c or name.startswith(c + sep) for c in by)


@pytest.mark.parametrize("stage", ["render", "shard", "infer_intrinsics", "relight", "evaluate"])
def test_each_stage_reruns_on_what_the_roots_same_stage_reruns_on(stage):
    """The weights are fixed in git here, so a change to the code or a params key that the root's stage
    depends on must rerun this one too (the models and their shape-giving keys above all)."""
    root, mine = _stages(REPO / "dvc.yaml")[stage], _stages(SHIPPED / "dvc.yaml")[stage]["do"]
    code = [d for d in root["deps"] if d.startswith(("stages/", "pilight/"))]
    deps = {d.removeprefix("../../") for d in mine["deps"]}
    assert code and all(_covered(d, deps, "/") for d in code), [d for d in code if not _covered(d, deps, "/")]
    keys = _keys(mine["params"])
    for key in _keys(root.get("params", [])):
        assert _covered(key, keys, "."), f"{stage}: {key}"
