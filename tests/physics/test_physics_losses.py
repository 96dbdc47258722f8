"""Physics losses, 1/t weighting, and feature extractors (tiny random DINOv2)."""

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from pilight.physics import (
    Dinov2Features,
    PooledRGBFeatures,
    compose,
    diffuse_shading_loss,
    make_feature_extractor,
    physical_shading_loss,
    physics_loss,
    reconstruction_loss,
)


def test_diffuse_shading_loss_is_masked_mse():
    a, b = torch.rand(2, 3, 4, 4), torch.rand(2, 3, 4, 4)
    mask = torch.zeros(2, 1, 4, 4)
    mask[0, :, :2] = 1
    mask[1] = 1
    per = diffuse_shading_loss(a, b, mask, reduction="none")
    torch.testing.assert_close(per[0], (a[0, :, :2] - b[0, :, :2]).pow(2).mean())
    torch.testing.assert_close(per[1], (a[1] - b[1]).pow(2).mean())
    torch.testing.assert_close(diffuse_shading_loss(a, b, mask), per.mean())
    b2 = b.clone()
    b2[0, :, 2:] += 100  # changes under the mask do not count
    torch.testing.assert_close(diffuse_shading_loss(a, b2, mask), per.mean())


def test_physical_shading_loss_zero_for_consistent_decomposition():
    A, D, S = torch.rand(2, 3, 8, 8), torch.rand(2, 3, 8, 8) * 3, torch.rand(2, 3, 8, 8) * 0.1
    relit = compose(A, D, S)
    assert physical_shading_loss(relit, A, D, S).item() == 0.0
    torch.testing.assert_close(physical_shading_loss(relit + 0.1, A, D, S), torch.tensor(0.01))
    mask = torch.zeros(2, 1, 8, 8)
    assert physical_shading_loss(relit + 1, A, D, S, mask).item() == 0.0


def test_physics_loss_weighting():
    l = torch.tensor([1.0, 2.0])
    # t = 0 is floored at t_min = 1 (no division by zero); t = 999 weighs 1/999
    torch.testing.assert_close(physics_loss(0, l, l, l, (1, 1, 1)), (3 * l).mean())
    torch.testing.assert_close(physics_loss(999, l, l, l, (1, 1, 1)), (3 * l / 999).mean())
    t = torch.tensor([0, 999])
    out = physics_loss(t, l, 0 * l, 0 * l, (2.0, 1.0, 1.0), t_min=1)
    torch.testing.assert_close(out, torch.tensor((2 * 1.0 / 1 + 2 * 2.0 / 999) / 2))
    torch.testing.assert_close(physics_loss(torch.tensor([999, 999]), l, l, l, (1, 2, 3)), (6 * l / 999).mean())
    with pytest.raises(ValueError):
        physics_loss(0, l, l, l, (1, 1, 1), t_min=0)
    # bf16 losses: weights still exact in fp32
    out16 = physics_loss(torch.tensor([999]), l.bfloat16()[:1], 0, 0, (1, 0, 0))
    assert torch.isfinite(out16) and abs(out16.item() - 1 / 999) < 1e-9


@settings(max_examples=20, deadline=None)
@given(t=st.integers(0, 998), t_min=st.floats(0.5, 10))
def test_physics_loss_finite_and_monotone(t, t_min):
    """The weight is 1 / max(t, t_min): finite at t = 0, and never larger at a noisier step (strictly
    smaller once past the floor)."""
    l = torch.tensor([0.3], requires_grad=True)
    out = physics_loss(torch.tensor([t]), l, l, l, (1, 1, 1), t_min)
    out.backward()
    assert torch.isfinite(out) and torch.isfinite(l.grad).all()
    assert out.item() == pytest.approx(0.9 / max(t, t_min), rel=1e-6)
    later = physics_loss(torch.tensor([t + 1]), l, l, l, (1, 1, 1), t_min)
    assert later <= out
    if t + 1 > t_min:
        assert later < out


