"""Stage 2's batch layout: which branch reads which condition maps, and how they are encoded.

Each pair becomes V = 3 batch items (sample-major), one per branch, told apart by one-hot domain
labels and denoised at one shared timestep; cross-batch attention lets the branches see each other
(paper, Sec. "Stage 2"):

    branch 0  relit     I_in1 = (I_in, A)          -> I_relit
    branch 1  diffuse   I_in2 = (N, L, m)          -> D_pred
    branch 2  specular  I_in3 = (N, L, M, R, m)    -> S_pred

Every condition map is a 3-channel image in [-1, 1] (1-channel M, R, m replicated; N as is; the
light ball L resized bilinearly to the image size and tone-mapped like any HDR map), encoded by the
codec ON ITS OWN, and the latents are concatenated on channels. All branches are zero-padded to the
widest, so ONE UNet (one input width) serves all three: the branch's one-hot label says which layout
its condition channels hold, and zero is also what classifier-free guidance feeds for "no
condition". `decomposition: false` (the paper's ablation) keeps only the relit branch (V = 1) and
gives it every map, so the ablation removes the decomposition, not the information about the light.

`d_calc_condition` (ours): the named branches also read D_calc, the Lambertian lookup of the target
ball with the CONDITIONING normals and metallic. It holds no information the branch lacks (N and L
are there), but reading the ball where it faces like this pixel is a non-local lookup that a small
UNet trained from scratch does not learn in a CPU budget.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from pilight.data import schema
from pilight.physics.calculated import diffuse_calculated

BRANCHES = ("relit", "diffuse", "specular")  # one-hot order = domain ids 0, 1, 2
TARGETS = {"relit": "image_b", "diffuse": "diffuse_b", "specular": "specular_b"}
BRANCH_MAPS = {
    "relit": ("image", "albedo"),
    "diffuse": ("normal", "ball", "mask"),
    "specular": ("normal", "ball", "metallic", "roughness", "mask"),
}
ABLATION_MAPS = ("image", "albedo", "normal", "ball", "metallic", "roughness", "mask")  # decomposition: false


def branch_layout(
    decomposition: bool, d_calc_branches: tuple[str, ...] = (), physics_first: bool = False
) -> dict[str, tuple[str, ...]]:
    """Condition maps per branch. ``d_calc_branches`` (relight.d_calc_condition) also get "d_calc";
    without decomposition the one branch gets it when any branch is named (the ablation keeps every
    input, as with ABLATION_MAPS). ``physics_first``: PHYSICS_FIRST_MAPS."""
    if physics_first:
        return dict(PHYSICS_FIRST_MAPS)
    if not decomposition:
        return {"relit": ABLATION_MAPS + (("d_calc",) if d_calc_branches else ())}
    return {b: maps + (("d_calc",) if b in d_calc_branches else ()) for b, maps in BRANCH_MAPS.items()}


def cond_width(decomposition: bool, d_calc_branches: tuple[str, ...] = (), physics_first: bool = False) -> int:
    """Condition maps per item after padding: the widest branch (5, or 6 with D_calc), or 7 (8) for the ablation."""
    return max(len(m) for m in branch_layout(decomposition, d_calc_branches, physics_first).values())


def condition_images(
    image_a: torch.Tensor,
    intr: dict[str, torch.Tensor],
    ball: torch.Tensor,
    mask: torch.Tensor,
    with_d_calc: bool = False,
) -> dict[str, torch.Tensor]:
    """Every condition map as a (B, 3, H, W) image in [-1, 1] (linear inputs, schema mappings).

    ``with_d_calc`` adds "d_calc": the Lambertian lookup of this (gray) ball with the CONDITIONING
    normals and metallic, i.e. a function of inputs the branch already has. It only spares the
    UNet the non-local lookup (which ball pixel faces the same way as this normal), which a small
    model trained from scratch does not learn in a CPU budget."""
    h, w = image_a.shape[-2:]
    up = F.interpolate(ball.float(), size=(h, w), mode="bilinear", align_corners=False).clamp_min(0)
    rep = lambda x: x.expand(-1, 3, -1, -1) if x.shape[1] == 1 else x
    maps = {
        "image": schema.to_model("image", image_a),
        "albedo": schema.to_model("albedo", intr["albedo"]),
        "normal": schema.to_model("normal", intr["normal"]),
        "ball": schema.to_model("ball", up),
        "metallic": rep(schema.to_model("metallic", intr["metallic"])),
        "roughness": rep(schema.to_model("roughness", intr["roughness"])),
        "mask": rep(schema.to_model("mask", mask)),
    }
    if with_d_calc:
        maps["d_calc"] = schema.to_model("image", diffuse_calculated(ball, intr["normal"], mask, intr["metallic"]))
    return maps


def encode_conditions(
    codec, maps: dict[str, torch.Tensor], layout: dict[str, tuple[str, ...]], width: int
) -> torch.Tensor:
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


# physics_first (pilight.relight.physics_first): every branch reads the anchors it corrects, and
# the target light only through maps divided by its level (ball_n, d_calc_n, s_calc_n), so the
# gains it outputs do not depend on the light's strength and I_relit is linear in it.
PHYSICS_FIRST_MAPS = {
    "relit": ("image", "mask", "albedo_x", "d_calc_n"),
    "diffuse": ("normal", "ball_n", "mask", "d_calc_n", "image", "albedo_x"),
    "specular": ("normal", "ball_n", "metallic", "roughness", "mask", "s_calc_n"),
}


def physics_first_images(
    image_a: torch.Tensor, intr: dict[str, torch.Tensor], ball: torch.Tensor, mask: torch.Tensor, anc
) -> dict[str, torch.Tensor]:
    """condition_images plus the physics-first maps of ``anc`` (a physics_first.Anchors)."""
    maps = condition_images(image_a, intr, ball, mask)
    h, w = image_a.shape[-2:]
    up = F.interpolate(ball.float(), size=(h, w), mode="bilinear", align_corners=False).clamp_min(0)
    maps["ball_n"] = schema.to_model("ball", up / anc.level)
    maps["d_calc_n"] = schema.to_model("image", anc.d_calc / anc.level)
    maps["s_calc_n"] = schema.to_model("image", anc.s_calc / anc.level)
    maps["albedo_x"] = schema.to_model("albedo", anc.albedo.clamp(0.0, 1.0))
    return maps
