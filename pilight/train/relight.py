"""Stage 2, physics-inspired neural forward rendering: (input image, intrinsics, target light) ->
relit image, diffuse shading D and specular S together (paper, Sec. "Stage 2"), as the Task that
pilight.train.loop.train runs.

The parts, each in a file named for it under pilight/relight/:
- branches.py: the three branches (relit, diffuse, specular) and the condition maps each reads;
- encoding.py: how the relit branch's change is encoded (relit_target gain) and the physics tone map;
- physics_first.py: the physics-first output (ours, relight.physics_first): on the mask
  I_relit = A_x D_pred + S_pred with D and S as gains on their physics lookups;
- physics_terms.py: the paper's L_DS, L_PS, L_rec;
- conditions.py: ground-truth or stage-1-predicted intrinsics as conditions.

Loss (paper, final loss):

    L = L_vpred + (1/max(t, t_min)) (lambda_ds L_DS + lambda_ps L_PS + lambda_rec L_rec)

L_vpred = MSE(v, v_target) (v_target: diffusers' DDPMScheduler.get_velocity) on the latents of all branches. ``lambda_image`` (ours; 0 = the paper) adds
E2E-FT's task loss where single-step inference runs: lambda_image * MSE(tonemap(I_relit), tonemap(I_b))
on the samples drawn at t = T - 1 (Garcia et al. 2024, "Fine-tuning image-conditional diffusion
models is easier than you think"), not weighted by 1/t, which there is 1/999. The physics terms act on the decoded x0
estimate x0 = v_to_x0(x_t, v), decoded WITH gradients (VAE: `decode(checkpoint=True)`). With
physics_first, L_PS is formed with the albedo A_x that the output uses, so it is 0 by construction
(the identity holds exactly) and lambda_ps has no effect; with the free relit branch it uses the
ground-truth albedo, as the paper does.

`relit_target` (image = the paper; residual; gain = ours, the default) and `relit_resolution`
(full = the paper; cell = ours): what the relit branch denoises (pilight.relight.encoding). With
`cell`, the change is one value per codec cell (the pixel-unshuffle factor, or the VAE's 8),
bilinearly interpolated: targets are cell means, outputs are cell-smoothed. Why: SSIM barely
notices a smooth error, but a small UNet's per-pixel errors inside its 4x4 cells read as noise over
every flat region. With physics_first the same resolution applies to the D and S gains.
"""

from __future__ import annotations

import json
import warnings
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from pilight.data import schema
from pilight.data.colour import to_uint8
from pilight.data.schema import DataError
from pilight.data.shards import make_loader, relight_dataset
from pilight.diffusion.codec import cell_mean, cell_smooth
from pilight.diffusion.schedule import sample_timesteps, v_to_x0
from pilight.eval.grids import labelled_grid
from pilight.params import RelightParams, SamplingParams
from pilight.physics import make_feature_extractor, masked_mse, physics_loss
from pilight.physics.calculated import diffuse_calculated
from pilight.relight import physics_first as pf
from pilight.relight.branches import (
    branch_layout,
    branch_targets,
    cond_width,
    condition_images,
    encode_conditions,
    physics_first_images,
)
from pilight.relight.conditions import PRED_DOMAINS, choose_intrinsics, load_condition_predictions
from pilight.relight.encoding import gain_decode, gain_encode, tonemap
from pilight.relight.intensity import BALL_KEYS, relative_pair, to_source_level
from pilight.relight.physics_terms import PHYSICS_SPACE, physics_terms
from pilight.train.build import PREVIEW_SAMPLING, Stack, build_stack
from pilight.train.grad_shares import grad_shares


