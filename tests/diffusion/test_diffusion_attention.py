"""Cross-batch self-attention (attention.py; paper appendix "batch-aware self-attention")."""

import pytest
import torch
from diffusers.models.attention_processor import Attention, AttnProcessor2_0

from fixtures.tiny_unet import tiny_diffusers_unet
from pilight.diffusion.attention import CrossBatchAttnProcessor, set_cross_batch_attention


def _tiny_unet():
    return tiny_diffusers_unet().eval()


def _unet_out(unet, x, ehs):
    with torch.no_grad():
        return unet(x, torch.full((x.shape[0],), 500), encoder_hidden_states=ehs).sample


def _unet_inputs(n, seed=1):
    g = torch.Generator().manual_seed(seed)
    return torch.randn(n, 4, 8, 8, generator=g), torch.randn(n, 3, 16, generator=g)


def _attention(**kw):
    torch.manual_seed(0)
    return Attention(query_dim=32, heads=4, dim_head=8, **kw).eval()


@pytest.mark.parametrize("kind", ["tokens", "image-groupnorm-residual"])
def test_single_view_equals_diffusers_processor(kind):
    if kind == "tokens":
        attn, x = _attention(), torch.randn(6, 10, 32)
    else:  # 4-D input path with group_norm, residual and rescale (as in VAE/mid-block attention)
        attn = _attention(norm_num_groups=8, residual_connection=True, rescale_output_factor=2.0)
        x = torch.randn(6, 32, 3, 5)
    with torch.no_grad():
        ref = AttnProcessor2_0()(attn, x)
        out = CrossBatchAttnProcessor(1)(attn, x)
    torch.testing.assert_close(out, ref, atol=1e-6, rtol=0)


def test_matches_appendix_equations():
    """q_a = W_q z^a, k_a/v_a = W_{k,v}(z^a (+) z^n (+) z^r (+) z^m), per view, computed naively."""
    attn, views = _attention(), 4
    z = torch.randn(2 * views, 5, 32)
    with torch.no_grad():
        out = CrossBatchAttnProcessor(views)(attn, z)
        for i in range(z.shape[0]):
            s, own = divmod(i, views)
            order = [own] + [j for j in range(views) if j != own]  # own view first, as in the paper
            cat = torch.cat([z[s * views + j] for j in order])  # (V*N, C)
            q, k, v = attn.to_q(z[i]), attn.to_k(cat), attn.to_v(cat)
            q, k, v = (t.view(t.shape[0], 4, 8).transpose(0, 1) for t in (q, k, v))
            w = torch.softmax(q @ k.transpose(1, 2) / 8**0.5, dim=-1)
            ref = attn.to_out[0]((w @ v).transpose(0, 1).reshape(-1, 32))
            torch.testing.assert_close(out[i], ref, atol=1e-5, rtol=0)


def test_single_view_equals_diffusers_on_whole_unet():
    unet = _tiny_unet()
    x, ehs = _unet_inputs(4)
    ref = _unet_out(unet, x, ehs)
    unet.set_attn_processor(
        {
            n: CrossBatchAttnProcessor(1) if n.endswith("attn1.processor") else AttnProcessor2_0()
            for n in unet.attn_processors
        }
    )
    torch.testing.assert_close(_unet_out(unet, x, ehs), ref, atol=1e-6, rtol=0)


def test_set_cross_batch_attention_switch():
    unet = _tiny_unet()
    n_self = sum(n.endswith("attn1.processor") for n in unet.attn_processors)
    assert set_cross_batch_attention(unet, 4) == n_self == 4  # down 1 + mid 1 + up 2
    for name, proc in unet.attn_processors.items():
        assert isinstance(proc, CrossBatchAttnProcessor) == name.endswith("attn1.processor")
    for off in (None, 1):
        assert set_cross_batch_attention(unet, off) == 0
        assert all(type(p) is AttnProcessor2_0 for p in unet.attn_processors.values())


def test_samples_are_independent_and_views_communicate():
    views, unet = 4, _tiny_unet()
    x, ehs = _unet_inputs(2 * views)
    x2 = x.clone()
    x2[0] += torch.randn(4, 8, 8)  # perturb view 0 of sample 0 only

    set_cross_batch_attention(unet, views)
    a, b = _unet_out(unet, x, ehs), _unet_out(unet, x2, ehs)
    assert torch.equal(a[views:], b[views:])  # sample 1 is untouched, bit for bit
    for view in range(1, views):  # information flows across the views of sample 0
        assert (a[view] - b[view]).abs().max() > 1e-4

    set_cross_batch_attention(unet, None)  # vanilla: views are independent
    a, b = _unet_out(unet, x, ehs), _unet_out(unet, x2, ehs)
    assert torch.equal(a[1:], b[1:])


def test_perturbing_a_whole_sample_leaves_others_exact():
    views, unet = 2, _tiny_unet()
    set_cross_batch_attention(unet, views)
    x, ehs = _unet_inputs(3 * views)
    x2 = x.clone()
    x2[2:4] = torch.randn(2, 4, 8, 8)  # sample 1 (items 2, 3)
    a, b = _unet_out(unet, x, ehs), _unet_out(unet, x2, ehs)
    assert torch.equal(a[:2], b[:2]) and torch.equal(a[4:], b[4:])


def test_bf16_is_finite():
    unet = _tiny_unet().to(torch.bfloat16)
    set_cross_batch_attention(unet, 4)
    x, ehs = _unet_inputs(4)
    out = _unet_out(unet, x.bfloat16(), ehs.bfloat16())
    assert out.dtype == torch.bfloat16 and torch.isfinite(out).all()


def test_errors_are_explicit():
    attn = _attention()
    with pytest.raises(ValueError, match="batch size 6 is not divisible by items_per_sample 4"):
        CrossBatchAttnProcessor(4)(attn, torch.randn(6, 5, 32))
    with pytest.raises(ValueError, match="self-attention"):
        CrossBatchAttnProcessor(2)(attn, torch.randn(4, 5, 32), encoder_hidden_states=torch.randn(4, 3, 32))
    with pytest.raises(ValueError, match="mask"):
        CrossBatchAttnProcessor(2)(attn, torch.randn(4, 5, 32), attention_mask=torch.ones(4, 5))
    with pytest.raises(ValueError):
        CrossBatchAttnProcessor(0)
