"""Stage 2, physics-inspired neural forward rendering: (input image, intrinsics, target light) ->
relit image, diffuse shading D and specular S together (paper, Sec. "Stage 2").

Batch layout: each pair becomes V = 3 batch items (sample-major), one per branch, told apart by
one-hot domain labels and denoised at one shared timestep; cross-batch attention lets the three
branches see each other. The paper's inputs and outputs per branch:

    branch 0  relit     I_in1 = (I_in, A)          -> I_relit
    branch 1  diffuse   I_in2 = (N, L, m)          -> D_pred
    branch 2  specular  I_in3 = (N, L, M, R, m)    -> S_pred

Every condition map is a 3-channel image in [-1, 1] (1-channel M, R, m replicated; N as is; the
light ball L resized bilinearly to the image size and tone-mapped like any HDR map), encoded by the
codec ON ITS OWN, and the latents are concatenated on channels. The three branches have 2, 3 and 5
maps; all are zero-padded to the width of 5 so ONE UNet (one input width) serves all three: the
branch's one-hot label says which layout its condition channels hold, and zero is also what
classifier-free guidance feeds for "no condition". `decomposition: false` (the paper's ablation)
keeps only the relit branch (V = 1) and gives it every map (I_in, A, N, L, M, R, m), so the
ablation removes the decomposition, not the information about the target light.

Loss (paper, final loss):

    L = L_vpred + (1/max(t, t_min)) (lambda_ds L_DS + lambda_ps L_PS + lambda_rec L_rec)

L_vpred = MSE(v, v_target) on the latents of all branches. The physics terms act on the decoded x0
estimate x0 = v_to_x0(x_t, v), decoded WITH gradients (VAE: `decode(checkpoint=True)`):

* L_DS = MSE(D_calc, D_pred) on the mask, D_calc = diffuse_shading(unfold(target ball), N_gt, m).
  ADAPTATION: our render contract defines D = k * L_diffuse with k = (1 - metallic)(1 - specular
  layer albedo) so that A*D + S is exact, while D_calc is Lambertian shading (k = 1). We use
  D_calc * (1 - metallic): metals (D = 0 in our ground truth) are not pulled toward Lambertian
  shading. The dielectric specular-layer factor (a few %) is not modelled.
* L_PS = MSE(I_relit, A * D_pred + S_pred), with the GROUND-TRUTH albedo (the targets satisfy the
  identity exactly with it, so L_PS never fights L_vpred even when the model is conditioned on
  stage-1 predicted albedo).
* L_rec = ||phi(I_relit) - phi(I_in)||^2 with `make_feature_extractor(rec_features)` (its name is
  logged; "pooled-rgb" is NOT DINO).

Space of the physics MSEs (PHYSICS_SPACE, default "tonemapped"): the relations (A*D + S, D_calc)
are formed in LINEAR HDR, then both sides are compared after the schema's tone map (hdr_to_model,
[-1, 1)); L_rec sees tone-mapped images in [0, 1]. Raw-HDR MSEs are unbounded: decoded x0 at high
noise maps to HDR values in the thousands and the squared error (and its gradient through
model_to_hdr, ~(1+h)^2) dwarfs L_vpred. To keep gradients finite, decoded outputs are clamped to
model values of at most hdr_to_model(PHYS_HDR_MAX) before the inverse tone map, and the tone map
adds TONEMAP_EPS (its 1/2.2 power has an infinite slope at 0).

`relit_target: residual` (ours, default image = the paper): the relit branch denoises
z(I_relit) - z(I_in) instead of z(I_relit), and z(I_in) is added back to its x0 before anything is
decoded (physics terms, inference). A relit image mostly repeats its input, so "copy the input" is
then the zero prediction and a model trained for a few hundred CPU steps starts from it instead of
having to learn the identity through the UNet. The D and S branches are unchanged.

`relit_target: gain` (ours): the relit branch denoises the log ratio of display values,
G = log((u_b + GAIN_EPS) / (u_a + GAIN_EPS)) / GAIN_SCALE with u = (y + 1) / 2 of the schema's tone
map, and decodes to u_relit = (u_a + GAIN_EPS) exp(GAIN_SCALE G) - GAIN_EPS. "Copy the input" is again
the zero prediction, but the input's texture now enters multiplicatively: where only shading
changes (u ~ (A D)^(1/2.2) below the Reinhard knee), G is the shading ratio (D_b / D_a)^(1/2.2), free
of texture. The residual target z(I_b) - z(I_a) is that ratio TIMES the input's texture, which a
small UNet reproduces with errors at every pixel of its 4x4 pixel-unshuffle cells, and those
errors are what SSIM punishes (README, "Where the SSIM deficit lives"). GAIN_EPS keeps black
pixels (background, deep shadow) finite: there G is bounded by log((1 + eps) / eps).

`relit_resolution: cell` (ours; `full` is the paper's per-pixel output): the relit branch's change
(its residual or G) is one value per codec cell (the pixel-unshuffle factor, or the VAE's 8),
bilinearly interpolated to pixels. Targets are the cell means, repeated over the cell; the decoded
change is averaged over each cell, then interpolated. Why: SSIM barely notices a smooth additive
or multiplicative error, but a small UNet's per-pixel errors inside its 4x4 cells read as noise
over every flat region, and a smooth change cannot add any. The cost: no change sharper than a
cell (moving shadow edges blur over 4 pixels). Needs relit_target residual or gain.

`d_calc_condition` (ours, default () = the paper): the named branches also read D_calc, the
Lambertian lookup of the target (gray) ball with the CONDITIONING normals and metallic, as one more
condition map. It holds no information the branch lacks (N and L are there), but reading the ball
where it faces like this pixel is a non-local lookup that a small UNet trained from scratch does
not learn in a CPU budget. The relit branch, which in the paper sees only (I_in, A), otherwise
hears of the target light only through cross-batch attention.

When decomposition is false there are no D/S branches: L_DS and L_PS are 0 (logged as such, with
`ds_ps_defined = 0`).
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path
from typing import Any, Iterable

import numpy as np
import torch
import torch.nn.functional as F

from pilight.data import schema
from pilight.data.pairs import read_pairs
from pilight.data.predictions import read_predictions
from pilight.data.schema import DataError
from pilight.data.shards import make_loader, relight_dataset
from pilight.diffusion.codec import cell_mean, cell_smooth
from pilight.diffusion.sampler import sample
from pilight.diffusion.schedule import sample_timesteps, v_target, v_to_x0
from pilight.params import RelightParams, SamplingParams
from pilight.physics import compose, make_feature_extractor, masked_mse, physics_loss, reconstruction_loss
from pilight.physics.calculated import diffuse_calculated
from pilight.train.build import PREVIEW_SAMPLING, Stack, build_stack
from pilight.train.intrinsics import to_uint8

BRANCHES = ("relit", "diffuse", "specular")  # one-hot order = domain ids 0, 1, 2
TARGETS = {"relit": "image_b", "diffuse": "diffuse_b", "specular": "specular_b"}
BRANCH_MAPS = {"relit": ("image", "albedo"), "diffuse": ("normal", "ball", "mask"),
               "specular": ("normal", "ball", "metallic", "roughness", "mask")}
ABLATION_MAPS = ("image", "albedo", "normal", "ball", "metallic", "roughness", "mask")  # decomposition: false
PRED_DOMAINS = ("albedo", "normal", "roughness", "metallic")  # what stage 1 predicts; the mask stays GT
PHYS_HDR_MAX = 64.0
Y_PHYS = float(schema.hdr_to_model(np.float64(PHYS_HDR_MAX)))
TONEMAP_EPS = 1e-6
PHYSICS_SPACE = "tonemapped"
GAIN_EPS = 0.05  # display-value floor of relit_target gain (u in [0, 1]; mid-gray 0.18 linear is u ~ 0.42)
GAIN_SCALE = 2.0  # G = log ratio / GAIN_SCALE: |G| <= log(1.05 / 0.05) / 2 = 1.52, the range of the other targets
GAIN_MAX = float(np.log((1.0 + GAIN_EPS) / GAIN_EPS) / GAIN_SCALE)


def branch_layout(decomposition: bool, d_calc_branches: tuple[str, ...] = ()) -> dict[str, tuple[str, ...]]:
    """Condition maps per branch. ``d_calc_branches`` (relight.d_calc_condition) also get "d_calc";
    without decomposition the one branch gets it when any branch is named (the ablation keeps every
    input, as with ABLATION_MAPS)."""
    if not decomposition:
        return {"relit": ABLATION_MAPS + (("d_calc",) if d_calc_branches else ())}
    return {b: maps + (("d_calc",) if b in d_calc_branches else ()) for b, maps in BRANCH_MAPS.items()}


def cond_width(decomposition: bool, d_calc_branches: tuple[str, ...] = ()) -> int:
    """Condition maps per item after padding: the widest branch (5, or 6 with D_calc), or 7 (8) for the ablation."""
    return max(len(m) for m in branch_layout(decomposition, d_calc_branches).values())


def gain_encode(y_b: torch.Tensor, y_a: torch.Tensor) -> torch.Tensor:
    """relit_target gain: model-space target y_b and input y_a ([-1, 1)) -> G (module docstring)."""
    u_b, u_a = (y_b.float() + 1) / 2, (y_a.float() + 1) / 2
    return torch.log((u_b.clamp_min(0) + GAIN_EPS) / (u_a.clamp_min(0) + GAIN_EPS)) / GAIN_SCALE


def gain_decode(g: torch.Tensor, y_a: torch.Tensor) -> torch.Tensor:
    """Inverse of gain_encode: G and the input y_a -> the relit image in model space [-1, 1)."""
    u_a = ((y_a.float() + 1) / 2).clamp_min(0)
    u = (u_a + GAIN_EPS) * torch.exp(GAIN_SCALE * g.float().clamp(-GAIN_MAX, GAIN_MAX)) - GAIN_EPS
    return 2 * u.clamp(0.0, 1.0 - 1e-6) - 1


def tonemap(x: torch.Tensor) -> torch.Tensor:
    """Linear HDR -> [-1, 1) like schema.hdr_to_model, with a finite slope at 0 (for gradients)."""
    u = x.clamp_min(0.0) * schema.EXPOSURE + TONEMAP_EPS
    return 2.0 * (u / (1.0 + u)) ** (1.0 / schema.GAMMA) - 1.0


def to_linear(y: torch.Tensor) -> torch.Tensor:
    """Decoded model-space output -> linear HDR, clamped to [0, PHYS_HDR_MAX] (gradients stay finite)."""
    return schema.model_to_hdr(y.clamp(-1.0, Y_PHYS))


def condition_images(image_a: torch.Tensor, intr: dict[str, torch.Tensor], ball: torch.Tensor,
                     mask: torch.Tensor, with_d_calc: bool = False) -> dict[str, torch.Tensor]:
    """Every condition map as a (B, 3, H, W) image in [-1, 1] (linear inputs, schema mappings).

    ``with_d_calc`` adds "d_calc": the Lambertian lookup of this (gray) ball with the CONDITIONING
    normals and metallic, i.e. a function of inputs the branch already has. It only spares the
    UNet the non-local lookup (which ball pixel faces the same way as this normal), which a small
    model trained from scratch does not learn in a CPU budget."""
    h, w = image_a.shape[-2:]
    up = F.interpolate(ball.float(), size=(h, w), mode="bilinear", align_corners=False).clamp_min(0)
    rep = lambda x: x.expand(-1, 3, -1, -1) if x.shape[1] == 1 else x
    maps = {"image": schema.to_model("image", image_a), "albedo": schema.to_model("albedo", intr["albedo"]),
            "normal": schema.to_model("normal", intr["normal"]), "ball": schema.to_model("ball", up),
            "metallic": rep(schema.to_model("metallic", intr["metallic"])),
            "roughness": rep(schema.to_model("roughness", intr["roughness"])),
            "mask": rep(schema.to_model("mask", mask))}
    if with_d_calc:
        maps["d_calc"] = schema.to_model("image", diffuse_calculated(ball, intr["normal"], mask, intr["metallic"]))
    return maps


def encode_conditions(codec, maps: dict[str, torch.Tensor], layout: dict[str, tuple[str, ...]],
                      width: int) -> torch.Tensor:
    """(B * V, width * latent_channels, h, w): per branch its maps' latents, concatenated, zero-padded."""
    names = sorted({n for ms in layout.values() for n in ms})
    B = maps[names[0]].shape[0]
    z = codec.encode(torch.cat([maps[n] for n in names]).float())
    lat = dict(zip(names, z.split(B)))
    lc = z.shape[1]
    per_branch = []
    for ms in layout.values():
        c = torch.cat([lat[n] for n in ms], dim=1)
        per_branch.append(F.pad(c, (0, 0, 0, 0, 0, (width - len(ms)) * lc)))
    return torch.stack(per_branch, dim=1).flatten(0, 1)


