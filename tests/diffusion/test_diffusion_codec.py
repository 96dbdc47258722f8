"""Codecs (codec.py): exact pixel codec; frozen fp32-decoding VAE loaded from a local dir."""

import pytest
import torch
from diffusers import AutoencoderKL

from pilight.diffusion.codec import PixelCodec, VaeCodec, make_codec


def test_pixel_codec_round_trip_exact():
    codec = PixelCodec(4)
    x = torch.rand(2, 3, 16, 24) * 2 - 1
    z = codec.encode(x)
    assert z.shape == (2, 48, 4, 6) and codec.latent_channels == 48
    assert codec.name == "pixel-unshuffle-4" and codec.factor == 4
    assert torch.equal(codec.decode(z), x)


def test_pixel_codec_rejects_indivisible_size():
    with pytest.raises(ValueError, match=r"18x24.*factor 4"):
        PixelCodec(4).encode(torch.zeros(1, 3, 18, 24))


def test_make_codec():
    assert make_codec("pixel", factor=2).name == "pixel-unshuffle-2"
    with pytest.raises(ValueError, match="codec.path"):
        make_codec("vae")
    with pytest.raises(ValueError, match="unknown codec"):
        make_codec("jpeg")


@pytest.fixture(scope="module")
def vae_dir(tmp_path_factory):
    torch.manual_seed(0)
    vae = AutoencoderKL(
        in_channels=3,
        out_channels=3,
        block_out_channels=(8, 16),
        layers_per_block=1,
        down_block_types=("DownEncoderBlock2D",) * 2,
        up_block_types=("UpDecoderBlock2D",) * 2,
        latent_channels=4,
        norm_num_groups=4,
        sample_size=16,
        scaling_factor=0.5,
    )
    path = tmp_path_factory.mktemp("models") / "tiny-vae"
    vae.save_pretrained(path)
    return path


def test_vae_missing_path_names_it(tmp_path):
    missing = tmp_path / "no-such-vae"
    with pytest.raises(FileNotFoundError, match="no-such-vae"):
        VaeCodec(missing)


def test_vae_codec_properties_and_encode(vae_dir):
    codec = make_codec("vae", path=str(vae_dir))
    assert codec.factor == 2 and codec.latent_channels == 4 and codec.name == "vae:tiny-vae"
    assert not any(p.requires_grad for p in codec.parameters())
    x = torch.rand(2, 3, 16, 16) * 2 - 1
    z = codec.encode(x)
    assert z.shape == (2, 4, 8, 8)
    ref = AutoencoderKL.from_pretrained(vae_dir).encode(x).latent_dist.mean * 0.5  # mean * scaling_factor
    torch.testing.assert_close(z, ref)
    sampled = codec.encode(x, generator=torch.Generator().manual_seed(0))
    assert not torch.equal(sampled, z)  # a posterior sample, not the mean
    codec.train()
    assert not codec.vae.training
    with pytest.raises(ValueError, match="factor 2"):
        codec.encode(torch.zeros(1, 3, 15, 16))


def test_vae_decode_gradients_checkpoint_and_fp32(vae_dir):
    codec = VaeCodec(vae_dir, dtype=torch.bfloat16)
    assert codec.vae.encoder.conv_in.weight.dtype == torch.bfloat16
    assert codec.vae.decoder.conv_in.weight.dtype == torch.float32
    assert codec.encode(torch.zeros(1, 3, 16, 16)).dtype == torch.float32

    z = torch.randn(2, 4, 8, 8)
    grads = []
    for ckpt in (False, True):
        zz = z.clone().requires_grad_(True)
        img = codec.decode(zz, checkpoint=ckpt)
        assert img.shape == (2, 3, 16, 16) and img.dtype == torch.float32
        img.square().mean().backward()
        assert zz.grad is not None and zz.grad.abs().sum() > 0
        grads.append((img.detach(), zz.grad))
    torch.testing.assert_close(grads[0][0], grads[1][0])
    torch.testing.assert_close(grads[0][1], grads[1][1])

    # bf16 latents (e.g. from an autocast sampler) still decode in fp32, also under autocast
    with torch.autocast("cpu", dtype=torch.bfloat16):
        img16 = codec.decode(z.bfloat16())
    assert img16.dtype == torch.float32
    torch.testing.assert_close(img16, codec.decode(z.bfloat16().float()))
