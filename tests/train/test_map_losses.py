"""Stage 1's task losses (pilight.train.map_losses) and the exact augmentations (pilight.train.intrinsics)."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from pilight.params import AugmentParams, TaskLossParams
from pilight.train.intrinsics import augment
from pilight.train.map_losses import albedo_loss, albedo_scale, angular_loss, bce_loss, l1_loss, task_loss


def _mask(b=2, h=8, w=8, p=0.6, seed=0):
    return (torch.rand(b, 1, h, w, generator=torch.Generator().manual_seed(seed)) < p).float()


def test_angular_loss_is_the_mean_angle_on_the_mask():
    n = F.normalize(torch.randn(2, 3, 8, 8), dim=1)
    m = _mask()
    assert float(angular_loss(n, n, m)) < 2e-3  # arccos(1 - 1e-6)
    assert float(angular_loss(-n, n, m)) == pytest.approx(math.pi, abs=2e-3)
    # a prediction 90 degrees off on the mask, anything elsewhere: pi / 2
    perp = torch.zeros_like(n)
    perp[:, 0], n2 = 1.0, torch.zeros_like(n)
    n2[:, 2] = 1.0
    off = torch.where(m > 0, perp, -n2)
    assert float(angular_loss(off * 3.0, n2, m)) == pytest.approx(math.pi / 2, abs=1e-4)  # scale-free


def test_losses_are_zero_not_nan_on_an_empty_mask():
    x, m = torch.rand(2, 3, 8, 8), torch.zeros(2, 1, 8, 8)
    for value in (angular_loss(x, x, m), l1_loss(x, x + 1, m), bce_loss(x, x, m), albedo_loss(x, x * 2, m, 1.0)[0]):
        assert float(value) == 0.0


def test_albedo_loss_separates_structure_from_level():
    gt, m = torch.rand(2, 3, 8, 8) * 0.8 + 0.05, _mask()
    scaled = gt / 3.0  # right structure, level off by 3
    total, parts = albedo_loss(scaled, gt, m, level_weight=0.5)
    assert float(parts["albedo_structure"]) < 1e-8
    assert float(parts["albedo_level"]) == pytest.approx(math.log(3.0) ** 2, rel=1e-4)
    assert float(total) == pytest.approx(0.5 * math.log(3.0) ** 2, rel=1e-4)
    assert albedo_scale(scaled, gt, m) == pytest.approx(torch.full((2,), 3.0), rel=1e-5)
    # the scale is fitted on the mask only: a wild value off the mask changes nothing
    wild = torch.where(m > 0, scaled, torch.full_like(scaled, 50.0))
    assert float(albedo_loss(wild, gt, m, 0.5)[0]) == pytest.approx(float(total), rel=1e-5)


def test_bce_prefers_the_right_class():
    gt, m = (torch.rand(2, 1, 8, 8) > 0.5).float(), torch.ones(2, 1, 8, 8)
    assert float(bce_loss(gt, gt, m)) < 1e-3
    assert float(bce_loss(1 - gt, gt, m)) > 9.0


def test_task_loss_weights_select_terms():
    g = {
        "albedo": torch.rand(1, 3, 8, 8),
        "normal": F.normalize(torch.randn(1, 3, 8, 8), dim=1),
        "roughness": torch.rand(1, 1, 8, 8),
        "metallic": torch.rand(1, 1, 8, 8),
    }
    p = {k: v.flip(-1) for k, v in g.items()}
    m = torch.ones(1, 1, 8, 8)
    only_normal = TaskLossParams(albedo=0, albedo_level=0, normal=1, roughness=0, metallic=0)
    total, terms = task_loss(p, g, m, only_normal)
    assert float(total) == pytest.approx(terms["normal_angle"], rel=1e-6)
    assert set(terms) == {"albedo_structure", "albedo_level", "normal_angle", "roughness_l1", "metallic_bce"}


def _sphere_batch(h=16):
    """A centred sphere: its flipped image, with the normals' x negated, is itself."""
    y, x = torch.meshgrid(torch.linspace(1, -1, h), torch.linspace(-1, 1, h), indexing="ij")
    inside = (x * x + y * y) < 0.8
    z = (1 - x * x - y * y).clamp_min(0).sqrt()
    n = torch.stack([x, y, z]) * inside
    shade = (n * torch.tensor([0.0, 0.6, 0.8]).view(3, 1, 1)).sum(0, keepdim=True).clamp_min(0)
    b = {
        "image": shade.expand(3, h, h)[None].repeat(4, 1, 1, 1),
        "normal": n[None].repeat(4, 1, 1, 1),
        "mask": inside[None, None].float().repeat(4, 1, 1, 1),
        "albedo": torch.full((4, 3, h, h), 0.5),
        "roughness": x.abs()[None, None].repeat(4, 1, 1, 1),
        "metallic": torch.zeros(4, 1, h, h),
    }
    return b


def test_flip_keeps_the_truth_true():
    b = _sphere_batch()
    out = augment(b, AugmentParams(flip=True), torch.Generator().manual_seed(1))
    for k in b:
        assert torch.allclose(out[k], b[k], atol=1e-6), k  # symmetric scene: flipped truth == truth
    # an asymmetric map really is flipped for some samples and not for others
    b["roughness"] = torch.linspace(0, 1, 16).view(1, 1, 1, 16).repeat(4, 1, 16, 1)
    out = augment(b, AugmentParams(flip=True), torch.Generator().manual_seed(1))
    flipped = [bool(torch.equal(out["roughness"][i], b["roughness"][i].flip(-1))) for i in range(4)]
    assert any(flipped) and not all(flipped)
    for i, f in enumerate(flipped):  # x negated exactly where the image was flipped
        want = b["normal"][i].flip(-1) * torch.tensor([-1.0, 1, 1]).view(3, 1, 1) if f else b["normal"][i]
        assert torch.equal(out["normal"][i], want)


def test_crop_cuts_every_map_alike():
    b = _sphere_batch(16)
    b["roughness"] = torch.arange(256.0).view(1, 1, 16, 16).repeat(4, 1, 1, 1)
    out = augment(b, AugmentParams(crop=8), torch.Generator().manual_seed(0))
    assert all(v.shape[-2:] == (8, 8) for k, v in out.items())
    top, left = divmod(int(out["roughness"][0, 0, 0, 0]), 16)
    assert torch.equal(out["normal"], b["normal"][..., top : top + 8, left : left + 8])
    with pytest.raises(ValueError, match="crop 32 is larger"):
        augment(b, AugmentParams(crop=32), torch.Generator())