def branch_targets(batch: dict, branches: tuple[str, ...]) -> torch.Tensor:
    """(B, V, 3, H, W) targets in [-1, 1] (all HDR)."""
    return torch.stack([schema.to_model("image", batch[TARGETS[b]]) for b in branches], dim=1)


def physics_terms(y: torch.Tensor, *, albedo: torch.Tensor, d_calc: torch.Tensor | None, mask: torch.Tensor,
                  image_a: torch.Tensor, extractor, space: str = PHYSICS_SPACE) -> dict[str, torch.Tensor]:
    """Per-sample (B,) L_DS, L_PS, L_rec from decoded outputs y (B, V, 3, H, W) in model space.

    V = 3 (relit, diffuse, specular) or V = 1 (relit only: L_DS = L_PS = 0). `space`: "tonemapped"
    (default) or "linear" (raw HDR, for comparison; see the module docstring)."""
    if space not in ("tonemapped", "linear"):
        raise ValueError(f"physics space must be 'tonemapped' or 'linear', got {space!r}")
    y = y.float()
    B = y.shape[0]
    relit_lin = to_linear(y[:, 0])
    relit_tm = tonemap(relit_lin)
    rec = reconstruction_loss((relit_tm + 1) / 2, (tonemap(image_a.float()) + 1) / 2, extractor, reduction="none")
    if y.shape[1] == 1:
        zero = torch.zeros(B, device=y.device)
        return {"ds": zero, "ps": zero, "rec": rec}
    d_lin, s_lin = to_linear(y[:, 1]), to_linear(y[:, 2])
    composed = compose(albedo.float(), d_lin, s_lin)
    if space == "tonemapped":
        ds = masked_mse(tonemap(d_calc), tonemap(d_lin), mask, reduction="none")
        ps = masked_mse(relit_tm, tonemap(composed), reduction="none")
    else:
        ds = masked_mse(d_calc, d_lin, mask, reduction="none")
        ps = masked_mse(relit_lin, composed, reduction="none")
    return {"ds": ds, "ps": ps, "rec": rec}


