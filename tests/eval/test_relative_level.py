"""benchmarks/relative_level.py's level rule: w = 0 leaves the model's image, w = 1 gives it the
exposure-matched copy's level r x Y(I_a) on the mask, and w = 1/2 the geometric mean of the two levels."""

from __future__ import annotations

import torch

from fixtures.script_modules import load_benchmark
from pilight.relight.intensity import mean_luminance

relative_level = load_benchmark("relative_level")


def scene():
    g = torch.Generator().manual_seed(3)
    relit = torch.rand(2, 3, 8, 8, generator=g) * torch.tensor([0.5, 3.0]).view(2, 1, 1, 1)
    image_a = torch.rand(2, 3, 8, 8, generator=g)
    mask = torch.zeros(2, 1, 8, 8)
    mask[..., 2:6, 1:7] = 1
    image_a[..., 0, :] = 50.0  # off the mask: must not count
    return relit, image_a, mask, torch.tensor([0.5, 2.0])


def test_w0_is_the_model_and_w1_the_copys_level():
    relit, image_a, mask, r = scene()
    torch.testing.assert_close(relative_level.toward_level(relit, image_a, mask, r, 0.0), relit)
    moved = relative_level.toward_level(relit, image_a, mask, r, 1.0)
    torch.testing.assert_close(mean_luminance(moved, mask), r * mean_luminance(image_a, mask))


def test_half_way_is_the_geometric_mean_of_the_two_levels():
    relit, image_a, mask, r = scene()
    half = mean_luminance(relative_level.toward_level(relit, image_a, mask, r, 0.5), mask)
    own, copy = mean_luminance(relit, mask), r * mean_luminance(image_a, mask)
    torch.testing.assert_close(half, (own * copy).sqrt())
