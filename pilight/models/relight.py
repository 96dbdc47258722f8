"""Stage 2 for inference: (input image, intrinsics, target light) -> relit image, diffuse shading D and
specular S in one batched pass, built from the params a model was trained with (its config.json).

What it holds is what prediction needs: the branches and the condition maps each reads
(pilight.relight.branches), the physics anchors (pilight.relight.physics_first), the light's intensity
(pilight.relight.intensity) and the DiffusionStack. Training (pilight.train.relight.RelightTask) builds on it
and adds batches, targets and the loss; the photo API, the relight stage and the trade sweep use this
alone, so they import nothing of training, shards or Blender.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import torch

from pilight.data import schema
from pilight.data.schema import DataError
from pilight.diffusion.codec import cell_smooth
from pilight.models.stack import DiffusionStack, build_stack
from pilight.params import DOMAINS, RelightParams, SamplingParams
from pilight.physics.precision import in_full_precision
from pilight.relight import physics_first as pf
from pilight.relight.branches import (
    branch_layout,
    cond_width,
    condition_images,
    encode_conditions,
    physics_first_images,
)
from pilight.relight.encoding import gain_decode
from pilight.relight.intensity import BALL_KEYS, to_source_level


class RelightModel:
    """Stage 2's model: ``predict`` a pairs-like batch under its target balls."""

    def __init__(self, p: RelightParams):
        self.p = p
        self.form = p.form
        self.physics_first = p.form.kind == "physics_first"
        self.layout = branch_layout(p.decomposition, p.d_calc_condition, self.physics_first)
        self.with_d_calc = any("d_calc" in maps for maps in self.layout.values())
        self.branches = tuple(self.layout)
        self.V = len(self.branches)
        self.width = cond_width(p.decomposition, p.d_calc_condition, self.physics_first)
        codec_channels = _latent_channels(p)
        self.stack: DiffusionStack = build_stack(p, num_domains=self.V, cond_channels=self.width * codec_channels)

    def describe(self) -> dict[str, Any]:
        return {
            **self.stack.describe(),
            "form": self.form.model_dump(mode="json"),
            "relit_target": self.form.target,
            "branches": list(self.branches),
            "condition_maps": {b: list(m) for b, m in self.layout.items()},
            "d_calc": f"Lambertian lookup of the {self.p.ds_ball} ball x (1 - metallic)",
        }

    def to(self, device) -> RelightModel:
        self.stack.model.to(device)
        if isinstance(self.stack.codec, torch.nn.Module):
            self.stack.codec.to(device)
        return self

    def _input_offset(self, z_cond: torch.Tensor) -> torch.Tensor | None:
        """(B * V, C, h, w): z(I_in) on the relit items, 0 on the D/S items; None unless form.target is residual.

        z(I_in) is read from the relit branch's condition latents (before any CFG drop), so the
        codec encodes the input once per step, not twice."""
        if self.form.target != "residual":
            return None
        lc = self.stack.codec.latent_channels
        i, r = self.layout["relit"].index("image"), self.branches.index("relit")
        per_item = z_cond.unflatten(0, (-1, self.V))
        offset = torch.zeros_like(per_item[:, :, :lc])
        offset[:, r] = per_item[:, r, i * lc : (i + 1) * lc]
        return offset.flatten(0, 1)

    def _relit_from_output(self, y: torch.Tensor, y_a: torch.Tensor) -> torch.Tensor:
        """Decoded outputs (B, V, 3, H, W) -> the relit branch as an image (gain decoded, cells smoothed)."""
        form, cell = self.form, self.stack.codec.factor
        r = self.branches.index("relit")
        out = y[:, r]
        if form.target == "gain":
            out = gain_decode(cell_smooth(out, cell) if form.resolution == "cell" else out, y_a)
        elif form.resolution == "cell":
            out = y_a + cell_smooth(out - y_a, cell)
        else:
            return y
        return torch.cat([y[:, :r], out[:, None], y[:, r + 1 :]], dim=1)

    @property
    def _cell(self) -> int:
        """Pixels per side of one physics-first output value: the codec cell with form.resolution cell, else 1."""
        return self.stack.codec.factor if self.form.resolution == "cell" else 1

    def attention_images(self, maps: dict[str, torch.Tensor]) -> torch.Tensor:
        """What the cross-attention conditioning reads: the target ball (level-divided where the form has it)
        for `conditioning.kind: ball_tokens` (pilight.diffusion.light_tokens), else the input image."""
        if self.p.conditioning.kind == "ball_tokens":
            return maps["ball_n"] if "ball_n" in maps else maps["ball"]
        return maps["image"]

    @in_full_precision  # data, not the network: light fits and anchors in fp32 under bf16 (physics.precision)
    def _conditions(
        self, batch: dict, intr: dict[str, torch.Tensor], dev, intensity: str | None = None
    ) -> tuple[dict, pf.Anchors | None, dict[str, torch.Tensor]]:
        """Condition maps, the physics anchors (physics_first) and the target balls in use, of a pairs batch.

        ``intensity`` (default relight.intensity): relative = the batch's target balls are relative to
        the input's own light and are scaled to its level (pilight.relight.intensity); absolute = as given."""
        image_a, mask = batch["image_a"].to(dev), batch["mask"].to(dev)
        balls = {k: batch[k].to(dev) for k in BALL_KEYS if k in batch}
        form = self.form
        effective = self.physics_first and form.albedo_source == "effective"
        rendered = effective and form.source_light == "rendered"
        if rendered and "ball_a" not in batch:
            raise DataError(
                "relight.form.source_light is 'rendered' but the batch has no ball_a (the input's own light "
                "ball): re-shard with this version, or use source_light: estimated (a photo has no ball)"
            )
        source = None  # the input's own light: (ball, found), when known or needed
        size = balls["ball_b"].shape[-1]
        if rendered:
            source = (batch["ball_a"].to(dev), torch.ones(image_a.shape[0], dtype=torch.bool, device=dev))
        elif effective:
            source = pf.source_balls(image_a, intr, mask, size)
        if (intensity or self.p.intensity) == "relative":
            # the level from its own fit (first order: pilight.physics.source_light), unless rendered
            prior = self.p.level_prior
            balls = to_source_level(
                balls,
                *(source if rendered else pf.source_balls(image_a, intr, mask, size, level=True)),
                prior=None if rendered or prior is None else (prior.alpha, prior.beta),
            )
        ball_b = balls["ball_b"]
        if not self.physics_first:
            return condition_images(image_a, intr, ball_b, mask, self.with_d_calc), None, balls
        anc = pf.anchors(
            image_a,
            intr,
            mask,
            ball_b,
            balls.get("ball_lambertian_b"),
            albedo_source=form.albedo_source,
            ball_a=source[0] if effective else None,
            lambertian_a=batch["ball_lambertian_a"].to(dev) if rendered and "ball_lambertian_a" in batch else None,
            smooth_cell=self._cell,
            specular=form.specular_anchor,
            found=source[1] if effective else None,
        )
        return physics_first_images(image_a, intr, ball_b, mask, anc), anc, balls

    def _physics_first_outputs(
        self, y: torch.Tensor, anc: pf.Anchors, y_a: torch.Tensor, mask: torch.Tensor
    ) -> dict[str, torch.Tensor]:
        """Decoded gains (B, 3, 3, H, W) -> linear {relit, diffuse, specular, albedo}: A_x D + S on the mask,
        the relit branch's gain on the input off it."""
        g_r, g_d, g_s = (cell_smooth(y[:, i].float(), self._cell) for i in range(3))
        out = pf.compose_relit(anc, g_d, g_s)
        off = schema.from_model("image", gain_decode(g_r, y_a))
        out["relit"] = torch.where(mask > 0.5, out["relit"], off)
        return out

    @torch.no_grad()
    def predict(
        self,
        batch: dict,
        sp: SamplingParams,
        generator: torch.Generator | None = None,
        intr: dict[str, torch.Tensor] | None = None,
        *,
        intensity: str | None = None,
        zero_gains: bool = False,
    ) -> dict[str, torch.Tensor]:
        """Pairs batch -> linear HDR {relit, diffuse, specular} (B, 3, H, W), all branches in one batched pass
        (+ "albedo", the A_x of I = A_x D + S, with physics_first).

        `intr`: the intrinsics to condition on (default: the batch's ground truth); the mask and
        the balls always come from the batch. ``intensity`` (default relight.intensity): relative = the
        batch's target balls are relative balls (level k; pilight.relight.intensity), absolute = as they
        are. ``zero_gains`` (physics_first only): the physics anchor alone, no network (its baseline)."""
        s, V = self.stack, self.V
        dev = next(s.model.parameters()).device
        intr = {d: (intr or batch)[d].to(dev) for d in DOMAINS}
        image_a = batch["image_a"].to(dev)
        B = image_a.shape[0]
        maps, anc, _ = self._conditions(batch, intr, dev, intensity)
        if zero_gains:
            if anc is None:
                raise ValueError("zero_gains is the physics-first anchor; this model has no anchor (form: free)")
            zero = torch.zeros(B, V, 3, *image_a.shape[-2:], device=dev)
            out = self._physics_first_outputs(zero, anc, maps["image"], batch["mask"].to(dev))
            return {k: v.clamp(0, schema.HDR_MAX) for k, v in out.items()}
        z_cond = encode_conditions(s.codec, maps, self.layout, self.width)
        ids = torch.arange(V, device=dev).repeat(B)
        z0 = s.sample(z_cond, ids, self.attention_images(maps), V, sp, generator)
        if anc is not None:
            out = self._physics_first_outputs(
                s.codec.decode(z0).float().unflatten(0, (B, V)), anc, maps["image"], batch["mask"].to(dev)
            )
            return {k: v.clamp(0, schema.HDR_MAX) for k, v in out.items()}
        offset = self._input_offset(z_cond)
        if offset is not None:
            z0 = z0 + offset
        y = self._relit_from_output(s.codec.decode(z0).float().unflatten(0, (B, V)), maps["image"])
        # Clamp: model_to_hdr of the top code rounds just above the float16 maximum (inf in an EXR).
        return {b: schema.from_model("image", y[:, i]).clamp(0, schema.HDR_MAX) for i, b in enumerate(self.branches)}


def _latent_channels(p: RelightParams) -> int:
    """The codec's latent width without building the UNet (pixel: 3 f^2; VAE: from its config)."""
    if p.codec.kind == "pixel":
        return 3 * p.codec.factor**2
    try:
        return int(json.loads((Path(p.codec.path) / "config.json").read_text()).get("latent_channels", 4))
    except (OSError, ValueError):
        return 4  # build_stack then reports the broken VAE folder itself