def test_gradcheck_losses():
    g = torch.Generator().manual_seed(1)
    r = lambda *s: torch.rand(*s, generator=g, dtype=torch.float64, requires_grad=True)
    mask = (torch.rand(2, 1, 4, 4, generator=g) > 0.3).double()
    assert torch.autograd.gradcheck(lambda a, b: diffuse_shading_loss(a, b, mask), (r(2, 3, 4, 4), r(2, 3, 4, 4)))
    assert torch.autograd.gradcheck(
        lambda i, a, d, s: physical_shading_loss(i, a, d, s, mask),
        (r(2, 3, 4, 4), r(2, 3, 4, 4), r(2, 3, 4, 4), r(2, 3, 4, 4)),
    )
    inp = torch.rand(2, 3, 16, 16, generator=g, dtype=torch.float64)
    ext = PooledRGBFeatures(4)
    assert torch.autograd.gradcheck(lambda x: reconstruction_loss(x, inp, ext), (r(2, 3, 16, 16),))
    t = torch.tensor([3, 500])
    assert torch.autograd.gradcheck(lambda a, b, c: physics_loss(t, a, b, c, (0.5, 1.0, 2.0)), (r(2), r(2), r(2)))


def test_pooled_rgb_extractor():
    ext = make_feature_extractor("pooled-rgb")
    assert ext.name == "pooled-rgb-8x8"
    x = torch.rand(2, 3, 32, 32)
    assert reconstruction_loss(x, x, ext).item() == 0.0
    assert reconstruction_loss(x, 1 - x, ext).item() > 0


def test_make_feature_extractor_errors(tmp_path):
    with pytest.raises(ValueError, match="dinov2"):
        make_feature_extractor("dinov2", None)
    with pytest.raises(ValueError, match="unknown"):
        make_feature_extractor("clip", None)
    missing = tmp_path / "no_such_dinov2"
    with pytest.raises(FileNotFoundError, match="no_such_dinov2"):
        make_feature_extractor("dinov2", str(missing))


@pytest.fixture(scope="module")
def tiny_dinov2(tmp_path_factory):
    from transformers import Dinov2Config, Dinov2Model

    torch.manual_seed(0)
    cfg = Dinov2Config(
        hidden_size=32,
        num_hidden_layers=2,
        num_attention_heads=2,
        intermediate_size=64,
        patch_size=4,
        image_size=32,
        hidden_dropout_prob=0.1,
        attention_probs_dropout_prob=0.1,
    )
    path = tmp_path_factory.mktemp("dinov2_tiny")
    Dinov2Model(cfg).save_pretrained(path)
    return path


def test_dinov2_features(tiny_dinov2):
    ext = Dinov2Features(tiny_dinov2, resolution=32)
    ext.train()  # a training loop calling .train() must not turn dropout on in the frozen backbone
    assert not ext.model.training
    assert ext.name.startswith("dinov2:")
    torch.manual_seed(1)
    x, y = torch.rand(2, 3, 48, 40), torch.rand(2, 3, 48, 40)
    f1, f2 = ext(x), ext(x)
    assert torch.equal(f1, f2)  # deterministic
    assert f1.shape == (2, 1 + (40 // 4) * (32 // 4), 32)  # short side 40 -> 32; long 48 -> 38.4 -> 40
    assert reconstruction_loss(x, x, ext).item() == 0.0
    relit = y.clone().requires_grad_(True)
    loss = reconstruction_loss(relit, x, ext)
    assert loss.item() > 0
    loss.backward()
    assert relit.grad is not None and torch.isfinite(relit.grad).all() and relit.grad.abs().sum() > 0
    assert all(not p.requires_grad and p.grad is None for p in ext.parameters())


def test_dinov2_via_factory(tiny_dinov2):
    ext = make_feature_extractor("dinov2", str(tiny_dinov2), resolution=16)
    assert ext(torch.rand(1, 3, 16, 16)).shape == (1, 1 + 16, 32)


def test_the_losses_compare_in_the_space_they_are_given():
    """Stage 2 trains with these very functions in its tone-mapped space (pilight.relight.physics_terms):
    ``space`` maps both sides, after the identity A * D + S is formed in linear HDR."""
    g = torch.Generator().manual_seed(0)
    a, b = torch.rand(2, 3, 4, 4, generator=g), torch.rand(2, 3, 4, 4, generator=g)
    mask = torch.ones(2, 1, 4, 4)
    double = lambda x: 2 * x
    torch.testing.assert_close(diffuse_shading_loss(a, b, mask, space=double), 4 * diffuse_shading_loss(a, b, mask))
    A, D, S = torch.full((1, 3, 2, 2), 0.5), torch.full((1, 3, 2, 2), 2.0), torch.zeros(1, 3, 2, 2)
    square = lambda x: x**2
    # linear: relit 1.5 against A * D + S = 1.0; squared first: 2.25 against 1.0
    torch.testing.assert_close(physical_shading_loss(A * 3, A, D, S), torch.tensor(0.25))
    torch.testing.assert_close(physical_shading_loss(A * 3, A, D, S, space=square), torch.tensor(1.5625))
