"""`relight.conditioning.kind: ball_tokens` (pilight/diffusion/light_tokens.py): the target ball as
cross-attention tokens. At initialisation it computes exactly what the learned embedding computes, so a
base trained with `learned` fine-tunes into it; once trained, the light reaches the UNet through it."""

from __future__ import annotations

import copy

import pytest
import torch
from pydantic import ValidationError

from fixtures.stage_scripts import TINY_NETWORK, tiny_shards
from pilight.base_model import BaseModelError, init_from_base
from pilight.data.shard_reader import make_loader, relight_dataset
from pilight.diffusion.light_tokens import BallTokens, ball_geometry
from pilight.models.folder import save_model
from pilight.models.stack import ModelError
from pilight.params import IntrinsicsParams, RelightParams, SamplingParams
from pilight.train.relight import RelightTask

SINGLE_STEP = SamplingParams(mode="single_step", cfg_scale=1.0)
TINY = {**TINY_NETWORK, "conditions": "gt", "train": {"steps": 1, "batch_size": 2, "warmup_steps": 0}}


def _p(kind: str, **unet) -> RelightParams:
    return RelightParams.model_validate(
        {**TINY, "conditioning": {"kind": kind}, "unet": {**TINY_NETWORK["unet"], **unet}}
    )


@pytest.fixture(scope="module")
def shards(tmp_path_factory):
    return tiny_shards(tmp_path_factory.mktemp("tokens"))


@pytest.fixture(scope="module")
def learned_base(shards, tmp_path_factory):
    """A tiny stage 2 with the learned embedding, saved as the export saves a base (float16)."""
    folder = tmp_path_factory.mktemp("base")
    torch.manual_seed(11)
    p = _p("learned")
    task = RelightTask(p, shards, seed=0)
    save_model(task.stack, folder / "relight", p.model_dump(mode="json"), dtype=torch.float16)
    return folder


def _batch(shards):
    return next(iter(make_loader(relight_dataset(shards, "train", shuffle=False), 2)))


def _from_base(kind: str, folder, shards) -> RelightTask:
    p = _p(kind, init="base", path=str(folder))
    torch.manual_seed(12)  # another random init, which the base replaces
    task = RelightTask(p, shards, seed=0)
    init_from_base(task.stack, p, "relight")
    task.stack.model.eval()
    return task


def test_the_geometry_is_the_ball_seen_from_the_camera():
    g = ball_geometry(8).reshape(8, 8, 4)
    n, inside = g[..., :3], g[..., 3]
    assert inside[0, 0] == 0 and inside[3, 3] == 1  # the corners are off the disc, the centre on it
    torch.testing.assert_close(n[inside > 0].norm(dim=-1), torch.ones(int(inside.sum())))
    assert bool((n[inside == 0] == 0).all())
    assert n[0, 3, 1] > 0 and n[7, 3, 1] < 0  # the top row faces up (the normal maps' y runs up)
    assert n[3, 0, 0] < 0 and n[3, 7, 0] > 0  # the left column faces left
    assert bool((n[..., 2] >= 0).all())  # the visible half faces the camera


def test_a_learned_base_loads_and_computes_the_same_relit_image(shards, learned_base):
    batch = _batch(shards)
    outs = {}
    for kind in ("learned", "ball_tokens"):
        task = _from_base(kind, learned_base, shards)
        with torch.no_grad():
            outs[kind] = task.predict(batch, SINGLE_STEP, torch.Generator().manual_seed(0))  # the same x_T
    assert task.stack.describe()["conditioning"] == "ball-tokens-8x8"
    for k in ("relit", "diffuse", "specular"):
        torch.testing.assert_close(outs["ball_tokens"][k], outs["learned"][k], rtol=1e-4, atol=1e-5)


