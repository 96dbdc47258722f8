"""The model card says what the base saw: the scene mix (a close-up share decides whether stage 1 reads a
portrait as a floor; docs/base-model.md), the data's sizes and its figures, all from the params and metrics
the export stage passes in (pilight/eval/model_card.py)."""

from __future__ import annotations

import pytest

from fixtures.script_modules import load_stage
from fixtures.stage_scripts import params_file
from fixtures.tiny_models import REPO
from pilight.eval.model_card import model_card
from pilight.params import load_section


def _card(path, training=None):
    sections = {
        name: load_section(name, path, check_paths=False) for name in ("base", "render", "intrinsics", "relight")
    }
    metrics = {"headline": {"normal_deg": 23.5}, "headline_heldout": {"normal_deg": 25.0}}
    return model_card(**sections, metrics=metrics, training=training or {}, weights_bytes=27 * 2**20)


def test_the_card_states_the_base_scene_mix_and_its_figures():
    card = _card(REPO / "base" / "params.yaml")
    render = load_section("render", REPO / "base" / "params.yaml", check_paths=False)
    sc = render.scene
    objects = 1 - sc.room_fraction - sc.closeup_fraction
    assert f"{sc.room_fraction:.0%} rooms, {sc.closeup_fraction:.0%} close-ups" in card
    assert f"{objects:.0%} objects on a ground plane" in card
    assert f"{render.scenes.train} training scenes" in card
    assert "| normal_deg | 23.500 | 25.000 |" in card


def test_the_default_params_card_has_no_close_ups():
    card = _card(REPO / "params.yaml")
    assert "0% close-ups" in card and "50% rooms" in card


def test_a_full_precision_stage_reads_fp32_not_accelerates_no():
    training = {"relight": {"steps": 2000, "mixed_precision": "no", "seconds": 733.0}}
    card = _card(REPO / "base" / "params.yaml", training)
    assert "fp32 precision" in card and "no precision" not in card


def test_a_stage_2_trained_with_a_light_level_prior_says_which(tmp_path):
    """Its weights relight at the prior's level, and params without the same prior are refused: the card
    names it, so a reader can set it."""
    plain = params_file(tmp_path, {"relight": {"level_prior": None}})
    assert "light-level prior" not in _card(plain)
    (tmp_path / "p").mkdir()
    with_prior = params_file(tmp_path / "p", {"relight": {"level_prior": {"alpha": -0.25, "beta": 0.44}}})
    line = next(x for x in _card(with_prior).splitlines() if x.startswith("- **relight**"))
    assert "light-level prior alpha -0.25, beta 0.44 (relight.level_prior)" in line


def test_a_retrained_stage_names_its_training_seed(tmp_path):
    """Two runs of one recipe differ by their seed alone (the twenty-first session trained seeds 1000 and
    1001 of the base's stage 2): the card says which, base.train_seed or, when null, base.seed."""
    line = lambda card: next(x for x in card.splitlines() if x.startswith("- **relight**"))
    assert ", seed 1001;" in line(_card(params_file(tmp_path, {"base": {"seed": 1000, "train_seed": 1001}})))
    (tmp_path / "n").mkdir()
    assert ", seed 1000;" in line(_card(params_file(tmp_path / "n", {"base": {"seed": 1000, "train_seed": None}})))


def test_a_stage_with_its_own_train_seed_names_that_seed(tmp_path):
    """The shipped base: stage 1 of base.seed 1000, stage 2 retrained with relight.train.seed 1002."""
    path = params_file(tmp_path, {"base": {"seed": 1000, "train_seed": None}, "relight": {"train": {"seed": 1002}}})
    card = _card(path)
    line = lambda stage: next(x for x in card.splitlines() if x.startswith(f"- **{stage}**"))
    assert ", seed 1002;" in line("relight") and ", seed 1000;" in line("intrinsics")


def test_a_stage_not_retrained_keeps_its_previous_training_line():
    kept = "- **intrinsics**: 6000 steps of 8, lr 0.0002 (cosine), bf16 precision; 0.58 h on a CPU (kept)"
    training = {"relight": {"steps": 10000, "mixed_precision": "bf16", "seconds": 3600.0}}
    sections = {
        name: load_section(name, REPO / "base" / "params.yaml", check_paths=False)
        for name in ("base", "render", "intrinsics", "relight")
    }
    card = model_card(**sections, metrics={}, training=training, weights_bytes=1, kept={"intrinsics": kept})
    lines = card.splitlines()
    assert kept in lines and sum(line.startswith("- **intrinsics**") for line in lines) == 1
    assert "- **relight**: 10000 steps of 2" in card and "1.00 h" in card


