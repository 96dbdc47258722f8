"""Physics of PI-Light: light ball -> diffuse env map, Lambertian lookup, physics losses.

Conventions (camera frame, ball layout, lat-long UV, units) are documented in
``pilight.physics.envmap``.
"""

from .envmap import BALL_ALBEDO, ENV_H, ENV_W, ball_normals, ball_to_envmap, envmap_directions, normal_to_uv
from .losses import (
    Dinov2Features,
    PooledRGBFeatures,
    diffuse_shading_loss,
    make_feature_extractor,
    masked_mse,
    physical_shading_loss,
    physics_loss,
    reconstruction_loss,
)
from .shading import ball_from_direction, ball_from_hdri, ball_from_light, compose, diffuse_shading, hdri_directions

__all__ = [
    "BALL_ALBEDO",
    "ENV_H",
    "ENV_W",
    "ball_normals",
    "ball_to_envmap",
    "envmap_directions",
    "normal_to_uv",
    "Dinov2Features",
    "PooledRGBFeatures",
    "diffuse_shading_loss",
    "make_feature_extractor",
    "masked_mse",
    "physical_shading_loss",
    "physics_loss",
    "reconstruction_loss",
    "ball_from_direction",
    "ball_from_hdri",
    "ball_from_light",
    "compose",
    "diffuse_shading",
    "hdri_directions",
]
