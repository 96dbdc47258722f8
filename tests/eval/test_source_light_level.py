"""benchmarks/source_light_level.py: the pipeline's split is the nine-term fit for the shading and the
first-order fit for the level, so only the relative tier can tell it from the nine-term fit."""

from __future__ import annotations

import torch

from fixtures.benchmark_scripts import load_benchmark
from fixtures.relight_pairs import physics_pair

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