def test_the_export_takes_a_kept_line_from_the_previous_card(tmp_path):
    export = load_stage("export_model")
    card = tmp_path / "MODEL_CARD.md"
    card.write_text("## Training\n- **intrinsics**: 6000 steps of 8; 0.58 h\n- **relight**: 10000 steps\n")
    line = export._kept_line(card, "intrinsics")
    assert line == "- **intrinsics**: 6000 steps of 8; 0.58 h" + export.KEPT_NOTE
    card.write_text(f"{line}\n")
    assert export._kept_line(card, "intrinsics") == line  # kept twice, marked once
    from pilight.failure import CommandFailure

    with pytest.raises(CommandFailure, match="no '- \\*\\*relight\\*\\*:' training line"):
        export._kept_line(card, "relight")
    with pytest.raises(CommandFailure, match="no previous card"):
        export._kept_line(tmp_path / "missing.md", "relight")


def test_a_tuned_stage_has_its_prior_line_then_the_tunes_with_the_weights_it_changed(tmp_path):
    sections = {
        name: load_section(name, REPO / "base" / "params.yaml", check_paths=False)
        for name in ("base", "render", "intrinsics", "relight")
    }
    tune = load_section("intrinsics", REPO / "base" / "tune.yaml", check_paths=False)
    log = {"steps": 2000, "mixed_precision": "bf16", "seconds": 1800.0, "machine": {"cpu": "AMD EPYC", "cores": 2}}
    card = model_card(
        **sections,
        metrics={},
        training={"intrinsics": {"steps": 6000, "seconds": 3600.0}},
        weights_bytes=1,
        tuned={"intrinsics": (tune, log)},
    )
    lines = card.splitlines()
    i = next(n for n, line in enumerate(lines) if line.startswith("- **intrinsics**: 6000 steps"))
    assert lines[i + 1] == (
        f"- **intrinsics, tuned** from it: 2000 steps of 8, lr {tune.train.lr} (cosine), bf16 precision, objective "
        "task, layout joint, loss weights normal 5; 0.50 h on AMD EPYC, 2 cores"
    )
    # a later export that keeps stage 1 keeps both lines: both made its weights
    export = load_stage("export_model")
    (tmp_path / "MODEL_CARD.md").write_text(card)
    kept = export._kept_line(tmp_path / "MODEL_CARD.md", "intrinsics").splitlines()
    assert kept == [lines[i] + export.KEPT_NOTE, lines[i + 1] + export.KEPT_NOTE]


def test_a_tune_from_the_previous_release_marks_its_kept_line_as_the_prior(tmp_path):
    export = load_stage("export_model")
    card = tmp_path / "MODEL_CARD.md"
    prior = "- **intrinsics**: 6000 steps of 8; 0.58 h"
    card.write_text(f"## Training\n{prior}{export.KEPT_NOTE}\n- **relight**: 10000 steps\n")
    line = export._kept_line(card, "intrinsics", tuned_since=True)
    assert line == prior + export.PRIOR_NOTE  # one note, the prior's, not "not retrained since"
    card.write_text(f"{line}\n")
    assert export._kept_line(card, "intrinsics") == prior + export.KEPT_NOTE


def test_the_export_refuses_a_tune_it_cannot_describe(tmp_path):
    import argparse

    from pilight.failure import CommandFailure

    export = load_stage("export_model")
    with pytest.raises(CommandFailure, match="expected intrinsics=PARAMS"):
        export._tunes(argparse.Namespace(tuned=["stage1=tune.yaml"], live=tmp_path))
    with pytest.raises(CommandFailure, match="needs --live"):
        export._tunes(argparse.Namespace(tuned=["intrinsics=tune.yaml"], live=None))
    with pytest.raises(CommandFailure, match="intrinsics_tune/metrics.json: unreadable"):
        export._tunes(argparse.Namespace(tuned=["intrinsics=tune.yaml"], live=tmp_path))
