"""benchmarks/source_light_level.py: the pipeline's split is the nine-term fit for the shading and the
first-order fit for the level, so only the relative tier can tell it from the nine-term fit."""

from __future__ import annotations

import torch

from fixtures.relight_pairs import physics_pair
from fixtures.script_modules import load_benchmark

source_light_level = load_benchmark("source_light_level")


def test_the_split_reads_the_shading_from_nine_terms_and_the_level_from_first_order():
    b = physics_pair()
    c = {k: b[k] for k in ("albedo", "normal", "roughness", "metallic")}
    est = source_light_level.estimates(b, c)
    (split_shading, _), (split_level, _) = est["split (pipeline)"]
    assert not torch.allclose(split_level, split_shading, rtol=1e-3)  # two fits, not one
    split = source_light_level.anchor_images(b, c, *est["split (pipeline)"])
    nine = source_light_level.anchor_images(b, c, *est["nine terms"])
    torch.testing.assert_close(split["absolute"], nine["absolute"])  # the level does not enter these two tiers
    torch.testing.assert_close(split["scale_invariant"], nine["scale_invariant"])
    assert not torch.allclose(split["relative"], nine["relative"], rtol=1e-3)


def test_the_true_albedo_row_changes_only_the_fit_albedo():
    """With conditions whose albedo is the truth, the true-albedo row IS the split; with a wrong albedo
    in the conditions it differs, and only through the light's fit (the other maps are the conditions')."""
    b = physics_pair()
    c = {k: b[k] for k in ("albedo", "normal", "roughness", "metallic")}
    est = source_light_level.estimates(b, c)
    for got, want in zip(est["split, true albedo"], est["split (pipeline)"]):
        torch.testing.assert_close(got[0], want[0])
    wrong = dict(c, albedo=(c["albedo"] * torch.linspace(0.5, 1.5, c["albedo"].shape[-1])).clamp(0, 1))
    est = source_light_level.estimates(b, wrong)
    (true_shading, _), _ = est["split, true albedo"]
    (split_shading, _), _ = est["split (pipeline)"]
    assert not torch.allclose(true_shading, split_shading, rtol=1e-3)
    torch.testing.assert_close(true_shading, source_light_level.estimates(b, c)["split, true albedo"][0][0])
