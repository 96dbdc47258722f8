"""Which Cycles passes each render needs, and the contract that turns them into maps.

The contract (image = A * D + S, D >= 0, S >= 0), written once:
- Cycles gives Diffuse Color DC, Diffuse Direct/Indirect light L_d (Cycles divides the light
  passes by the colour pass, so DC * L_d is exactly the diffuse radiance of the samples).
- DC is NOT the base colour A: the Principled BSDF layers a dielectric specular over its
  diffuse lobe and removes that share from it, and metals have no diffuse lobe, so
  DC = k * A with k = (1 - metallic) * (1 - specular layer albedo) in [0, 1], one scalar per
  pixel (the same for R, G and B; checked in tests).
- We keep A = Base Color (the network's target) and put k into the shading, per channel:
      D_c = DC_c * L_d,c / A_c      (= k * L_d,c),
  so A * D = DC * L_d is the diffuse radiance exactly, and S = image - A * D is everything else
  (glossy + transmission + emission + background), >= 0 up to float rounding.
  The division uses the view's written albedo (rendered once per view) and each light's DC:
  with adaptive sampling a pixel stops after a light-dependent number of samples, so at
  texture edges the two averages differ a little and D deviates from k * L_d there; dividing
  (rather than using k * L_d) keeps the identity exact, which the losses rely on.
- Where A_c ~ 0 (background, glass, emission: not Principled) D_c = k * L_d,c (0 off surfaces).
Nothing here needs the glossy/transmission passes; `VERIFY_PASSES` renders them only so tests
can check S against their sum.
"""

from __future__ import annotations

import numpy as np

BEAUTY_PASSES = ("combined",)
DIFFUSE_PASSES = ("diffuse_direct", "diffuse_indirect", "diffuse_color")
VIEW_PASSES = ("normal",)  # plus the shader AOVs, always present on the view layer
VERIFY_PASSES = (
    "glossy_direct",
    "glossy_indirect",
    "glossy_color",
    "transmission_direct",
    "transmission_indirect",
    "transmission_color",
    "emit",
    "environment",
)
_ALL = BEAUTY_PASSES + DIFFUSE_PASSES + VIEW_PASSES + VERIFY_PASSES
MASK_THRESHOLD = 1.0 - 1e-4  # "principled" AOV averaged over the pixel: 1 only if fully covered
S_NEGATIVE_TOLERANCE = 1e-4  # relative; larger negative S means the contract is broken


class ContractError(RuntimeError):
    """The passes violate image = A * D + S with D, S >= 0 beyond float rounding."""


def configure(view_layer, *, diffuse: bool, view_maps: bool, verify: bool = False) -> None:
    """Enable exactly the passes that a render's outputs read (model only what is needed)."""
    wanted = set(BEAUTY_PASSES)
    if diffuse:
        wanted |= set(DIFFUSE_PASSES)
    if view_maps:
        wanted |= set(VIEW_PASSES)
    if verify:
        wanted |= set(VERIFY_PASSES)
    _enable(view_layer, wanted)


def configure_ball(view_layer, *, lambertian: bool) -> None:
    """The gray ball reads Combined; its Lambertian twin the diffuse light passes (not the colour)."""
    _enable(view_layer, set(BEAUTY_PASSES) | ({"diffuse_direct", "diffuse_indirect"} if lambertian else set()))


def _enable(view_layer, wanted: set[str]) -> None:
    for name in _ALL:
        setattr(view_layer, f"use_pass_{name}", name in wanted)


def decompose(passes: dict[str, np.ndarray], albedo: np.ndarray, where: str) -> dict[str, np.ndarray]:
    """image, diffuse D and specular S from one render's passes and the view's albedo A."""
    image = passes["Combined"]
    light = passes["Diffuse Direct"] + passes["Diffuse Indirect"]
    colour = passes["Diffuse Color"]
    a_sum = albedo.sum(axis=-1, keepdims=True)
    has_albedo = a_sum > 1e-6
    k = np.where(has_albedo, colour.sum(axis=-1, keepdims=True) / np.where(has_albedo, a_sum, 1.0), 0.0)
    k = np.clip(k, 0.0, 1.0)
    has_channel = albedo > 1e-4
    diffuse = np.where(has_channel, colour * light / np.where(has_channel, albedo, 1.0), k * light).astype(np.float32)
    specular = image - albedo * diffuse
    worst = float((-specular / (np.abs(image) + 1e-3)).max(initial=0.0))
    if worst > S_NEGATIVE_TOLERANCE:
        raise ContractError(f"{where}: specular would be negative (relative {worst:.2e}); A*D exceeds the image")
    specular = np.maximum(specular, 0.0).astype(np.float32)
    return {"image": image.astype(np.float32), "diffuse": diffuse, "specular": specular}


def view_maps(passes: dict[str, np.ndarray], world_from_camera: np.ndarray) -> dict[str, np.ndarray]:
    """albedo, camera-space normal, roughness, metallic and mask from a render with view passes."""
    mask = (passes["principled"][..., :1] >= MASK_THRESHOLD).astype(np.float32)
    # Normal pass is world space; camera space n_cam = R^T n_world (row vectors: n_world @ R).
    n = passes["Normal"] @ np.asarray(world_from_camera, dtype=np.float32)[:3, :3]
    length = np.linalg.norm(n, axis=-1, keepdims=True)
    normal = np.where((length > 1e-6) & (mask > 0), n / np.maximum(length, 1e-6), 0.0).astype(np.float32)
    return {
        "albedo": np.clip(passes["albedo"][..., :3], 0.0, None).astype(np.float32),
        "normal": normal,
        "roughness": np.clip(passes["roughness"][..., :1], 0.0, 1.0),
        "metallic": np.clip(passes["metallic"][..., :1], 0.0, 1.0),
        "mask": mask,
    }


def ball_maps(passes: dict[str, np.ndarray], *, lambertian: bool = True) -> dict[str, np.ndarray]:
    """The gray ball, and its Lambertian twin from the same render.

    The ball is convex, so its diffuse light passes are the irradiance from the scene's lights;
    a pure diffuse ball of albedo 0.5 would have radiance 0.5 * L_d exactly: no second render.
    """
    balls = {"ball": passes["Combined"].astype(np.float32)}
    if lambertian:
        balls["ball_lambertian"] = (0.5 * (passes["Diffuse Direct"] + passes["Diffuse Indirect"])).astype(np.float32)
    return balls