def _sample_keys(batch: dict) -> list[str]:
    """Stage-1 prediction keys of the INPUT images: `<scene>_vNN_lNN` of meta_a."""
    metas = [json.loads(m) if isinstance(m, str) else m for m in batch["meta_a"]]
    return [schema.sample_key(m["scene"], m["view"], m["light"]) for m in metas]


def load_condition_predictions(shard_dir: Path, pred_dir: Path | None, split: str,
                               why: str) -> dict[str, dict[str, np.ndarray]]:
    """Stage-1 predictions for every input image of `split`'s pairs; DataError naming what is missing."""
    if pred_dir is None or not (Path(pred_dir) / "index.json").is_file():
        raise DataError(f"{why} needs stage-1 predictions of the {split!r} split, but {pred_dir}/index.json "
                        "was not found: run infer_intrinsics (with infer_intrinsics.splits including "
                        f"{split!r}) first, or set relight.conditions: gt")
    try:
        preds = read_predictions(Path(pred_dir), split)
    except DataError as exc:
        raise DataError(f"{why}: {exc}") from None
    needed = sorted({schema.sample_key(p.scene, p.view, p.a) for p in read_pairs(Path(shard_dir) / "pairs" / f"{split}.tsv")})
    missing = [k for k in needed if k not in preds]
    if missing:
        raise DataError(f"{why}: {pred_dir} has no {split!r} predictions for {len(missing)} input image(s), e.g. "
                        f"{missing[:3]}; rerun infer_intrinsics on the current shards")
    short = sorted({d for k in needed for d in PRED_DOMAINS if d not in preds[k]})
    if short:
        raise DataError(f"{why}: {pred_dir} lacks predicted {short} (infer_intrinsics.domains must "
                        f"include all of {list(PRED_DOMAINS)})")
    return preds


