"""Stage 2, physics-inspired neural forward rendering: (input image, intrinsics, target light) ->
relit image, diffuse shading D and specular S together (paper, Sec. "Stage 2"), as the Task that
pilight.train.loop.train runs.

The parts, each in a file named for it under pilight/relight/:
- branches.py: the three branches (relit, diffuse, specular) and the condition maps each reads;
- encoding.py: how the relit branch's change is encoded (form.target gain) and the physics tone map;
- physics_first.py: the physics-first output (ours, relight.form kind physics_first): on the mask
  I_relit = A_x D_pred + S_pred with D and S as gains on their physics lookups;
- physics_terms.py: the paper's L_DS, L_PS, L_rec;
- objective.py: the whole loss, L = L_vpred + (1/max(t, t_min)) (lambda_ds L_DS + lambda_ps L_PS +
  lambda_rec L_rec) + lambda_image L_image, every weight in one place;
- conditions.py: ground-truth or stage-1-predicted intrinsics as conditions.

This Task forms what the objective reads: the batch, the targets, and the decoded x0 estimate
x0 = v_to_x0(x_t, v), decoded WITH gradients (VAE: `decode(checkpoint=True)`). With physics_first,
L_PS is formed with the albedo A_x that the output uses, so it is 0 by construction (the identity
holds exactly) and lambda_ps has no effect; with the free relit branch it uses the ground-truth
albedo, as the paper does.

`relight.form` (pilight.params): what the relit branch denoises (pilight.relight.encoding). The free
form (the paper's) has its `target` (image = the paper; residual; gain = ours) and `resolution`
(full = the paper; cell = ours); physics_first (ours, the default) always denoises a gain. With
`cell`, the change is one value per codec cell (the pixel-unshuffle factor, or the VAE's 8),
bilinearly interpolated: targets are cell means, outputs are cell-smoothed. Why: SSIM barely
notices a smooth error, but a small UNet's per-pixel errors inside its 4x4 cells read as noise over
every flat region. With physics_first the same resolution applies to the D and S gains.
"""

from __future__ import annotations

import warnings
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from pilight.data import schema
from pilight.data.schema import DataError
from pilight.data.shard_reader import make_loader, relight_dataset
from pilight.diffusion.codec import cell_mean
from pilight.diffusion.schedule import sample_timesteps, v_to_x0
from pilight.eval.grids import labelled_grid
from pilight.models.relight import RelightModel
from pilight.models.stack import PREVIEW_SAMPLING
from pilight.params import RelightParams
from pilight.physics import make_feature_extractor
from pilight.physics.calculated import diffuse_calculated
from pilight.pictures import to_uint8
from pilight.relight import objective
from pilight.relight import physics_first as pf
from pilight.relight.branches import (
    branch_targets,
    encode_conditions,
)
from pilight.relight.conditions import choose_intrinsics, load_condition_predictions
from pilight.relight.encoding import gain_encode, tonemap
from pilight.relight.intensity import relative_pair
from pilight.relight.physics_terms import PHYSICS_SPACE, physics_terms
from pilight.train.grad_shares import grad_shares


class RelightTask(RelightModel):
    """The stage-2 Task for pilight.train.loop.train: the inference model (pilight.models.relight) and what
    training adds to it (batches, the predicted conditions, targets, the loss, the previews)."""

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
        super().__init__(p)
        self.shard_dir, self.seed, self.device = Path(shard_dir), seed, device
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
        return super().describe() | {
            "rec_features": self.extractor.name,
            "physics_space": self.physics_space,
            "conditions": self.p.conditions,
        }

    def trainable(self) -> torch.nn.Module:
        return self.stack.model

    def to(self, device) -> RelightTask:  # the loop places the UNet itself (accelerate)
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

    def _relit_target(self, y_b: torch.Tensor, y_a: torch.Tensor) -> torch.Tensor:
        """The relit branch's target image (B, 3, H, W) before encoding: y_b, G (gain), cell means."""
        form, cell = self.form, self.stack.codec.factor
        if form.target == "gain":
            g = gain_encode(y_b, y_a)
            return cell_mean(g, cell) if form.resolution == "cell" else g
        if form.resolution == "cell":  # residual: the latent offset z(y_a) is subtracted after encoding
            return y_a + cell_mean(y_b - y_a, cell)
        return y_b

    def _physics_first_targets(self, batch: dict, anc: pf.Anchors, y_a: torch.Tensor, dev) -> torch.Tensor:
        """(B, 3, 3, H, W): relit gain off the mask (0 on it), g_D of D_eff, g_S of S_b (cell means at cell)."""
        mask = batch["mask"].to(dev).float()
        image_b, spec_b = batch["image_b"].to(dev).float(), batch["specular_b"].to(dev).float()
        g_r = gain_encode(schema.to_model("image", image_b), y_a) * (1 - mask)
        g_d = pf.gain_of(pf.diffuse_target(image_b, spec_b, anc.albedo), anc.d_calc, anc.eps)
        g_s = pf.gain_of(spec_b, anc.s_calc, anc.eps)
        return torch.stack([cell_mean(g, self._cell) for g in (g_r, g_d, g_s)], dim=1)

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
        v = model(x_t, z_cond, tv, ids, condition_images=self.attention_images(maps), drop=drop).float()
        alphas = s.alphas_cumprod(dev)
        l_v = objective.vpred_loss(v, s.scheduler.get_velocity(z0, noise, tv))
        logs = {
            "l_vpred": float(l_v.detach()),
            "pred_conditions": float(use_pred.float().mean()),
            "ds_ps_defined": float(p.decomposition),
            "t_mean": float(t.float().mean()),
        }
        if not objective.needs_decode(p):  # the no-physics ablation: no decode at all
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
        phys = objective.physics_part(t.to(dev), terms, p)
        logs.update({f"l_{k}": float(v.detach().mean()) for k, v in terms.items()})
        logs["l_physics"] = float(phys.detach())
        l_img, logs["l_image"] = objective.image_loss(
            y[:, 0], batch["image_b"].to(dev), t.to(dev), s.scheduler.config.num_train_timesteps
        )
        l_image = p.lambda_image * l_img
        self._calls += 1
        if p.train.grad_share_every and self._calls % p.train.grad_share_every == 0:
            weighted = objective.weighted_terms(t.to(dev), terms, p)
            shares = grad_shares({"vpred": l_v, **weighted, "image": l_image}, _trainable(self.stack.model))
            logs.update(shares)
        return l_v + phys + l_image, logs

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


def _trainable(model: torch.nn.Module) -> list[torch.nn.Parameter]:
    return [prm for prm in model.parameters() if prm.requires_grad]
