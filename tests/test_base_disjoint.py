"""The shipped base never sees the embedded default's test scenes or held-out HDRIs, and its held-out split's
shapes and textures are ones it never trained on; its params build the default's networks."""

from __future__ import annotations

import json
from pathlib import Path

from pilight.base_model import mismatches
from pilight.params import RenderParams, read_params
from pilight.profiles import compose
from pilight.render.spec import scene_spec

REPO = Path(__file__).resolve().parents[1]
DEFAULT, BASE, HELDOUT = (read_params(REPO / f) for f in ("params.yaml", "base/params.yaml", "base/heldout.yaml"))


def _render(p: dict) -> RenderParams:
    return RenderParams.model_validate(p["render"])


def test_base_params_are_the_profiles_composed():
    assert compose(DEFAULT, read_params(REPO / "base/profile.yaml")) == BASE
    assert compose(BASE, read_params(REPO / "base/heldout_profile.yaml")) == HELDOUT
    assert compose(BASE, read_params(REPO / "base/tune_profile.yaml")) == read_params(REPO / "base/tune.yaml")


def test_the_tune_builds_the_recipes_network_and_goes_on_from_it():
    """base/tune.yaml (a measured tune, run by hand) loads the recipe's models/intrinsics by `unet.init: base`,
    which refuses another network; and it sees the base's scenes, not new ones."""
    tune = read_params(REPO / "base/tune.yaml")
    assert tune["intrinsics"]["unet"] | {"init": "scratch", "path": None} == BASE["intrinsics"]["unet"]
    assert (tune["intrinsics"]["unet"]["init"], tune["intrinsics"]["unet"]["path"]) == ("base", "models")
    assert mismatches("intrinsics", tune["intrinsics"], BASE["intrinsics"]) == []
    assert tune["base"]["seed"] == BASE["base"]["seed"] and tune["render"] == BASE["render"]


def test_seeds_differ_so_no_scene_is_shared():
    seeds = [p["base"]["seed"] for p in (DEFAULT, BASE, HELDOUT)]
    assert len(set(seeds)) == 3
    # and, drawn, no scene of the default's test split is among the base's (its objects and materials)
    content = lambda s: json.dumps([s["objects"], s["backdrop"], s["views"]], sort_keys=True)
    r_def, r_base = _render(DEFAULT), _render(BASE)
    test = {content(scene_spec(r_def, seeds[0], "test", i)) for i in range(r_def.scenes.test)}
    base = {content(scene_spec(r_base, seeds[1], s, i)) for s in ("train", "test") for i in range(60)}
    assert not test & base


def test_no_held_out_hdri_of_the_default_reaches_the_base():
    held = set(_render(DEFAULT).hdri.test_holdout)
    for p in (BASE, HELDOUT):
        assert not held & set(_render(p).hdri.names)


def test_the_held_out_split_has_shapes_and_textures_the_base_never_saw():
    base, held = _render(BASE).scene, _render(HELDOUT).scene
    assert held.shapes and held.textures
    assert not set(held.shapes) & set(base.shapes)
    assert not set(held.textures) & set(base.textures)


def test_the_base_builds_the_defaults_networks():
    for stage in ("intrinsics", "relight"):
        assert mismatches(stage, DEFAULT[stage], BASE[stage]) == []


def test_the_defaults_dvc_repro_never_collects_the_base_pipeline():
    """base/ is a DVC project of its own: the root's `dvc repro` (the README's first command) must not
    run the base's stages, whose data (hours of renders) a fresh clone does not have."""
    from dvc.repo import Repo

    assert (REPO / "base" / ".dvc" / "config").is_file()
    with Repo(str(REPO)) as root:
        paths = {stage.path for stage in root.index.stages}
    assert paths and all(not p.startswith(str(REPO / "base")) for p in paths), paths


def test_the_recipe_is_what_made_the_shipped_base():
    """base/dvc.yaml states how weights/pilight-base was made: its stages are the ones base/dvc.lock recorded,
    with the same commands (a stage the shipped weights have not been through does not belong in it)."""
    import yaml

    stages = yaml.safe_load((REPO / "base/dvc.yaml").read_text(encoding="utf-8"))["stages"]
    locked = yaml.safe_load((REPO / "base/dvc.lock").read_text(encoding="utf-8"))["stages"]
    assert set(stages) == set(locked)
    squash = lambda cmd: " ".join(cmd.split())
    assert {k: squash(v["cmd"]) for k, v in stages.items()} == {k: squash(v["cmd"]) for k, v in locked.items()}
