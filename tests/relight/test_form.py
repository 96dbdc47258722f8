"""Stage 2's output form is one choice with its own options (`relight.form`, pilight.params): the free
relit branch (the paper's) or physics-first (ours). The six flat keys of earlier versions are refused
in params with the form that means the same, and saved models that carry them still load."""

from __future__ import annotations

import json
import re

import pytest
from pydantic import ValidationError

from fixtures.tiny_models import REPO
from pilight.base_model import BASE_DIR, mismatches
from pilight.params import (
    FreeRelitForm,
    PhysicsFirstForm,
    RelightParams,
    form_from_flat,
    load_section,
    migrate_saved_relight,
)
from pilight.profiles import compose

SHIPPED = BASE_DIR / "relight" / "config.json"
# stage 2's saved params of the base of ea6a7b9, the last one saved with the flat keys (physics_first, ...)
FLAT_SAVED = REPO / "fixtures" / "flat_relight_params.json"
FLAT_PHYSICS_FIRST = {
    "physics_first": True,
    "relit_target": "gain",
    "relit_resolution": "cell",
    "albedo_source": "effective",
    "source_light": "estimated",
    "specular_anchor": "ggx",
}


def test_each_form_holds_only_its_own_options():
    assert RelightParams().form == FreeRelitForm(target="image", resolution="full")  # the paper, by default
    p = RelightParams.model_validate({"form": {"kind": "physics_first"}})
    assert isinstance(p.form, PhysicsFirstForm) and p.form.target == "gain"
    with pytest.raises(ValidationError, match="albedo_source"):  # a physics-first option on the free branch
        RelightParams.model_validate({"form": {"kind": "free", "albedo_source": "effective"}})
    with pytest.raises(ValidationError, match="kind"):
        RelightParams.model_validate({"form": {"kind": "physics-first"}})


def test_flat_keys_are_refused_with_the_form_that_means_the_same():
    with pytest.raises(ValidationError, match=r"physics_first, relit_target.*relight.form") as err:
        RelightParams.model_validate(FLAT_PHYSICS_FIRST)
    suggested = json.loads(re.search(r"form: (\{.*?\})", str(err.value)).group(1))
    assert RelightParams.model_validate({"form": suggested}).form == PhysicsFirstForm(
        resolution="cell", albedo_source="effective", source_light="estimated", specular_anchor="ggx"
    )


@pytest.mark.parametrize(
    "flat, form",
    [
        ({}, FreeRelitForm(target="image", resolution="full")),  # the defaults of the flat keys
        ({"relit_target": "gain", "relit_resolution": "cell"}, FreeRelitForm(target="gain", resolution="cell")),
        (
            {"physics_first": True, "relit_target": "gain"},
            PhysicsFirstForm(resolution="full", specular_anchor="lookup"),
        ),
    ],
)
def test_the_flat_keys_defaults_mean_what_they_meant(flat, form):
    assert RelightParams.model_validate({"form": form_from_flat(flat)}).form == form


def test_the_shipped_base_is_saved_with_the_form_and_fits_the_default_params():
    saved = json.loads(SHIPPED.read_text())["params"]
    wanted = load_section("relight", "params.yaml", check_paths=False)
    assert not any(k in saved for k in FLAT_PHYSICS_FIRST)
    assert migrate_saved_relight(saved)["form"] == wanted.form.model_dump(mode="json")
    assert mismatches("relight", wanted.model_dump(mode="json"), saved) == []


def test_a_saved_model_with_flat_keys_migrates_and_fits_the_default_params():
    """A base saved with the flat keys (ea6a7b9's) reads as the form the embedded default asks for,
    so `unet.init: base` finds no mismatch, and migrating twice changes nothing."""
    saved = json.loads(FLAT_SAVED.read_text())
    assert saved.get("physics_first") is True  # the test is about a flat config
    migrated = migrate_saved_relight(saved)
    assert not any(k in migrated for k in FLAT_PHYSICS_FIRST) and migrate_saved_relight(migrated) == migrated
    wanted = load_section("relight", "params.yaml", check_paths=False)
    # that base had no light-level prior; the default's is the shipped base's (tests/relight/test_level_prior.py)
    wanted = wanted.model_copy(update={"level_prior": None})
    assert migrated["form"] == wanted.form.model_dump(mode="json")
    assert mismatches("relight", wanted.model_dump(mode="json"), saved) == []
    free = wanted.model_copy(update={"form": FreeRelitForm(target="gain", resolution="cell")})
    wrong = mismatches("relight", free.model_dump(mode="json"), saved)
    assert wrong[0] == "relight.form.kind: the base has 'physics_first', the params ask for 'free'"
    assert [w.split(":")[0] for w in wrong[1:]] == [
        "relight.form.target",
        "relight.form.albedo_source",
        "relight.form.specular_anchor",
    ]


def test_an_overlay_with_another_kind_replaces_the_form_and_the_same_kind_merges():
    base = {"relight": {"form": {"kind": "physics_first", "resolution": "cell", "specular_anchor": "ggx"}}}
    other = compose(base, {"relight": {"form": {"kind": "free", "target": "image"}}})
    assert other["relight"]["form"] == {"kind": "free", "target": "image"}
    same = compose(base, {"relight": {"form": {"kind": "physics_first", "specular_anchor": "lookup"}}})
    assert same["relight"]["form"] == {"kind": "physics_first", "resolution": "cell", "specular_anchor": "lookup"}
