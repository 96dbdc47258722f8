"""UNet construction (unet.py) and loading a local pretrained UNet with a widened conv_in."""

import pytest
import torch
from diffusers import UNet2DConditionModel

from fixtures.tiny_unet import TINY, tiny_diffusers_unet
from pilight.diffusion.unet import PAPER_UNET_SPEC, UNetSpec, build_unet, load_pretrained_unet


def test_build_unet_domain_embedding():
    torch.manual_seed(0)
    unet = build_unet(TINY, in_channels=8, out_channels=4, num_domains=4).eval()
    assert unet.config.class_embed_type == "projection"
    assert unet.config.projection_class_embeddings_input_dim == 4
    x, ehs, t = torch.randn(4, 8, 8, 8), torch.randn(4, 1, 16), torch.full((4,), 10)
    with torch.no_grad():
        out_a = unet(x, t, ehs, class_labels=torch.eye(4)).sample
        out_b = unet(x, t, ehs, class_labels=torch.eye(4).roll(1, 0)).sample
    assert out_a.shape == (4, 4, 8, 8)
    assert (out_a - out_b).abs().amax(dim=(1, 2, 3)).min() > 0  # the label changes every item's output


def test_default_and_paper_specs():
    default = UNetSpec()
    assert default.block_out_channels == (64, 128, 128) and default.sample_size == 32
    assert PAPER_UNET_SPEC.block_out_channels == (320, 640, 1280, 1280)
    assert PAPER_UNET_SPEC.attention_head_dim == (5, 10, 20, 20)
    assert PAPER_UNET_SPEC.cross_attention_dim == 1024 and PAPER_UNET_SPEC.use_linear_projection
    with torch.device("meta"):  # no memory: just check the config builds and its size is SD2's
        unet = build_unet(PAPER_UNET_SPEC, in_channels=8, out_channels=4, num_domains=4)
    n = sum(p.numel() for p in unet.parameters())
    assert 865e6 < n < 870e6  # SD2 UNet: 865.9M (+ conv_in widening + domain embedding)


@pytest.fixture()
def pretrained_dir(tmp_path):
    unet = tiny_diffusers_unet()
    path = tmp_path / "tiny-unet"
    unet.save_pretrained(path)
    return path


def test_load_pretrained_zero_init_is_exactly_the_pretrained_model(pretrained_dir, tmp_path):
    original = UNet2DConditionModel.from_pretrained(pretrained_dir).eval()
    unet = load_pretrained_unet(pretrained_dir, in_channels=8, num_domains=4, out_channels=4).eval()
    assert unet.config.in_channels == 8 and unet.conv_in.in_channels == 8
    assert unet.config.class_embed_type == "projection"

    g = torch.Generator().manual_seed(1)
    latent, cond = torch.randn(3, 4, 8, 8, generator=g), 5 * torch.randn(3, 4, 8, 8, generator=g)
    ehs, t = torch.randn(3, 1, 16, generator=g), torch.tensor([0, 400, 999])
    labels = torch.eye(4)[[0, 2, 3]]
    with torch.no_grad():
        ref = original(latent, t, ehs).sample
        out = unet(torch.cat([latent, cond], 1), t, ehs, class_labels=labels).sample
    torch.testing.assert_close(out, ref, atol=1e-6, rtol=0)

    # gradients reach the new condition kernel and the domain embedding, so both can learn
    unet.train()
    unet(torch.cat([latent, cond], 1), t, ehs, class_labels=labels).sample.square().mean().backward()
    assert unet.conv_in.weight.grad[:, 4:].abs().sum() > 0
    assert unet.class_embedding.linear_2.weight.grad.abs().sum() > 0

    # the updated config round-trips through save_pretrained
    unet.save_pretrained(tmp_path / "adapted")
    again = UNet2DConditionModel.from_pretrained(tmp_path / "adapted").eval()
    unet.eval()
    with torch.no_grad():
        torch.testing.assert_close(
            again(torch.cat([latent, cond], 1), t, ehs, class_labels=labels).sample,
            unet(torch.cat([latent, cond], 1), t, ehs, class_labels=labels).sample,
        )


def test_load_pretrained_errors(pretrained_dir, tmp_path):
    with pytest.raises(FileNotFoundError, match="missing-unet"):
        load_pretrained_unet(tmp_path / "missing-unet", in_channels=8, num_domains=4)
    with pytest.raises(ValueError, match=r"codec/UNet channel mismatch.*48.*predicts 4"):
        load_pretrained_unet(pretrained_dir, in_channels=8, num_domains=4, out_channels=48)
    with pytest.raises(ValueError, match="smaller"):
        load_pretrained_unet(pretrained_dir, in_channels=2, num_domains=4)
