"""Mirror augmentation: exact, an involution, and consistent with the physics module."""

from __future__ import annotations

import pytest
import torch
from hypothesis import given, settings, strategies as st

from pilight.data.augment import hflip
from pilight.data.shards import make_loader, relight_dataset
from pilight.train.relight import diffuse_calculated
from tests.stage_scripts import tiny_shards


@pytest.fixture(scope="module")
def pairs(tmp_path_factory):
    shards = tiny_shards(tmp_path_factory.mktemp("aug"))
    return next(iter(make_loader(relight_dataset(shards, "train", shuffle=False), 2)))


def test_mirror_negates_normal_x_only_and_mirrors_every_map():
    n = torch.nn.functional.normalize(torch.randn(1, 3, 4, 5), dim=1)
    img = torch.rand(1, 3, 4, 5)
    out = hflip({"normal": n, "image": img, "key": ["s0"]}, torch.tensor([True]))
    assert out["key"] == ["s0"]
    torch.testing.assert_close(out["image"], img.flip(-1), rtol=0, atol=0)
    torch.testing.assert_close(out["normal"][:, 0], -n[:, 0].flip(-1), rtol=0, atol=0)
    torch.testing.assert_close(out["normal"][:, 1:], n[:, 1:].flip(-1), rtol=0, atol=0)


@settings(max_examples=30, deadline=None)
@given(st.lists(st.booleans(), min_size=1, max_size=4), st.integers(1, 6))
def test_mirror_is_an_involution_and_leaves_unselected_samples(flags, width):
    g = torch.Generator().manual_seed(width)
    maps = {"normal": torch.randn(len(flags), 3, 3, width, generator=g), "mask": torch.rand(len(flags), 1, 3, width, generator=g)}
    flip = torch.tensor(flags)
    once = hflip(maps, flip)
    for k, x in maps.items():
        torch.testing.assert_close(hflip(once, flip)[k], x, rtol=0, atol=0)
        torch.testing.assert_close(once[k][~flip], x[~flip], rtol=0, atol=0)


def test_mismatched_batch_is_an_error():
    with pytest.raises(ValueError, match="'image' holds 2 samples but flip has 3"):
        hflip({"image": torch.zeros(2, 3, 4, 4)}, torch.ones(3, dtype=torch.bool))


def test_mirrored_pair_keeps_the_physics(pairs):
    """The mirrored sample is a render of the mirrored scene: the ball's Lambertian lookup with the
    mirrored normals is the mirror of the original lookup, and A * D + S = I still holds."""
    flip = torch.ones(pairs["image_a"].shape[0], dtype=torch.bool)
    m = hflip(pairs, flip)
    d_calc = diffuse_calculated(pairs["ball_b"], pairs["normal"], pairs["mask"], pairs["metallic"])
    d_calc_mirrored = diffuse_calculated(m["ball_b"], m["normal"], m["mask"], m["metallic"])
    torch.testing.assert_close(d_calc_mirrored, d_calc.flip(-1), rtol=1e-4, atol=1e-4)
    recon = lambda b: b["albedo"] * b["diffuse_b"] + b["specular_b"]
    torch.testing.assert_close(recon(m), recon(pairs).flip(-1), rtol=0, atol=0)
    assert (d_calc - d_calc.flip(-1)).abs().max() > 1e-2  # the scene is not mirror-symmetric already
