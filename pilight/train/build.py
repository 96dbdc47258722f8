"""params -> codec + UNet + attention + conditioning + schedule, the same code for both stages.

Also the trained model's files: `<dir>/model.safetensors` (trainable weights only; frozen
pretrained parts such as a CLIP encoder or a VAE are reloaded from their own local paths) and
`<dir>/config.json` (the params that built it, and the names of every substituted part).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import torch
from safetensors.torch import load_file, save_file

from pilight import atomic
from pilight.diffusion.attention import set_cross_batch_attention
from pilight.diffusion.codec import make_codec
from pilight.diffusion.conditioning import make_conditioning, null_like
from pilight.diffusion.model import DomainDiffusion
from pilight.diffusion.sampler import sample
from pilight.diffusion.schedule import make_train_scheduler
from pilight.diffusion.unet import UNetSpec, build_unet, load_pretrained_unet
from pilight.params import SamplingParams
from pilight.train.checkpoint import sha256_file

# How the training-time image grids (dvclive) sample: one evaluation at t = T-1, the model's x0
# estimate from pure noise. Four DDIM steps, used before, showed pure noise all through a
# CPU-budget run (DDIM needs every timestep learned), which told the user nothing. The sampler a
# user picks lives in the infer sections, which training must not read: changing them never retrains.
PREVIEW_SAMPLING = SamplingParams(mode="single_step", cfg_scale=1.0)


class ModelError(ValueError):
    """A model cannot be built or loaded as the params describe (paths, channels, sizes)."""


@dataclass
class Stack:
    codec: object
    model: DomainDiffusion
    scheduler: object
    num_views: int
    cross_batch: bool

    def alphas_cumprod(self, device) -> torch.Tensor:
        return self.scheduler.alphas_cumprod.to(device)

    def encode_condition(self, image: torch.Tensor, drop: torch.Tensor) -> torch.Tensor:
        """Cross-attention states (B, tokens, D); dropped samples get the null (zero) state."""
        return self.model.condition_states(image, drop)

    def null_condition(self, ehs: torch.Tensor) -> torch.Tensor:
        return null_like(ehs)

    def sample(
        self,
        z_cond: torch.Tensor,
        ids: torch.Tensor,
        image: torch.Tensor,
        num_views: int,
        sp: SamplingParams,
        generator: torch.Generator | None = None,
    ) -> torch.Tensor:
        """Clean latents (B * V, C, h, w) of the V = ``num_views`` views of B samples in one batched pass,
        as ``sp`` says (steps, CFG against the null condition, ensemble); ``image``: the B condition images."""
        drop = torch.zeros(image.shape[0], dtype=torch.bool, device=image.device)
        ehs = self.encode_condition(image, drop).repeat_interleave(num_views, 0)
        return sample(
            self.model,
            z_cond,
            ids,
            ehs,
            num_views=num_views,
            steps=sp.steps,
            cfg_scale=sp.cfg_scale,
            timestep_spacing=sp.timestep_spacing,
            mode=sp.mode,
            ensemble=sp.ensemble,
            generator=generator,
            null_hidden_states=self.null_condition(ehs),
            scheduler_config=self.scheduler.config,
        )

    def describe(self) -> dict[str, str]:
        """What each part is, for reports: substitutes are named, never silent."""
        return {
            "codec": self.codec.name,
            "conditioning": self.model.conditioning.name,
            "attention": f"cross-batch over {self.num_views} views" if self.cross_batch else "vanilla self-attention",
        }


def build_stack(
    p,
    *,
    num_domains: int,
    num_views: int | None = None,
    cond_channels: int | None = None,
    maps_per_item: int = 1,
) -> Stack:
    """p: a params section with codec, unet, conditioning, cross_batch_attention, schedule.
    ``maps_per_item``: how many maps one UNet item predicts, stacked on channels (stage 1's joint layout:
    the UNet's output is that many codec latents)."""
    num_views = num_views or num_domains
    codec = make_codec(p.codec.kind, factor=p.codec.factor, path=p.codec.path)
    latent = codec.latent_channels
    cond = cond_channels or latent
    if p.unet.init == "pretrained" and maps_per_item != 1:
        raise ModelError(
            f"a pretrained UNet predicts one map per item; {maps_per_item} maps per item need a UNet built from params"
        )
    latent *= maps_per_item
    if p.unet.init == "pretrained":
        unet = load_pretrained_unet(p.unet.path, in_channels=latent + cond, num_domains=num_domains)
        if unet.config.out_channels != latent:
            raise ModelError(
                f"unet.path {p.unet.path}: out_channels {unet.config.out_channels} != codec latent channels {latent} ({codec.name})"
            )
    else:
        n = len(p.unet.block_out_channels)
        # Attention everywhere but the full-resolution level, where its token count is largest.
        down = ("DownBlock2D",) + ("CrossAttnDownBlock2D",) * (n - 1)
        up = ("CrossAttnUpBlock2D",) * (n - 1) + ("UpBlock2D",)
        spec = UNetSpec(
            block_out_channels=tuple(p.unet.block_out_channels),
            layers_per_block=p.unet.layers_per_block,
            attention_head_dim=p.unet.attention_head_dim,
            cross_attention_dim=p.unet.cross_attention_dim,
            down_block_types=down,
            up_block_types=up,
            norm_num_groups=min(32, min(p.unet.block_out_channels)),
        )
        unet = build_unet(spec, in_channels=latent + cond, out_channels=latent, num_domains=num_domains)
    dim = unet.config.cross_attention_dim
    conditioning = make_conditioning(p.conditioning.kind, p.conditioning.clip_path, dim)
    if conditioning.dim != dim:
        raise ModelError(
            f"conditioning {conditioning.name} gives {conditioning.dim}-d states but the UNet's cross_attention_dim is {dim}"
        )
    set_cross_batch_attention(unet, num_views if p.cross_batch_attention else None)
    s = p.schedule
    model = DomainDiffusion(
        unet,
        conditioning,
        num_domains=num_domains,
        cond_channels=cond,
        terminal_timestep=s.num_train_timesteps - 1 if s.terminal_input == "zero" else None,
    )
    scheduler = make_train_scheduler(s.num_train_timesteps, s.beta_schedule, s.rescale_zero_snr, s.timestep_spacing)
    return Stack(codec, model, scheduler, num_views, p.cross_batch_attention)


def check_image_size(size: tuple[int, int], factor: int, where: str) -> None:
    if size[0] % factor or size[1] % factor:
        raise ModelError(f"{where}: image size {size[0]}x{size[1]} is not divisible by the codec factor {factor}")


def trainable_state(model: torch.nn.Module) -> dict[str, torch.Tensor]:
    keep = {n for n, prm in model.named_parameters() if prm.requires_grad}
    return {
        k: v.detach().cpu().contiguous()
        for k, v in model.state_dict().items()
        if k in keep or not k.startswith("conditioning.")
    }


MODEL_FILE = "model.safetensors"
CHECKSUM_FILE = "checksums.json"


def save_model(stack: Stack, out_dir: Path, params: dict, dtype: torch.dtype | None = None) -> None:
    """Weights, config.json, then checksums.json (sha256 of the weights, which load_model verifies).
    ``dtype``: store floating tensors in it (float16 for the shipped base: half the bytes; load_model
    copies them into the float32 model).

    Written last, so a crash between the files leaves new weights with the old checksum, which
    load_model reports as a mismatch rather than loading weights of unknown provenance."""
    out_dir = Path(out_dir)
    state = trainable_state(stack.model)
    bad = [k for k, t in state.items() if t.is_floating_point() and not bool(torch.isfinite(t).all())]
    if bad:
        raise ModelError(
            f"{out_dir / MODEL_FILE}: not saved, the trained weights hold NaN/Inf "
            f"({', '.join(bad[:3])}{', ...' if len(bad) > 3 else ''})"
        )
    if dtype is not None:
        state = {k: t.to(dtype) if t.is_floating_point() else t for k, t in state.items()}
    out_dir.mkdir(parents=True, exist_ok=True)
    atomic.write_with(out_dir / MODEL_FILE, lambda tmp: save_file(state, tmp))
    atomic.write_text(
        out_dir / "config.json", json.dumps({"params": params, "parts": stack.describe()}, indent=1, sort_keys=True)
    )
    atomic.write_json(
        out_dir / CHECKSUM_FILE, {"sha256": {MODEL_FILE: sha256_file(out_dir / MODEL_FILE)}}, sort_keys=True
    )


def load_model(stack: Stack, model_dir: Path) -> None:
    """Load trained weights into ``stack``; every way the file can be wrong is a ModelError naming it."""
    path = Path(model_dir) / MODEL_FILE
    if not path.is_file():
        raise ModelError(f"{path}: trained model not found; run the training stage first")
    sums = Path(model_dir) / CHECKSUM_FILE
    if sums.is_file():  # a model saved before checksums were recorded has none: it loads as before
        try:
            digest = json.loads(sums.read_text(encoding="utf-8"))["sha256"][MODEL_FILE]
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise ModelError(f"{sums}: unreadable ({type(exc).__name__}: {exc}); rerun the training stage") from None
        if sha256_file(path) != digest:
            raise ModelError(
                f"{path}: sha256 differs from {sums}: the weights were damaged or only partly "
                "written; rerun the training stage"
            )
    try:
        state = load_file(str(path))
    except Exception as exc:  # noqa: BLE001 - safetensors raises its own error types on truncation
        raise ModelError(
            f"{path}: unreadable safetensors file ({exc}); truncated or not a model, rerun the training stage"
        ) from None
    bad = [k for k, t in state.items() if t.is_floating_point() and not bool(torch.isfinite(t).all())]
    if bad:
        raise ModelError(f"{path}: weights hold NaN/Inf ({', '.join(bad[:3])}); rerun the training stage")
    try:
        missing, unexpected = stack.model.load_state_dict(state, strict=False)
    except RuntimeError as exc:  # shapes differ: the params build another architecture than the one saved
        first = str(exc).strip().splitlines()[1:2] or [str(exc)]
        raise ModelError(f"{path}: does not match the params' model ({first[0].strip()})") from None
    missing = [k for k in missing if k in trainable_state(stack.model)]
    if missing or unexpected:
        raise ModelError(
            f"{path}: does not match the params' model (missing {missing[:3]}, unexpected {unexpected[:3]})"
        )