def optional_predictions(shard_dir: Path, pred_dir: Path, split: str, why: str) -> dict | None:
    """Stage-1 predictions of ``split`` when ``pred_dir`` holds them, else None: the caller then
    conditions on ground truth and must say so in what it writes."""
    index = Path(pred_dir) / "index.json"
    if not index.is_file() or split not in json.loads(index.read_text()).get("splits", {}):
        return None
    return load_condition_predictions(shard_dir, pred_dir, split, why)


def choose_intrinsics(batch: dict, use_pred: torch.Tensor, preds: dict | None) -> dict[str, torch.Tensor]:
    """Per sample: stage-1 predictions of image a where use_pred, ground truth elsewhere."""
    out = {d: batch[d].clone() for d in PRED_DOMAINS}
    if not bool(use_pred.any()):
        return out
    for i, key in enumerate(_sample_keys(batch)):
        if not use_pred[i]:
            continue
        if preds is None or key not in preds:
            raise DataError(f"no stage-1 prediction for input image {key}")
        for d in PRED_DOMAINS:
            out[d][i] = torch.from_numpy(preds[key][d]).permute(2, 0, 1).to(out[d])
    return out


class RelightTask:
    """The stage-2 Task for pilight.train.loop.train."""

    def __init__(self, p: RelightParams, shard_dir: Path, *, seed: int, pred_dir: Path | None = None,
                 device: str = "cpu", physics_space: str = PHYSICS_SPACE):
        self.p, self.shard_dir, self.seed, self.device = p, Path(shard_dir), seed, device
        self.layout = branch_layout(p.decomposition, p.d_calc_condition)
        self.with_d_calc = any("d_calc" in maps for maps in self.layout.values())
        self.branches = tuple(self.layout)
        self.V = len(self.branches)
        self.width = cond_width(p.decomposition, p.d_calc_condition)
        codec_channels = _latent_channels(p)
        self.stack: Stack = build_stack(p, num_domains=self.V, cond_channels=self.width * codec_channels)
        self.extractor = make_feature_extractor(p.rec_features, p.dinov2_path)
        self.physics_space = physics_space
        self.samples_per_batch = p.train.batch_size
        self.preview = PREVIEW_SAMPLING
        self.pred_share = {"gt": 0.0, "pred": 1.0, "mix": p.pred_probability}[p.conditions]
        self.preds = None
        if self.pred_share > 0:
            why = f"relight.conditions is {p.conditions!r}" + (f" (pred_probability {p.pred_probability})" if p.conditions == "mix" else "")
            self.preds = load_condition_predictions(self.shard_dir, pred_dir, "train", why)
        if not p.decomposition:
            warnings.warn("relight.decomposition is false: no diffuse/specular branches, so L_DS and L_PS are "
                          "undefined and logged as 0 (ds_ps_defined = 0)", stacklevel=2)

    def describe(self) -> dict[str, Any]:
        return {**self.stack.describe(), "rec_features": self.extractor.name, "relit_target": self.p.relit_target,
                "relit_resolution": self.p.relit_resolution,
                "physics_space": self.physics_space,
                "branches": list(self.branches), "conditions": self.p.conditions,
                "condition_maps": {b: list(m) for b, m in self.layout.items()},
                "d_calc": f"Lambertian lookup of the {self.p.ds_ball} ball x (1 - metallic)"}

    def trainable(self) -> torch.nn.Module:
        return self.stack.model

    def to(self, device) -> "RelightTask":
        if isinstance(self.stack.codec, torch.nn.Module):
            self.stack.codec.to(device)
        self.extractor.to(device)
        return self

    def batches(self, epoch: int) -> Iterable[Any]:
        ds = relight_dataset(self.shard_dir, "train", shuffle=True, seed=self.seed)
        ds.set_epoch(epoch)
        return make_loader(ds, self.p.train.batch_size, num_workers=self.p.train.num_workers, drop_last=True)

    def _ball(self, batch: dict) -> torch.Tensor:
        if self.p.ds_ball == "lambertian":
            if "ball_lambertian_b" not in batch:
                raise DataError("relight.ds_ball is 'lambertian' but the shards have no ball_lambertian "
                                "(render.lambertian_ball: true, then re-render)")
            return batch["ball_lambertian_b"]
        return batch["ball_b"]

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
        offset[:, r] = per_item[:, r, i * lc:(i + 1) * lc]
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
        return torch.cat([y[:, :r], out[:, None], y[:, r + 1:]], dim=1)

    def loss(self, batch: dict, generator: torch.Generator) -> tuple[torch.Tensor, dict[str, float]]:
        s, V, p = self.stack, self.V, self.p
        dev = next(s.model.parameters()).device
        B = batch["image_a"].shape[0]
        # Draw order (fixed, for exact resume): t, conditions source, CFG drop, noise.
        t = sample_timesteps(B, s.scheduler.config.num_train_timesteps, p.train.terminal_fraction, generator)
        use_pred = torch.rand(B, generator=generator) < self.pred_share
        drop = torch.rand(B, generator=generator) < p.train.cond_dropout  # CFG needs an unconditional model
        intr = {k: v.to(dev) for k, v in choose_intrinsics(batch, use_pred, self.preds).items()}
        mask = batch["mask"].to(dev)
        with torch.no_grad():
            maps = condition_images(batch["image_a"].to(dev), intr, batch["ball_b"].to(dev), mask, self.with_d_calc)
            z_cond = encode_conditions(s.codec, maps, self.layout, self.width)
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
        ehs = s.encode_condition(maps["image"], drop)
        z_cond = z_cond * (~drop).repeat_interleave(V).to(z_cond.dtype)[:, None, None, None]
        ids = torch.arange(V, device=dev).repeat(B)
        v = s.model(x_t, z_cond, tv, ids, ehs.repeat_interleave(V, 0)).float()
        alphas = s.alphas_cumprod(dev)
        l_v = F.mse_loss(v, v_target(z0, noise, alphas, tv).float())
        lambdas = (p.lambda_ds, p.lambda_ps, p.lambda_rec)
        logs = {"l_vpred": float(l_v.detach()), "pred_conditions": float(use_pred.float().mean()),
                "ds_ps_defined": float(p.decomposition), "t_mean": float(t.float().mean())}
        if not any(lambdas):  # the no-physics ablation: no decode at all
            logs.update(l_ds=0.0, l_ps=0.0, l_rec=0.0, l_physics=0.0)
            return l_v, logs
        x0 = v_to_x0(x_t.float(), v, alphas, tv)
        if offset is not None:
            x0 = x0 + offset
        y = self._relit_from_output(s.codec.decode(x0, checkpoint=True).float().unflatten(0, (B, V)), maps["image"])
        d_calc = None
        if p.decomposition:
            with torch.no_grad():
                d_calc = diffuse_calculated(self._ball(batch).to(dev), batch["normal"].to(dev), mask,
                                            batch["metallic"].to(dev))
        terms = physics_terms(y, albedo=batch["albedo"].to(dev), d_calc=d_calc, mask=mask,
                              image_a=batch["image_a"].to(dev), extractor=self.extractor, space=self.physics_space)
        phys = physics_loss(t.to(dev), terms["ds"], terms["ps"], terms["rec"], lambdas, p.t_min)
        logs.update({f"l_{k}": float(v.detach().mean()) for k, v in terms.items()})
        logs["l_physics"] = float(phys.detach())
        return l_v + phys, logs

    @torch.no_grad()
    def predict(self, batch: dict, sp: SamplingParams, generator: torch.Generator | None = None,
                intr: dict[str, torch.Tensor] | None = None) -> dict[str, torch.Tensor]:
        """Pairs batch -> linear HDR {relit, diffuse, specular} (B, 3, H, W), all branches in one batched pass.

        `intr`: the intrinsics to condition on (default: the batch's ground truth); the mask and
        the target ball always come from the batch."""
        s, V = self.stack, self.V
        dev = next(s.model.parameters()).device
        intr = {d: (intr or batch)[d].to(dev) for d in PRED_DOMAINS}
        image_a = batch["image_a"].to(dev)
        B = image_a.shape[0]
        maps = condition_images(image_a, intr, batch["ball_b"].to(dev), batch["mask"].to(dev), self.with_d_calc)
        z_cond = encode_conditions(s.codec, maps, self.layout, self.width)
        ids = torch.arange(V, device=dev).repeat(B)
        ehs = s.encode_condition(maps["image"], torch.zeros(B, dtype=torch.bool, device=dev)).repeat_interleave(V, 0)
        z0 = sample(s.model, z_cond, ids, ehs, num_views=V, steps=sp.steps, cfg_scale=sp.cfg_scale,
                    timestep_spacing=sp.timestep_spacing, mode=sp.mode, ensemble=sp.ensemble, generator=generator,
                    null_hidden_states=s.null_condition(ehs), scheduler_config=s.scheduler.config)
        offset = self._input_offset(z_cond)
        if offset is not None:
            z0 = z0 + offset
        y = self._relit_from_output(s.codec.decode(z0).float().unflatten(0, (B, V)), maps["image"])
        # Clamp: model_to_hdr of the top code rounds just above the float16 maximum (inf in an EXR).
        return {b: schema.from_model("image", y[:, i]).clamp(0, schema.HDR_MAX) for i, b in enumerate(self.branches)}

    @torch.no_grad()
    def images(self, batch: dict) -> dict[str, np.ndarray]:
        """Rows: input | target | relit; then D_calc | D gt | D pred and S gt | S pred (first pair)."""
        one = {k: v[:1] for k, v in batch.items()}
        pred = self.predict(one, self.preview, torch.Generator().manual_seed(0))
        u8 = lambda x: to_uint8(x[0].cpu(), hdr=True)
        rows = [np.concatenate([u8(one["image_a"]), u8(one["image_b"]), u8(pred["relit"])], axis=1)]
        if "diffuse" in pred:
            d_calc = diffuse_calculated(self._ball(one), one["normal"], one["mask"], one["metallic"])
            rows.append(np.concatenate([u8(d_calc), u8(one["diffuse_b"]), u8(pred["diffuse"])], axis=1))
            rows.append(np.concatenate([np.zeros_like(rows[0][:, :rows[0].shape[1] // 3]), u8(one["specular_b"]),
                                        u8(pred["specular"])], axis=1))
        return {"relight_grid": np.concatenate(rows, axis=0)}


def _latent_channels(p: RelightParams) -> int:
    """The codec's latent width without building the UNet (pixel: 3 f^2; VAE: from its config)."""
    if p.codec.kind == "pixel":
        return 3 * p.codec.factor ** 2
    try:
        return int(json.loads((Path(p.codec.path) / "config.json").read_text()).get("latent_channels", 4))
    except (OSError, ValueError):
        return 4  # build_stack then reports the broken VAE folder itself
