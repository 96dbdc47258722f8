"""Cross-attention conditioning (conditioning.py): local CLIP vision tower, learned embedding."""

import pytest
import torch
from transformers import CLIPVisionConfig, CLIPVisionModelWithProjection

from pilight.diffusion.conditioning import ClipImageEmbedding, LearnedEmbedding, make_conditioning


@pytest.fixture(scope="module")
def clip_dir(tmp_path_factory):
    torch.manual_seed(0)
    cfg = CLIPVisionConfig(
        hidden_size=32,
        intermediate_size=64,
        num_hidden_layers=2,
        num_attention_heads=4,
        image_size=32,
        patch_size=8,
        projection_dim=24,
    )
    path = tmp_path_factory.mktemp("models") / "tiny-clip"
    CLIPVisionModelWithProjection(cfg).save_pretrained(path)
    return path


def test_clip_image_embedding(clip_dir):
    emb = make_conditioning("clip", path=str(clip_dir))
    assert isinstance(emb, ClipImageEmbedding)
    assert emb.dim == 24 and emb.name == "clip:tiny-clip"
    assert not any(p.requires_grad for p in emb.parameters())
    images = torch.rand(3, 3, 48, 64) * 2 - 1  # any size: resized to the model's 32x32
    out = emb(images)
    assert out.shape == (3, 1, 24) and torch.isfinite(out).all()
    # per-image: each embedding depends only on its own image
    torch.testing.assert_close(emb(images[1:2]), out[1:2], atol=1e-5, rtol=0)
    emb.train()
    assert not emb.model.training


def test_clip_missing_path_names_it(tmp_path):
    with pytest.raises(FileNotFoundError, match="no-clip-here"):
        ClipImageEmbedding(tmp_path / "no-clip-here")
    with pytest.raises(ValueError, match="model.clip_path"):
        make_conditioning("clip")


def test_learned_embedding():
    emb = make_conditioning("learned", dim=16)
    assert isinstance(emb, LearnedEmbedding) and emb.name == "learned-embedding" and emb.dim == 16
    out = emb(torch.zeros(5, 3, 8, 8))
    assert out.shape == (5, 1, 16)
    out.sum().backward()
    assert emb.embedding.grad is not None
    assert LearnedEmbedding(8, tokens=3)(torch.zeros(2, 3, 4, 4)).shape == (2, 3, 8)
    with pytest.raises(ValueError, match="dim"):
        make_conditioning("learned")