def _relit_latents(task, batch, attention_images):
    """The UNet's clean latents of a batch, with the cross-attention reading ``attention_images``."""
    from pilight.relight.branches import encode_conditions

    intr = {k: batch[k] for k in ("albedo", "normal", "roughness", "metallic")}
    maps, _, _ = task._conditions(batch, intr, "cpu")
    z_cond = encode_conditions(task.stack.codec, maps, task.layout, task.width)
    ids = torch.arange(task.V).repeat(batch["image_a"].shape[0])
    images = attention_images(maps)
    return task.stack.sample(z_cond, ids, images, task.V, SINGLE_STEP, torch.Generator().manual_seed(0))


@pytest.mark.parametrize("kind", ["learned", "ball_tokens"])
def test_once_trained_the_tokens_carry_the_light(shards, learned_base, kind):
    """Only the cross-attention's input changes between two calls: the target ball, mirrored (the light
    from the other side). With trained tokens the output follows it; the learned embedding cannot."""
    task = _from_base(kind, learned_base, shards)
    cond = task.stack.model.conditioning
    with torch.no_grad():
        if kind == "ball_tokens":
            torch.manual_seed(0)
            torch.nn.init.normal_(cond.proj.weight, std=1.0)  # as training would move it
        batch = _batch(shards)
        same = _relit_latents(task, batch, task.attention_images)
        mirrored = _relit_latents(task, batch, lambda maps: task.attention_images(maps).flip(-1))
    moved = float((same - mirrored).abs().max())
    if kind == "ball_tokens":
        maps = task._conditions(batch, batch, "cpu")[0]
        assert torch.equal(task.attention_images(maps), maps["ball"])  # the free form's ball (no ball_n)
        assert cond(task.attention_images(maps)).shape == (2, 64, 32)
        assert moved > 1e-3
    else:
        assert moved == 0.0


def test_tokens_are_zero_at_initialisation_apart_from_the_embedding():
    tok = BallTokens(16, grid=4)
    out = tok(torch.rand(3, 3, 12, 12) * 2 - 1)
    assert out.shape == (3, 16, 16)
    torch.testing.assert_close(out, tok.embedding[None].expand(3, 16, -1))
    with pytest.raises(ValueError, match="ball images B x 3 x H x W"):
        tok(torch.zeros(3, 1, 12, 12))


def test_a_ball_token_base_does_not_load_into_the_learned_embedding(shards, tmp_path):
    """The extension goes one way: a base with the projection cannot drop it silently."""
    p = _p("ball_tokens")
    task = RelightTask(p, shards, seed=0)
    save_model(task.stack, tmp_path / "relight", p.model_dump(mode="json"), dtype=torch.float16)
    q = _p("learned", init="base", path=str(tmp_path))
    with pytest.raises(BaseModelError, match=r"relight\.conditioning\.kind: the base has 'ball_tokens'"):
        init_from_base(RelightTask(q, shards, seed=0).stack, q, "relight")


def test_a_saved_ball_token_model_needs_its_projection(shards, learned_base, tmp_path):
    """Only init_from_base may start the projection at zero: loading a trained model without it is an error."""
    from pilight.models.folder import load_model

    task = RelightTask(_p("ball_tokens"), shards, seed=0)
    with pytest.raises(ModelError, match=r"missing \['conditioning\.proj"):
        load_model(task.stack, learned_base / "relight")


def test_stage1_refuses_ball_tokens_naming_the_key():
    raw = copy.deepcopy(TINY_NETWORK)
    with pytest.raises(ValidationError, match="intrinsics.conditioning.kind 'ball_tokens'"):
        IntrinsicsParams.model_validate({**raw, "conditioning": {"kind": "ball_tokens"}})


def test_training_feeds_the_tokens_the_target_ball(shards):
    """The training loss's cross-attention reads what inference reads (attention_images): the target ball."""
    task = RelightTask(_p("ball_tokens"), shards, seed=0)
    chosen, seen = [], []
    original = task.attention_images
    task.attention_images = lambda maps: chosen.append(original(maps)) or chosen[-1]
    task.stack.model.conditioning.register_forward_hook(lambda mod, args, out: seen.append(args[0]))
    loss, _ = task.loss(_batch(shards), torch.Generator().manual_seed(0))
    assert torch.isfinite(loss)
    assert len(chosen) == 1 and len(seen) == 1 and seen[0] is chosen[0]
