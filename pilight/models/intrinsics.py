"""Stage 1 for inference: one image -> albedo, normal, roughness, metallic together, in one batched pass,
built from the params a model was trained with (its config.json).

Two layouts (`intrinsics.layout`): ``domains`` (the paper: V = 4 UNet items per image, one per map, told
apart by one-hot domain labels, seeing each other through cross-batch attention) and ``joint`` (one
item whose output stacks the four maps' latents on channels). Training
(pilight.train.intrinsics.IntrinsicsTask) builds on this class; the photo API, the infer_intrinsics
stage and the trade sweep use it alone.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from pilight.data import schema
from pilight.data.colour import srgb_to_linear
from pilight.models.stack import DiffusionStack, build_stack
from pilight.params import DOMAINS, IntrinsicsParams, SamplingParams


def targets_to_maps(x: torch.Tensor, domains: tuple[str, ...], albedo_space: str = "linear") -> dict[str, torch.Tensor]:
    """Inverse of `domain_targets` for predictions (B, V, 3, H, W) -> linear maps in their ranges."""
    out = {}
    for i, d in enumerate(domains):
        if d == "normal":
            # The direction of the raw output, as the angular loss trains it (it normalises, never clamps).
            # Clamping each component to [-1, 1] first turned every normal with a component beyond 1 toward
            # the axes: the shipped base's floors and walls by ~12 degrees, its test normals 23.1 -> 11.4
            # degrees mean error once removed (benchmarks/normal_frame.py, docs: stage 1).
            out[d] = F.normalize(x[:, i], dim=1, eps=1e-6)
            continue
        y = x[:, i].clamp(-1, 1)
        if d in ("roughness", "metallic"):
            out[d] = schema.from_model(d, y.mean(dim=1, keepdim=True)).clamp(0, 1)
        else:
            a = schema.from_model(d, y).clamp(0, 1)  # in [0, 1]: the sRGB curve's domain
            out[d] = srgb_to_linear(a) if albedo_space == "srgb" else a
    return out


class IntrinsicsModel:
    """Stage 1's model: ``predict`` maps of a linear HDR image batch."""

    def __init__(self, p: IntrinsicsParams):
        self.p = p
        self.joint = p.layout == "joint"
        V = len(DOMAINS)
        self.stack: DiffusionStack = (
            build_stack(p, num_domains=1, items_per_sample=1, cond_channels=None, maps_per_item=V)
            if self.joint
            else build_stack(p, num_domains=V, cond_channels=None)
        )

    def describe(self) -> dict[str, str]:
        return self.stack.describe()

    def to(self, device) -> IntrinsicsModel:
        self.stack.model.to(device)
        if isinstance(self.stack.codec, torch.nn.Module):
            self.stack.codec.to(device)
        return self

    def _items(self, z: torch.Tensor, B: int) -> torch.Tensor:
        """(B*V, C, h, w) per-domain latents -> the UNet's items: the same (domains) or (B, V*C, h, w) (joint)."""
        return z.unflatten(0, (B, -1)).flatten(1, 2) if self.joint else z

    def _domains(self, x: torch.Tensor, B: int) -> torch.Tensor:
        """Inverse of ``_items``: UNet items -> (B*V, C, h, w)."""
        return x.unflatten(1, (len(DOMAINS), -1)).flatten(0, 1) if self.joint else x

    def _ids(self, B: int, dev) -> torch.Tensor:
        V = len(DOMAINS)
        return torch.zeros(B, dtype=torch.long, device=dev) if self.joint else torch.arange(V, device=dev).repeat(B)

    @torch.no_grad()
    def predict(
        self,
        image: torch.Tensor,
        domains: tuple[str, ...],
        sp: SamplingParams,
        generator: torch.Generator | None = None,
    ) -> dict[str, torch.Tensor]:
        """Linear HDR image batch (B, 3, H, W) -> predicted maps for `domains`, all in one batched pass."""
        s = self.stack
        dev = next(s.model.parameters()).device
        x = schema.to_model("image", image).to(dev)
        B, V = x.shape[0], len(domains)
        if self.joint:  # one item carries every map; a subset costs the same, and is picked afterwards
            z0 = s.sample(s.codec.encode(x), self._ids(B, dev), x, 1, sp, generator)
            pred = s.codec.decode(self._domains(z0, B)).float().unflatten(0, (B, len(DOMAINS)))
            maps = targets_to_maps(pred, DOMAINS, self.p.albedo_space)
            return {d: maps[d] for d in domains}
        z_cond = s.codec.encode(x).repeat_interleave(V, 0)
        ids = torch.tensor([DOMAINS.index(d) for d in domains], device=dev).repeat(B)
        z0 = s.sample(z_cond, ids, x, V, sp, generator)
        pred = s.codec.decode(z0).float().unflatten(0, (B, V))
        return targets_to_maps(pred, domains, self.p.albedo_space)