class RelightTask:
    """The stage-2 Task for pilight.train.loop.train."""

    def __init__(
        self,
        p: RelightParams,
        shard_dir: Path,
        *,
        seed: int,
        pred_dir: Path | None = None,
        device: str = "cpu",
        physics_space: str = PHYSICS_SPACE,
    ):
        self.p, self.shard_dir, self.seed, self.device = p, Path(shard_dir), seed, device
        self.physics_first = p.physics_first
        self.layout = branch_layout(p.decomposition, p.d_calc_condition, p.physics_first)
        self.with_d_calc = any("d_calc" in maps for maps in self.layout.values())
        self.branches = tuple(self.layout)
        self.V = len(self.branches)
        self.width = cond_width(p.decomposition, p.d_calc_condition, p.physics_first)
        codec_channels = _latent_channels(p)
        self.stack: Stack = build_stack(p, num_domains=self.V, cond_channels=self.width * codec_channels)
        self.extractor = make_feature_extractor(p.rec_features, p.dinov2_path)
        self.physics_space = physics_space
        self.samples_per_batch = p.train.batch_size
        self.preview = PREVIEW_SAMPLING
        self.pred_share = {"gt": 0.0, "pred": 1.0, "mix": p.pred_probability}[p.conditions]
        self._calls = 0  # loss() calls, for train.grad_share_every (logging only: no effect on the weights)
        self.preds = None
        if self.pred_share > 0:
            why = f"relight.conditions is {p.conditions!r}" + (
                f" (pred_probability {p.pred_probability})" if p.conditions == "mix" else ""
            )
            self.preds = load_condition_predictions(self.shard_dir, pred_dir, "train", why)
        if not p.decomposition:
            warnings.warn(
                "relight.decomposition is false: no diffuse/specular branches, so L_DS and L_PS are "
                "undefined and logged as 0 (ds_ps_defined = 0)",
                stacklevel=2,
            )

    def describe(self) -> dict[str, Any]:
        return {
            **self.stack.describe(),
            "rec_features": self.extractor.name,
            "relit_target": self.p.relit_target,
            "relit_resolution": self.p.relit_resolution,
            "physics_first": self.physics_first,
            "albedo_source": self.p.albedo_source if self.physics_first else None,
            "source_light": self.p.source_light if self.physics_first else None,
            "specular_anchor": self.p.specular_anchor if self.physics_first else None,
            "physics_space": self.physics_space,
            "branches": list(self.branches),
            "conditions": self.p.conditions,
            "condition_maps": {b: list(m) for b, m in self.layout.items()},
            "d_calc": f"Lambertian lookup of the {self.p.ds_ball} ball x (1 - metallic)",
        }

    def trainable(self) -> torch.nn.Module:
        return self.stack.model

    def to(self, device) -> RelightTask:
        if isinstance(self.stack.codec, torch.nn.Module):
            self.stack.codec.to(device)
        self.extractor.to(device)
        return self

    def batches(self, epoch: int) -> Iterable[Any]:
        ds = relight_dataset(
            self.shard_dir, "train", shuffle=True, seed=self.seed, cross_only=not self.p.identity_pairs
        )
        ds.set_epoch(epoch)
        return make_loader(ds, self.p.train.batch_size, num_workers=self.p.train.num_workers, drop_last=True)

    def _ball(self, balls: dict) -> torch.Tensor:
        """The ball D_calc of the physics terms unfolds (relight.ds_ball), from the target balls in use."""
        if self.p.ds_ball == "lambertian":
            if "ball_lambertian_b" not in balls:
                raise DataError(
                    "relight.ds_ball is 'lambertian' but the shards have no ball_lambertian "
                    "(render.lambertian_ball: true, then re-render)"
                )
            return balls["ball_lambertian_b"]
        return balls["ball_b"]

    def _input_offset(self, z_cond: torch.Tensor) -> torch.Tensor | None:
        """(B * V, C, h, w): z(I_in) on the relit items, 0 on the D/S items; None unless relit_target is residual.

        z(I_in) is read from the relit branch's condition latents (before any CFG drop), so the
        codec encodes the input once per step, not twice."""
        if self.p.relit_target != "residual":
            return None
        lc = self.stack.codec.latent_channels
        i, r = self.layout["relit"].index("image"), self.branches.index("relit")
        per_item = z_cond.unflatten(0, (-1, self.V))
        offset = torch.zeros_like(per_item[:, :, :lc])
        offset[:, r] = per_item[:, r, i * lc : (i + 1) * lc]
        return offset.flatten(0, 1)

    def _relit_target(self, y_b: torch.Tensor, y_a: torch.Tensor) -> torch.Tensor:
        """The relit branch's target image (B, 3, H, W) before encoding: y_b, G (gain), cell means."""
        p, cell = self.p, self.stack.codec.factor
        if p.relit_target == "gain":
            g = gain_encode(y_b, y_a)
            return cell_mean(g, cell) if p.relit_resolution == "cell" else g
        if p.relit_resolution == "cell":  # residual: the latent offset z(y_a) is subtracted after encoding
            return y_a + cell_mean(y_b - y_a, cell)
        return y_b

    def _relit_from_output(self, y: torch.Tensor, y_a: torch.Tensor) -> torch.Tensor:
        """Decoded outputs (B, V, 3, H, W) -> the relit branch as an image (gain decoded, cells smoothed)."""
        p, cell = self.p, self.stack.codec.factor
        r = self.branches.index("relit")
        out = y[:, r]
        if p.relit_target == "gain":
            out = gain_decode(cell_smooth(out, cell) if p.relit_resolution == "cell" else out, y_a)
        elif p.relit_resolution == "cell":
            out = y_a + cell_smooth(out - y_a, cell)
        else:
            return y
        return torch.cat([y[:, :r], out[:, None], y[:, r + 1 :]], dim=1)

    @property
    def _cell(self) -> int:
        """Pixels per side of one physics-first output value: the codec cell with relit_resolution cell, else 1."""
        return self.stack.codec.factor if self.p.relit_resolution == "cell" else 1

    def _conditions(
        self, batch: dict, intr: dict[str, torch.Tensor], dev, intensity: str | None = None
    ) -> tuple[dict, pf.Anchors | None, dict[str, torch.Tensor]]:
        """Condition maps, the physics anchors (physics_first) and the target balls in use, of a pairs batch.

        ``intensity`` (default relight.intensity): relative = the batch's target balls are relative to
        the input's own light and are scaled to its level (pilight.relight.intensity); absolute = as given."""
        image_a, mask = batch["image_a"].to(dev), batch["mask"].to(dev)
        balls = {k: batch[k].to(dev) for k in BALL_KEYS if k in batch}
        rendered = self.physics_first and self.p.albedo_source == "effective" and self.p.source_light == "rendered"
        if rendered and "ball_a" not in batch:
            raise DataError(
                "relight.source_light is 'rendered' but the batch has no ball_a (the input's own light "
                "ball): re-shard with this version, or use source_light: estimated (a photo has no ball)"
            )
        source = None  # the input's own light: (ball, found), when known or needed
        if rendered:
            source = (batch["ball_a"].to(dev), torch.ones(image_a.shape[0], dtype=torch.bool, device=dev))
        elif (
            self.physics_first and self.p.albedo_source == "effective" or (intensity or self.p.intensity) == "relative"
        ):
            source = pf.source_balls(image_a, intr, mask, balls["ball_b"].shape[-1])
        if (intensity or self.p.intensity) == "relative":
            balls = to_source_level(balls, *source)
        ball_b = balls["ball_b"]
        if not self.physics_first:
            return condition_images(image_a, intr, ball_b, mask, self.with_d_calc), None, balls
        effective = self.p.albedo_source == "effective"
        anc = pf.anchors(
            image_a,
            intr,
            mask,
            ball_b,
            balls.get("ball_lambertian_b"),
            albedo_source=self.p.albedo_source,
            ball_a=source[0] if effective else None,
            lambertian_a=batch["ball_lambertian_a"].to(dev) if rendered and "ball_lambertian_a" in batch else None,
            smooth_cell=self._cell,
            specular=self.p.specular_anchor,
            found=source[1] if effective else None,
        )
        return physics_first_images(image_a, intr, ball_b, mask, anc), anc, balls

    def _physics_first_targets(self, batch: dict, anc: pf.Anchors, y_a: torch.Tensor, dev) -> torch.Tensor:
        """(B, 3, 3, H, W): relit gain off the mask (0 on it), g_D of D_eff, g_S of S_b (cell means at cell)."""
        mask = batch["mask"].to(dev).float()
        image_b, spec_b = batch["image_b"].to(dev).float(), batch["specular_b"].to(dev).float()
        g_r = gain_encode(schema.to_model("image", image_b), y_a) * (1 - mask)
        g_d = pf.gain_of(pf.diffuse_target(image_b, spec_b, anc.albedo), anc.d_calc, anc.eps)
        g_s = pf.gain_of(spec_b, anc.s_calc, anc.eps)
        return torch.stack([cell_mean(g, self._cell) for g in (g_r, g_d, g_s)], dim=1)

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

    def loss(
        self, batch: dict, generator: torch.Generator, model: torch.nn.Module | None = None
    ) -> tuple[torch.Tensor, dict[str, float]]:
        """``model``: what the loop prepared (a DDP wrapper under several processes); default the stack's."""
        s, V, p = self.stack, self.V, self.p
        model = s.model if model is None else model
        dev = next(s.model.parameters()).device
        B = batch["image_a"].shape[0]
        if p.intensity == "relative":  # told r = level(ball_b) / level(ball_a), as a user states k
            batch = relative_pair(batch)
        # Draw order (fixed, for exact resume): t, conditions source, CFG drop, noise.
        t = sample_timesteps(B, s.scheduler.config.num_train_timesteps, p.train.terminal_fraction, generator)
        use_pred = torch.rand(B, generator=generator) < self.pred_share
        drop = torch.rand(B, generator=generator) < p.train.cond_dropout  # CFG needs an unconditional model
        intr = {k: v.to(dev) for k, v in choose_intrinsics(batch, use_pred, self.preds).items()}
        mask = batch["mask"].to(dev)
        with torch.no_grad():
            maps, anc, balls = self._conditions(batch, intr, dev)
            z_cond = encode_conditions(s.codec, maps, self.layout, self.width)
            if anc is not None:
                targets = self._physics_first_targets(batch, anc, maps["image"], dev)
            else:
                targets = branch_targets(batch, self.branches).to(dev).float()
                r = self.branches.index("relit")
                targets[:, r] = self._relit_target(targets[:, r], maps["image"])
            z0 = s.codec.encode(targets.flatten(0, 1))
            offset = self._input_offset(z_cond)
            if offset is not None:
                z0 = z0 - offset
        noise = torch.randn(z0.shape, generator=generator).to(dev)
        drop, tv = drop.to(dev), t.repeat_interleave(V).to(dev)  # one timestep per sample, shared by its branches
        x_t = s.scheduler.add_noise(z0, noise, tv)
        z_cond = z_cond * (~drop).repeat_interleave(V).to(z_cond.dtype)[:, None, None, None]
        ids = torch.arange(V, device=dev).repeat(B)
        v = model(x_t, z_cond, tv, ids, condition_images=maps["image"], drop=drop).float()
        alphas = s.alphas_cumprod(dev)
        l_v = F.mse_loss(v, s.scheduler.get_velocity(z0, noise, tv).float())
        lambdas = (p.lambda_ds, p.lambda_ps, p.lambda_rec)
        logs = {
            "l_vpred": float(l_v.detach()),
            "pred_conditions": float(use_pred.float().mean()),
            "ds_ps_defined": float(p.decomposition),
            "t_mean": float(t.float().mean()),
        }
        if not any(lambdas) and not p.lambda_image:  # the no-physics ablation: no decode at all
            logs.update(l_ds=0.0, l_ps=0.0, l_rec=0.0, l_physics=0.0, l_image=0.0)
            return l_v, logs
        x0 = v_to_x0(x_t.float(), v, alphas, tv)
        if offset is not None:
            x0 = x0 + offset
        decoded = s.codec.decode(x0, checkpoint=True).float().unflatten(0, (B, V))
        albedo = batch["albedo"].to(dev)
        if anc is not None:  # physics_first: the physics terms see the formed outputs, and A_x in L_PS
            lin = self._physics_first_outputs(decoded, anc, maps["image"], mask)
            y = torch.stack([tonemap(lin[b]) for b in self.branches], dim=1)
            albedo = lin["albedo"]
        else:
            y = self._relit_from_output(decoded, maps["image"])
        d_calc = None
        if p.decomposition:
            with torch.no_grad():
                d_calc = diffuse_calculated(self._ball(balls), batch["normal"].to(dev), mask, batch["metallic"].to(dev))
        terms = physics_terms(
            y,
            albedo=albedo,
            d_calc=d_calc,
            mask=mask,
            image_a=batch["image_a"].to(dev),
            extractor=self.extractor,
            space=self.physics_space,
            ps_on_mask=anc is not None,
        )
        phys = physics_loss(t.to(dev), terms["ds"], terms["ps"], terms["rec"], lambdas, p.t_min)
        logs.update({f"l_{k}": float(v.detach().mean()) for k, v in terms.items()})
        logs["l_physics"] = float(phys.detach())
        # E2E-FT's task loss where single-step inference runs: the formed relit image against the target,
        # in display space, on the samples at t = T-1 only (elsewhere x0 is a noisy estimate).
        terminal = (t == s.scheduler.config.num_train_timesteps - 1).to(dev, torch.float32)
        l_img = masked_mse(y[:, 0], tonemap(batch["image_b"].to(dev).float()), reduction="none")
        logs["l_image"] = float((l_img.detach() * terminal).sum() / terminal.sum().clamp_min(1))
        l_image = p.lambda_image * (l_img * terminal).mean()
        self._calls += 1
        if p.train.grad_share_every and self._calls % p.train.grad_share_every == 0:
            w = 1.0 / t.to(dev).float().clamp_min(p.t_min)  # each physics term as physics_loss weighs it
            weighted = {k: (w * lam * terms[k]).mean() for k, lam in zip(("ds", "ps", "rec"), lambdas)}
            shares = grad_shares({"vpred": l_v, **weighted, "image": l_image}, _trainable(self.stack.model))
            logs.update(shares)
        return l_v + phys + l_image, logs

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
        intr = {d: (intr or batch)[d].to(dev) for d in PRED_DOMAINS}
        image_a = batch["image_a"].to(dev)
        B = image_a.shape[0]
        maps, anc, _ = self._conditions(batch, intr, dev, intensity)
        if zero_gains:
            if anc is None:
                raise ValueError(
                    "zero_gains is the physics-first anchor; this model has no anchor (physics_first: false)"
                )
            zero = torch.zeros(B, V, 3, *image_a.shape[-2:], device=dev)
            out = self._physics_first_outputs(zero, anc, maps["image"], batch["mask"].to(dev))
            return {k: v.clamp(0, schema.HDR_MAX) for k, v in out.items()}
        z_cond = encode_conditions(s.codec, maps, self.layout, self.width)
        ids = torch.arange(V, device=dev).repeat(B)
        z0 = s.sample(z_cond, ids, maps["image"], V, sp, generator)
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

    @torch.no_grad()
    def images(self, batch: dict) -> dict[str, np.ndarray]:
        """Rows: input | target | relit; then D_calc | D truth | D model and S_calc | S truth | S model
        (the first pair), labelled."""
        one = {k: v[:1] for k, v in batch.items()}
        pred = self.predict(
            relative_pair(one) if self.p.intensity == "relative" else one,
            self.preview,
            torch.Generator().manual_seed(0),
        )
        u8 = lambda x: to_uint8(x[0].cpu(), hdr=True)
        rows = [[u8(one["image_a"]), u8(one["image_b"]), u8(pred["relit"])]]
        labels = ["relit"]
        if "diffuse" in pred:
            balls = relative_pair(one) if self.p.intensity == "relative" else one
            d_calc = diffuse_calculated(self._ball(balls), one["normal"], one["mask"], one["metallic"])
            rows.append([u8(d_calc), u8(one["diffuse_b"]), u8(pred["diffuse"])])
            rows.append([None, u8(one["specular_b"]), u8(pred["specular"])])
            labels += ["D", "S"]
        return {"relight_grid": labelled_grid(rows, ["input / physics", "truth", "model"], row_labels=labels)}


def _latent_channels(p: RelightParams) -> int:
    """The codec's latent width without building the UNet (pixel: 3 f^2; VAE: from its config)."""
    if p.codec.kind == "pixel":
        return 3 * p.codec.factor**2
    try:
        return int(json.loads((Path(p.codec.path) / "config.json").read_text()).get("latent_channels", 4))
    except (OSError, ValueError):
        return 4  # build_stack then reports the broken VAE folder itself


def _trainable(model: torch.nn.Module) -> list[torch.nn.Parameter]:
    return [prm for prm in model.parameters() if prm.requires_grad]
