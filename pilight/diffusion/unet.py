"""The denoiser: a diffusers ``UNet2DConditionModel`` (Stable Diffusion 2's UNet in the paper).

Inputs are ``[noisy latent, condition latent]`` concatenated on channels (paper Sec.
Stage 1: the input image "as condition channelwisely concatenating with noise"); the
domain (albedo/normal/roughness/metallic) enters as a one-hot label through the
class embedding (``class_embed_type="projection"``, added to the timestep embedding,
as in GeoWizard).  The UNet predicts v.

Note on diffusers naming: ``attention_head_dim`` is in fact used as the number of
heads per block when ``num_attention_heads`` is unset (SD2's (5, 10, 20, 20) means
64-dim heads).  We keep the diffusers key so configs transfer verbatim.
"""

from __future__ import annotations

import os
from dataclasses import asdict, dataclass

import torch
from diffusers import UNet2DConditionModel
from diffusers.models.embeddings import TimestepEmbedding


@dataclass(frozen=True)
class UNetSpec:
    """Architecture of a UNet trained from scratch.  The defaults are a small config that
    trains on CPU at a 32x32 latent: attention only at 16x16 and 8x8 (and the mid block),
    where cross-batch attention over 4 items costs 4*256 and 4*64 tokens."""

    sample_size: int = 32
    block_out_channels: tuple[int, ...] = (64, 128, 128)
    layers_per_block: int = 1
    attention_head_dim: int | tuple[int, ...] = 8
    cross_attention_dim: int = 128
    norm_num_groups: int = 32
    down_block_types: tuple[str, ...] = ("DownBlock2D", "CrossAttnDownBlock2D", "CrossAttnDownBlock2D")
    up_block_types: tuple[str, ...] = ("CrossAttnUpBlock2D", "CrossAttnUpBlock2D", "UpBlock2D")
    use_linear_projection: bool = False


# Stable Diffusion 2 (stabilityai/stable-diffusion-2, 768-v) UNet; the paper fine-tunes it with
# in_channels 8 (VAE latent 4 + condition latent 4) and out_channels 4.  Used with random init
# for benchmarks; real weights come through load_pretrained_unet.
PAPER_UNET_SPEC = UNetSpec(
    sample_size=96,
    block_out_channels=(320, 640, 1280, 1280),
    layers_per_block=2,
    attention_head_dim=(5, 10, 20, 20),
    cross_attention_dim=1024,
    norm_num_groups=32,
    down_block_types=("CrossAttnDownBlock2D", "CrossAttnDownBlock2D", "CrossAttnDownBlock2D", "DownBlock2D"),
    up_block_types=("UpBlock2D", "CrossAttnUpBlock2D", "CrossAttnUpBlock2D", "CrossAttnUpBlock2D"),
    use_linear_projection=True,
)


def build_unet(spec: UNetSpec, in_channels: int, out_channels: int, num_domains: int) -> UNet2DConditionModel:
    """A randomly initialised v-prediction UNet with a one-hot domain class embedding."""
    cfg = asdict(spec)
    for key in ("block_out_channels", "down_block_types", "up_block_types"):
        cfg[key] = tuple(cfg[key])
    if isinstance(cfg["attention_head_dim"], list):
        cfg["attention_head_dim"] = tuple(cfg["attention_head_dim"])
    return UNet2DConditionModel(
        in_channels=in_channels,
        out_channels=out_channels,
        class_embed_type="projection",
        projection_class_embeddings_input_dim=num_domains,
        **cfg,
    )


def load_pretrained_unet(
    path: str | os.PathLike, in_channels: int, num_domains: int, out_channels: int | None = None
) -> UNet2DConditionModel:
    """Load a local pretrained UNet (e.g. SD2's ``unet/`` folder) and adapt it to this task.

    * ``conv_in`` is widened to ``in_channels``: the pretrained kernel is kept for the first
      (noisy-latent) channels and the new condition channels are ZERO-initialised.  At step 0
      the network is therefore exactly the pretrained one whatever the condition is, and the
      condition enters gradually as its kernel grows.  We prefer this over Marigold's
      "repeat the kernel and halve it": repeat-and-halve only preserves the output when the
      condition equals the noisy latent (true for nothing here) and its halved noise path
      starts the fine-tune from a perturbed, off-distribution network.
    * A one-hot domain embedding (``class_embed_type="projection"``) is added if missing,
      with its last linear zero-initialised so it starts as a no-op.
    * ``out_channels`` (the codec's latent channels), if given, must match the UNet's.
    """
    path = os.fspath(path)
    if not os.path.isdir(path):
        raise FileNotFoundError(
            f"pretrained UNet directory not found: {path!r} (expected a diffusers "
            "UNet2DConditionModel saved with save_pretrained; nothing is downloaded)"
        )
    unet = UNet2DConditionModel.from_pretrained(path, local_files_only=True)
    cfg = unet.config
    if out_channels is not None and out_channels != cfg.out_channels:
        raise ValueError(
            f"codec/UNet channel mismatch: the codec has {out_channels} latent channels "
            f"but the pretrained UNet at {path!r} predicts {cfg.out_channels}"
        )
    if in_channels < cfg.in_channels:
        raise ValueError(
            f"in_channels {in_channels} is smaller than the pretrained UNet's {cfg.in_channels} input channels"
        )
    if in_channels > cfg.in_channels:
        _widen_conv_in(unet, in_channels)
    _ensure_domain_embedding(unet, num_domains)
    return unet


def _widen_conv_in(unet: UNet2DConditionModel, in_channels: int) -> None:
    old = unet.conv_in
    new = torch.nn.Conv2d(
        in_channels,
        old.out_channels,
        old.kernel_size,
        old.stride,
        old.padding,
        dtype=old.weight.dtype,
        device=old.weight.device,
    )
    with torch.no_grad():
        new.weight.zero_()
        new.weight[:, : old.in_channels] = old.weight  # pretrained path for the noisy latent
        new.bias.copy_(old.bias)
    unet.conv_in = new
    unet.register_to_config(in_channels=in_channels)


def _ensure_domain_embedding(unet: UNet2DConditionModel, num_domains: int) -> None:
    cfg = unet.config
    if cfg.class_embed_type == "projection":
        if cfg.projection_class_embeddings_input_dim != num_domains:
            raise ValueError(
                f"pretrained UNet's projection class embedding takes "
                f"{cfg.projection_class_embeddings_input_dim} inputs, expected {num_domains} domains"
            )
        return
    if cfg.class_embed_type is not None or cfg.num_class_embeds is not None:
        raise ValueError(
            f"pretrained UNet already has a class embedding of type {cfg.class_embed_type!r} "
            f"(num_class_embeds={cfg.num_class_embeds}); cannot add the one-hot domain embedding"
        )
    time_embed_dim = unet.time_embedding.linear_2.out_features
    ref = unet.time_embedding.linear_1.weight
    # Same module diffusers builds for class_embed_type="projection" (default SiLU), so a
    # save_pretrained / from_pretrained round trip reconstructs it exactly.
    emb = TimestepEmbedding(num_domains, time_embed_dim).to(ref.device, ref.dtype)
    with torch.no_grad():  # no-op at init: linear_2 outputs exactly zero
        emb.linear_2.weight.zero_()
        emb.linear_2.bias.zero_()
    unet.class_embedding = emb
    unet.register_to_config(class_embed_type="projection", projection_class_embeddings_input_dim=num_domains)
