"""Typed, validated view of params.yaml: one class per section.

Each stage validates the sections it reads before doing any work, so a bad value fails in
milliseconds (not after Blender has started) with the key, the value and what is allowed.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Any, Literal

import yaml
from pydantic import (
    BaseModel,
    ConfigDict,
    Discriminator,
    Field,
    Tag,
    ValidationError,
    ValidationInfo,
    field_validator,
    model_validator,
)

from pilight.data.layout import INTRINSIC_MAPS
from pilight.optional import installed, missing

# The HDRIs Blender ships in datafiles/studiolights/world (no download needed).
BUNDLED_HDRIS = ("city", "courtyard", "forest", "interior", "night", "studio", "sunrise", "sunset")
SHAPES = ("sphere", "icosphere", "cube", "cylinder", "cone", "torus", "monkey")  # the default list
# Also allowed in render.scene.shapes: shapes with a hole that are not tori (pilight/render/holed_shapes.py);
# not in the default list, so its scenes keep their draws.
EXTRA_SHAPES = ("tube", "frame")
PROCEDURAL_TEXTURES = ("noise", "voronoi", "checker", "wave", "brick", "magic")  # the default list
# Also allowed in render.scene.textures (base-model variety); not in the default list, so its scenes keep their draws.
EXTRA_TEXTURES = ("gradient", "gabor")
MATERIAL_CLASSES = ("metal", "plastic", "rubber", "wood", "stone", "ceramic")  # pilight/render/material_classes.py
ASSET_SUFFIXES = (".glb", ".gltf", ".obj", ".blend")

# Upper limits of keys defined before the render limits below (issue 36: every key has a range and a
# resource bound; a typo'd extra digit must fail in milliseconds, not after an hour or 40 GB).
MAX_SEED = 2**32 - 1  # numpy's and most samplers' seed width
MAX_SCENES = 1_000_000  # per split; rendering that many takes weeks on a GPU farm
MAX_PER_SCENE = 1000  # views per scene, lights per view, objects per scene
MAX_ANGLE_DEG = 720.0
MAX_LEVEL = 10_000.0  # light strengths, ambient and HDRI multipliers


class ParamsError(ValueError):
    """params.yaml is missing, malformed or holds a value outside what is allowed."""


def _weights_folder(value: str | None, key: str, info: ValidationInfo) -> None:
    """A local weights folder (VAE, UNet, CLIP, DINOv2) must exist, unless the validation was told not to
    look: context {"check_paths": False}, e.g. a profile checked on a machine that lacks the weights."""
    if value and (info.context or {}).get("check_paths", True) and not Path(value).is_dir():
        raise ValueError(f"{key} {value!r} does not exist")


class _Section(BaseModel):
    # allow_inf_nan=False: a NaN or Inf anywhere (a light's elevation, a CFG scale) is refused by key,
    # not found later as NaN lights in scene.json or saturated images written with exit 0.
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    @field_validator("*", mode="before")
    @classmethod
    def _no_bool_numbers(cls, v, info: ValidationInfo):
        """YAML's true/false are ints to pydantic's lax mode, so `scenes.train: true` would count 1.
        In a params file (context "from_file") an empty sub-section (`cycles: {}`) is refused like an
        empty section (``_validate``); in Python, ``RenderParams(cycles={})`` still means the defaults."""
        annotation = cls.model_fields[info.field_name].annotation
        if isinstance(v, bool) and annotation in (
            int,
            float,
            int | None,
            float | None,
        ):
            raise ValueError("a boolean where a number is expected")
        from_file = (info.context or {}).get("from_file", False)
        if (
            from_file
            and isinstance(v, dict)
            and not v
            and isinstance(annotation, type)
            and issubclass(annotation, BaseModel)
        ):
            raise ValueError("an empty section: give its keys, or leave the key out to use the defaults")
        return v


class BaseParams(_Section):
    seed: int = Field(42, ge=0, le=MAX_SEED, description="root of every random draw in the pipeline")
    train_seed: int | None = Field(
        None,
        ge=0,
        le=MAX_SEED,
        description="seed of every stage after the shards (training, inference, sampling); null = seed. "
        "Varying it reruns training on the same renders and shards (python -m pilight.seeds)",
    )

    @property
    def training_seed(self) -> int:
        """The seed of the stages after the shards: ``train_seed``, or ``seed`` when it is null."""
        return self.seed if self.train_seed is None else self.train_seed

    def stage_training_seed(self, train: TrainParams) -> int:
        """A training stage's seed: its own ``train.seed`` where set, else :attr:`training_seed`."""
        return self.training_seed if train.seed is None else train.seed


class Range(_Section):
    lo: float = Field(ge=-1e6, le=1e6)
    hi: float = Field(ge=-1e6, le=1e6)

    @model_validator(mode="after")
    def _ordered(self) -> Range:
        if self.lo > self.hi:
            raise ValueError(f"lo ({self.lo}) must not exceed hi ({self.hi})")
        return self


class IntRange(_Section):
    lo: int = Field(ge=0, le=MAX_PER_SCENE)
    hi: int = Field(ge=0, le=MAX_PER_SCENE)

    @model_validator(mode="after")
    def _ordered(self) -> IntRange:
        if self.lo > self.hi:
            raise ValueError(f"lo ({self.lo}) must not exceed hi ({self.hi})")
        return self


class SplitCounts(_Section):
    train: int = Field(ge=0, le=MAX_SCENES)
    val: int = Field(ge=0, le=MAX_SCENES)
    test: int = Field(ge=0, le=MAX_SCENES)


class AngleRange(Range):
    """A range of angles in degrees (azimuth: any turn, written within two of them)."""

    lo: float = Field(ge=-MAX_ANGLE_DEG, le=MAX_ANGLE_DEG)
    hi: float = Field(ge=-MAX_ANGLE_DEG, le=MAX_ANGLE_DEG)


class ElevationRange(Range):
    """A range of elevations in degrees; above 90 lies past the zenith."""

    lo: float = Field(ge=-180.0, le=180.0)
    hi: float = Field(ge=-180.0, le=180.0)


class LevelRange(Range):
    """A range of a non-negative light level (strength, ambient, an HDRI's multiplier)."""

    lo: float = Field(ge=0.0, le=MAX_LEVEL)
    hi: float = Field(ge=0.0, le=MAX_LEVEL)


class DensityRange(Range):
    """A range of a non-negative physical factor (an atmosphere's density, an intensity multiplier)."""

    lo: float = Field(ge=0.0, le=100.0)
    hi: float = Field(ge=0.0, le=100.0)


class LightParams(_Section):
    """Light sampling, the paper's appendix (object data / scene data)."""

    azimuth_deg: AngleRange = AngleRange(lo=0.0, hi=360.0)
    elevation_mean_deg: float = Field(60.0, ge=-180.0, le=180.0)
    elevation_std_deg: float = Field(40.0, ge=0.0, le=360.0)
    elevation_clip_deg: ElevationRange = ElevationRange(lo=20.0, hi=160.0)
    # Irradiance at the scene centre in units where a white Lambertian surface facing the
    # light has radiance strength * irradiance_scale / pi (the paper's [5, 20] is in Blender units
    # of an unknown exposure; irradiance_scale sets ours so typical pixels sit near 1).
    strength: LevelRange = LevelRange(lo=5.0, hi=20.0)
    irradiance_scale: float = Field(0.5, gt=0.0, le=1000.0)
    jitter: float = Field(0.1, ge=0.0, le=0.5, description="relative random variation of strength")
    distance: float = Field(6.0, gt=0.0, le=1000.0, description="point light distance from the scene centre (m)")
    radius: float = Field(0.1, ge=0.0, le=100.0, description="point light radius (soft shadows)")
    hdri_probability: float = Field(
        0.2, ge=0.0, le=1.0, description="paper: 20% point light + env map, 80% point light alone"
    )
    hdri_strength: LevelRange = LevelRange(lo=0.3, hi=1.0)
    point_scale_with_hdri: float = Field(0.5, gt=0.0, le=1.0, description="point light is lowered when an HDRI is on")
    ambient: LevelRange = LevelRange(lo=0.01, hi=0.05)
    room_back_light_deg: float = Field(
        30.0, ge=0.0, le=90.0, description="room scenes: extra light behind the camera within +- this angle"
    )
    sky_probability: float = Field(
        0.0,
        ge=0.0,
        le=1.0,
        description="share of light conditions lit by Blender's procedural sky (multiple scattering) instead of "
        "the point light and HDRI (room scenes keep their back light): its sun comes from the point light's "
        "drawn direction, at its irradiance",
    )
    sky_air: DensityRange = Field(
        DensityRange(lo=0.8, hi=1.5), description="sky air density (Rayleigh: blue sky, reddened low sun); 1 = Earth"
    )
    sky_aerosol: DensityRange = Field(
        DensityRange(lo=0.5, hi=4.0), description="sky aerosol (dust, haze: whiter sky, softer sun); 1 = Earth"
    )
    sky_sun_intensity: DensityRange = Field(
        DensityRange(lo=0.7, hi=1.0), description="multiplier of the sun disc alone (thin cloud); 1 = physical"
    )

    @model_validator(mode="after")
    def _sun_above_the_horizon(self) -> LightParams:
        # The sky's sun takes the point light's elevation (above 90: over the zenith); below ~5 degrees
        # it sets, and a sky-lit image would be night.
        if self.sky_probability > 0 and not 5.0 <= self.elevation_clip_deg.lo <= self.elevation_clip_deg.hi <= 175.0:
            raise ValueError(
                f"sky_probability > 0 needs elevation_clip_deg within [5, 175] (the sun's elevation); "
                f"got [{self.elevation_clip_deg.lo}, {self.elevation_clip_deg.hi}]"
            )
        return self


class HdriParams(_Section):
    dir: str | None = Field(None, description="folder of the user's .exr/.hdr HDRIs; null = Blender's bundled ones")
    names: tuple[str, ...] = BUNDLED_HDRIS
    test_holdout: tuple[str, ...] = ("courtyard", "sunset")

    @model_validator(mode="after")
    def _known(self) -> HdriParams:
        if self.dir is None:
            unknown = [n for n in self.names + self.test_holdout if n not in BUNDLED_HDRIS]
            if unknown:
                raise ValueError(f"unknown bundled HDRI name(s) {unknown}; allowed: {list(BUNDLED_HDRIS)}")
        else:
            folder = Path(self.dir)
            if not folder.is_dir():
                raise ValueError(f"hdri.dir {self.dir!r} does not exist or is not a folder")
            found = {p.stem for p in folder.iterdir() if p.suffix.lower() in (".exr", ".hdr")}
            unknown = [n for n in self.names + self.test_holdout if n not in found]
            if unknown:
                raise ValueError(f"HDRI name(s) {unknown} not found in {self.dir!r}; found: {sorted(found)}")
        missing = [n for n in self.test_holdout if n not in self.names]
        if missing:
            raise ValueError(f"test_holdout {missing} must also be listed in names")
        if not set(self.names) - set(self.test_holdout):
            raise ValueError("every HDRI is held out for test: the train split would have none")
        return self


class StretchParams(_Section):
    """Anisotropic shapes: an object's size is multiplied per local axis by U[lo, hi]."""

    probability: float = Field(0.0, ge=0.0, le=1.0, description="share of objects stretched; 0 = all uniform")
    lo: float = Field(0.6, gt=0.0, le=10.0)
    hi: float = Field(1.6, gt=0.0, le=10.0)

    @model_validator(mode="after")
    def _ordered(self) -> StretchParams:
        if self.lo > self.hi:
            raise ValueError(f"lo ({self.lo}) must not exceed hi ({self.hi})")
        return self


class MaterialClassWeights(_Section):
    """Relative weights of the material classes (material_model: classes); they need not sum to 1."""

    metal: float = Field(0.2, ge=0.0, le=1000.0)
    plastic: float = Field(0.25, ge=0.0, le=1000.0)
    rubber: float = Field(0.1, ge=0.0, le=1000.0)
    wood: float = Field(0.15, ge=0.0, le=1000.0)
    stone: float = Field(0.15, ge=0.0, le=1000.0)
    ceramic: float = Field(0.15, ge=0.0, le=1000.0)

    @model_validator(mode="after")
    def _some_weight(self) -> MaterialClassWeights:
        if sum(self.model_dump().values()) <= 0:
            raise ValueError(f"at least one class needs a positive weight; classes: {list(MATERIAL_CLASSES)}")
        return self


class SceneParams(_Section):
    room_fraction: float = Field(
        0.5, ge=0.0, le=1.0, description="share of room/ground scenes; the rest are object scenes"
    )
    closeup_fraction: float = Field(
        0.0,
        ge=0.0,
        le=1.0,
        description="share of close-up scenes, framed like a portrait: one subject filling most of the picture "
        "at eye level before a wall or nothing, no floor in view; drawn from the object scenes' share",
    )
    objects_object_scene: IntRange = IntRange(lo=1, hi=2)
    objects_room_scene: IntRange = IntRange(lo=3, hi=5)
    shapes: tuple[str, ...] = SHAPES
    textures: tuple[str, ...] = PROCEDURAL_TEXTURES
    textured_probability: float = Field(
        0.6, ge=0.0, le=1.0, description="share of textured materials (shared) or maps (independent)"
    )
    material_pattern: Literal["shared", "independent"] = Field(
        "shared",
        description="shared: a textured material blends two sub-materials (colour, roughness, metal 0/1) "
        "along one pattern, like a real asset's material mask; independent: each map its own texture and range",
    )
    non_principled_probability: float = Field(0.15, ge=0.0, le=1.0, description="glass/emission objects, masked out")
    metallic_probability: float = Field(
        0.3,
        ge=0.0,
        le=1.0,
        description="share of (sub-)materials that are metal; textured metallic ranges are not (independent)",
    )
    modifier_probability: float = Field(0.5, ge=0.0, le=1.0, description="bevel / subdivision / displacement")
    stretch: StretchParams = StretchParams()
    material_model: Literal["uniform", "classes"] = Field(
        "uniform",
        description="uniform: colour, roughness and metal drawn independently (metallic_probability, "
        "textured_probability); classes: each Principled material is a class (metal, plastic, ...) whose "
        "colours, roughness, metal and patterns go together, drawn by material_classes' weights",
    )
    material_classes: MaterialClassWeights = MaterialClassWeights()

    @model_validator(mode="after")
    def _kinds(self):
        if self.room_fraction + self.closeup_fraction > 1.0:
            raise ValueError(
                f"room_fraction ({self.room_fraction}) + closeup_fraction ({self.closeup_fraction}) must not "
                "exceed 1 (the rest are object scenes)"
            )
        return self

    @field_validator("shapes")
    @classmethod
    def _shapes(cls, v: tuple[str, ...]) -> tuple[str, ...]:
        bad = [s for s in v if s not in SHAPES + EXTRA_SHAPES]
        if bad or not v:
            raise ValueError(f"unknown shape(s) {bad}; allowed: {list(SHAPES + EXTRA_SHAPES)}")
        return v

    @field_validator("textures")
    @classmethod
    def _textures(cls, v: tuple[str, ...]) -> tuple[str, ...]:
        bad = [s for s in v if s not in PROCEDURAL_TEXTURES + EXTRA_TEXTURES]
        if bad:
            raise ValueError(f"unknown texture(s) {bad}; allowed: {list(PROCEDURAL_TEXTURES + EXTRA_TEXTURES)}")
        return v


# Upper limits where a runaway value costs hours, not a clear error (a typo'd extra digit).
MAX_RESOLUTION = 4096  # the paper renders 768; 4096^2 is ~3 min per Cycles bundle on a GPU
MAX_SAMPLES = 65536
MAX_STEPS = 10_000_000
MAX_CFG = 50.0
MAX_BOUNCES = 1024  # Blender's own limit
# The render's disk estimate, uncompressed bytes per pixel: a view's maps (albedo float32 RGB, normal
# float16 RGB, roughness, metallic, mask float16) and a light's (image, diffuse, specular float32 RGB,
# its preview strip); balls per ball pixel (ball, ball_lambertian float16 RGB). ZIP makes it ~2x smaller.
VIEW_BYTES_PER_PIXEL, LIGHT_BYTES_PER_PIXEL, BALL_BYTES_PER_PIXEL = 24, 39, 12
MAX_RENDER_BYTES = 256 * 2**40  # ~8x the paper's profile (30 TiB): a typo'd count, not a dataset


class CyclesParams(_Section):
    samples: int = Field(64, ge=1, le=MAX_SAMPLES)
    adaptive_threshold: float = Field(
        0.02, ge=0.0, le=1.0, description="Cycles noise threshold; 0 turns adaptive sampling off"
    )
    adaptive_min_samples: int = Field(16, ge=0, le=MAX_SAMPLES)
    max_bounces: int = Field(4, ge=0, le=MAX_BOUNCES)
    diffuse_bounces: int = Field(2, ge=0, le=MAX_BOUNCES)
    glossy_bounces: int = Field(2, ge=0, le=MAX_BOUNCES)
    transmission_bounces: int = Field(4, ge=0, le=MAX_BOUNCES)
    transparent_max_bounces: int = Field(4, ge=0, le=MAX_BOUNCES)
    world_map_resolution: int = Field(
        256,
        ge=16,
        le=16384,
        description="importance map of the world (HDRI), built on every world edit; Blender's AUTOMATIC map costs ~0.8 s per HDRI render",
    )
    device: Literal["CPU", "GPU"] = "CPU"
    threads: int = Field(0, ge=0, le=4096, description="0 = all cores")


class ClusterParams(_Section):
    """Where the render runs (README "Rendering on a cluster"); none of it changes a rendered byte, so
    these keys are not in the views' stamps nor in dvc.yaml's params of the render stage."""

    executor: Literal["local", "dask"] = Field(
        "local",
        description=(
            "local = in this process; dask = partitions of scenes as tasks on a Dask cluster (pilight.render.cluster)"
        ),
    )
    address: str | None = Field(
        None,
        description="a running Dask scheduler (tcp://host:8786); null = a local "
        "cluster of `workers` processes on this machine",
    )
    workers: int = Field(2, ge=1, le=4096, description="processes of the local cluster (address: null)")
    scenes_per_task: int = Field(4, ge=1, le=MAX_SCENES, description="scenes per partition: one task, one marker")
    retries: int = Field(
        2,
        ge=0,
        le=100,
        description="reruns of a partition whose task raised (a killed worker's "
        "partition is rescheduled by Dask itself)",
    )


class RenderParams(_Section):
    resolution: int = Field(128, ge=8, le=MAX_RESOLUTION)
    scenes: SplitCounts = SplitCounts(train=8, val=1, test=3)
    views_per_scene: int = Field(4, ge=1, le=MAX_PER_SCENE)
    lights_per_view: int = Field(3, ge=1, le=MAX_PER_SCENE)
    cycles: CyclesParams = CyclesParams()
    light: LightParams = LightParams()
    hdri: HdriParams = HdriParams()
    scene: SceneParams = SceneParams()
    cluster: ClusterParams = ClusterParams()
    lambertian_ball: bool = Field(True, description="also write the pure-diffuse ball (free: same render)")
    ball_resolution: int = Field(
        32, ge=16, le=MAX_RESOLUTION, description="the light ball's own size; it is a smooth probe (16x32 env map)"
    )
    ball_samples: int = Field(
        32, ge=1, le=MAX_SAMPLES, description="Cycles samples for the ball (adaptive threshold as the scene)"
    )
    ball_min_samples: int = Field(
        4, ge=0, le=MAX_SAMPLES, description="adaptive sampling's minimum for the ball (0 = Cycles' automatic)"
    )
    assets: tuple[str, ...] = Field(
        (), description=".glb/.gltf/.obj/.blend files placed beside or instead of procedural shapes"
    )
    assets_only: bool = Field(False, description="true: scenes hold only the listed assets, no procedural shapes")
    camera_backdrop: float | None = Field(
        None,
        ge=0.0,
        le=10.0,
        allow_inf_nan=False,
        description=(
            "linear gray radiance that CAMERA rays see behind the scene (the lighting HDRI stays hidden from "
            "them but still lights the scene), so the background is the same for every light of a view; "
            "null = camera rays see the lighting world (the paper's renders)"
        ),
    )

    @field_validator("resolution")
    @classmethod
    def _div8(cls, v: int) -> int:
        if v % 8:
            raise ValueError(f"must be divisible by 8 (the latent codecs downsample by 8); got {v}")
        return v

    @field_validator("assets")
    @classmethod
    def _assets(cls, v: tuple[str, ...]) -> tuple[str, ...]:
        for a in v:
            p = Path(a)
            if p.suffix.lower() not in ASSET_SUFFIXES:
                raise ValueError(f"asset {a!r} has unsupported type {p.suffix!r}; allowed: {list(ASSET_SUFFIXES)}")
            if not p.is_file():
                raise ValueError(f"asset {a!r} does not exist")
        return v

    @model_validator(mode="after")
    def _assets_needed(self) -> RenderParams:
        if self.assets_only and not self.assets:
            raise ValueError("assets_only is true but no assets are listed")
        return self

    def estimated_bytes(self) -> int:
        """Bytes the renders take on disk before compression (the constants above MAX_RENDER_BYTES)."""
        scenes = self.scenes.train + self.scenes.val + self.scenes.test
        per_view = VIEW_BYTES_PER_PIXEL * self.resolution**2 + self.lights_per_view * (
            LIGHT_BYTES_PER_PIXEL * self.resolution**2 + BALL_BYTES_PER_PIXEL * self.ball_resolution**2
        )
        return scenes * self.views_per_scene * per_view

    @model_validator(mode="after")
    def _fits_a_disk(self) -> RenderParams:
        need = self.estimated_bytes()
        if need > MAX_RENDER_BYTES:
            raise ValueError(
                f"scenes x views_per_scene x lights_per_view at resolution {self.resolution} would write about "
                f"{need / 2**40:.0f} TiB of renders (uncompressed estimate), over the limit of "
                f"{MAX_RENDER_BYTES / 2**40:.0f} TiB: lower the scene counts, views, lights or resolution"
            )
        return self


DOMAINS = INTRINSIC_MAPS  # stage 1's outputs, in one-hot order (pilight.data.layout: one definition)
MAX_CHANNELS = 8192  # a UNet level's width (SD2's widest: 1280)
MAX_LEVELS = 8  # UNet levels: each halves the latent
MAX_UNET_PARAMS = 2_000_000_000  # ~32 GiB to train with AdamW (SD2's UNet: 0.87e9)
MAX_BATCH = 4096  # samples per training step or per sampling call
MAX_ENSEMBLE = 256
MAX_LOSS_WEIGHT = 1000.0
MAX_SWEEP = 64  # points per factor of the trade sweep


class CodecParams(_Section):
    kind: Literal["pixel", "vae"] = Field(
        "pixel", description="pixel = lossless pixel-unshuffle (no weights); vae = AutoencoderKL"
    )
    factor: int = Field(4, ge=1, le=64, description="pixel codec downsampling factor")
    path: str | None = Field(
        None, description="local AutoencoderKL folder (e.g. Stable Diffusion 2's vae/) for kind: vae"
    )

    @model_validator(mode="after")
    def _path(self, info: ValidationInfo) -> CodecParams:
        if self.kind == "vae" and not self.path:
            raise ValueError("codec.kind is 'vae' but codec.path is not set (a local AutoencoderKL folder)")
        _weights_folder(self.path, "codec.path", info)
        return self


class UNetParams(_Section):
    init: Literal["scratch", "pretrained", "base"] = Field(
        "scratch",
        description="scratch = random weights; pretrained = a local SD2 / GeoWizard UNet (the paper); base = the "
        "shipped pilight-base model of this stage (pilight.base_model; the params must build its network)",
    )
    path: str | None = Field(
        None,
        description="init pretrained: a local UNet folder; init base: a pilight-base folder (null = the shipped one)",
    )
    block_out_channels: tuple[Annotated[int, Field(ge=1, le=MAX_CHANNELS)], ...] = Field(
        (64, 128, 128),
        min_length=1,
        max_length=MAX_LEVELS,
        description="channels per level; each level halves the latent",
    )
    layers_per_block: int = Field(1, ge=1, le=16)
    attention_head_dim: int = Field(
        8, ge=1, le=MAX_CHANNELS, description="diffusers' name for the number of attention heads per block"
    )
    cross_attention_dim: int = Field(128, ge=1, le=MAX_CHANNELS)

    @model_validator(mode="after")
    def _path(self, info: ValidationInfo) -> UNetParams:
        if self.init == "pretrained" and not self.path:
            raise ValueError("unet.init is 'pretrained' but unet.path is not set (a local UNet folder)")
        _weights_folder(self.path, "unet.path", info)
        return self

    @model_validator(mode="after")
    def _structure(self) -> UNetParams:
        """The channel list, the GroupNorm groups and the heads must fit each other (pilight.models.stack):
        a mismatch died in a modulo by zero or in min() of an empty list, far from the key."""
        ch = self.block_out_channels
        groups = min(32, min(ch))
        odd = [c for c in ch if c % groups]
        if odd:
            raise ValueError(
                f"block_out_channels {list(ch)}: every level's channels must be divisible by {groups}, the "
                f"GroupNorm groups (min(32, smallest level)); {odd} are not"
            )
        # attention runs at every level but the first (and in the mid block, at the last level's width)
        attended = sorted(set(ch[1:] + ch[-1:]))
        bad = [c for c in attended if c % self.attention_head_dim]
        if bad:
            raise ValueError(
                f"attention_head_dim {self.attention_head_dim} (the number of heads) must divide the channels of "
                f"every attention level; {bad} of block_out_channels {list(ch)} are not divisible by it"
            )
        params = self.estimated_parameters()
        if self.init != "pretrained" and params > MAX_UNET_PARAMS:
            raise ValueError(
                f"block_out_channels {list(ch)} with layers_per_block {self.layers_per_block} build a UNet of about "
                f"{params / 1e9:.1f}e9 parameters (~{16 * params / 2**30:.0f} GiB to train with AdamW), over the "
                f"limit of {MAX_UNET_PARAMS / 1e9:.0f}e9"
            )
        return self

    def estimated_parameters(self) -> int:
        """About how many parameters build_stack's UNet has (within ~10% for the configs in this repo):
        two 3x3 convolutions per resnet, attention at every level but the first, (2L + 1) blocks per level
        down and up, and the mid block; x1.6 for what the sum leaves out (norms, embeddings, skips)."""
        ch, layers, x = self.block_out_channels, self.layers_per_block, self.cross_attention_dim
        total = 0
        for i, c in enumerate(ch):
            per = 18 * c * c + ((12 * c * c + 2 * c * x) if i > 0 or len(ch) == 1 else 0)
            total += (2 * layers + 1) * per
        c = ch[-1]
        total += 48 * c * c + 2 * c * x
        return int(1.6 * total)


class ConditioningParams(_Section):
    kind: Literal["learned", "clip", "ball_tokens"] = Field(
        "learned",
        description="clip = CLIP image encoder (paper); learned = a named learned embedding; ball_tokens = the "
        "target ball as cross-attention tokens (ours, stage 2 only: pilight.diffusion.light_tokens)",
    )
    clip_path: str | None = None

    @model_validator(mode="after")
    def _path(self, info: ValidationInfo) -> ConditioningParams:
        if self.kind == "clip" and not self.clip_path:
            raise ValueError("conditioning.kind is 'clip' but conditioning.clip_path is not set")
        if self.kind == "clip" and not installed("transformers"):
            raise ValueError(missing("transformers", "conditioning.kind: clip"))
        _weights_folder(self.clip_path, "conditioning.clip_path", info)
        return self


class ScheduleParams(_Section):
    num_train_timesteps: int = Field(
        1000, ge=2, le=100_000, description="the paper: 1000; the schedule's arrays have one entry per step"
    )
    beta_schedule: Literal["linear", "scaled_linear", "squaredcos_cap_v2"] = "scaled_linear"
    rescale_zero_snr: bool = False
    timestep_spacing: Literal["leading", "trailing", "linspace"] = "leading"
    terminal_input: Literal["noise", "zero"] = Field(
        "noise",
        description="what the UNet reads as its latent at t = T-1: noise (the paper) | zero (ours, "
        "as E2E-FT): with zero terminal SNR x_T holds nothing of x0, so its mean, 0, removes input noise "
        "from the single-step prediction; training and every sampler see the same",
    )

    @model_validator(mode="after")
    def _terminal_input(self) -> ScheduleParams:
        if self.terminal_input == "zero" and not self.rescale_zero_snr:
            raise ValueError(
                "schedule.terminal_input 'zero' needs schedule.rescale_zero_snr: true (without zero "
                "terminal SNR x_T still carries x0, and zeroing it would discard signal)"
            )
        return self


class TrainParams(_Section):
    steps: int = Field(
        600,
        ge=0,
        le=MAX_STEPS,
        description="optimizer steps; 0 = the initial weights (e.g. unet.init: base) as the model",
    )
    batch_size: int = Field(2, ge=1, le=MAX_BATCH, description="samples per step; each carries every domain")
    lr: float = Field(2e-4, gt=0, le=1.0)
    weight_decay: float = Field(
        1e-2,
        ge=0,
        le=1.0,
        description="AdamW's decoupled decay: each step multiplies the weights by 1 - lr x weight_decay",
    )
    warmup_steps: int = Field(20, ge=0, le=MAX_STEPS)
    lr_schedule: Literal["constant", "cosine"] = Field(
        "constant", description="after warmup: constant, or a cosine decay to 0 at `steps`"
    )
    grad_accum: int = Field(1, ge=1, le=1024)
    max_grad_norm: float | None = Field(1.0, gt=0, le=1e6, description="gradient-norm clip; null = no clipping")
    mixed_precision: Literal["fp32", "bf16", "fp16", "auto"] = Field(
        "fp32",
        description="fp32 = no mixed precision (accelerate's 'no'); auto = bf16 on a GPU or a CPU with native "
        "bf16 kernels (AVX512-BF16/AMX), else fp32 (pilight.train.loop.resolve_mixed_precision)",
    )
    cond_dropout: float = Field(0.1, ge=0.0, le=1.0, description="drop the condition so CFG works")
    terminal_fraction: float = Field(
        0.0,
        ge=0.0,
        le=1.0,
        description="share of samples trained at t = T-1, the timestep single-step inference uses (the rest uniform)",
    )
    ema_decay: float = Field(
        0.0,
        ge=0.0,
        lt=1.0,
        description="exponential moving average of the weights, "
        "saved as the model (diffusers EMAModel, warmup (1+n)/(10+n)); 0 = off",
    )
    grad_share_every: int = Field(
        0,
        ge=0,
        le=MAX_STEPS,
        description="log each loss term's share of the gradient norm every N steps (stage 2's terms; stage 1's "
        "maps with objective: task; one backward per term, pilight.train.grad_shares); 0 = off",
    )
    checkpoint_every: int = Field(200, ge=1, le=MAX_STEPS)
    keep_checkpoints: int = Field(2, ge=1, le=1000, description="each holds the weights and AdamW's state")
    log_every: int = Field(10, ge=1, le=MAX_STEPS)
    image_every: int = Field(200, ge=1, le=MAX_STEPS)
    num_workers: int = Field(0, ge=0, le=256)
    seed: int | None = Field(
        None,
        ge=0,
        le=MAX_SEED,
        description="this stage's training seed; null = base.train_seed (else base.seed). Pins one stage: a "
        "stage retrained with its own seed on another kept as it was (the shipped base's stage 2)",
    )

    @field_validator("mixed_precision", mode="before")
    @classmethod
    def _yaml_no(cls, v):
        # Accelerate's own name, "no", is accepted too.  It is not the default: `dvc exp run -S`
        # rewrites params.yaml without its quotes, YAML 1.1 then reads False, and DVC sees every
        # section holding it as changed.
        return "fp32" if v in ("no", False) else v


class ModelParams(_Section):
    """What both diffusion stages share: built by pilight.models.stack.build_stack."""

    codec: CodecParams = CodecParams()
    unet: UNetParams = UNetParams()
    conditioning: ConditioningParams = ConditioningParams()
    cross_batch_attention: bool = Field(True, description="false = the ablation: vanilla self-attention")
    schedule: ScheduleParams = ScheduleParams()
    train: TrainParams = TrainParams()


class TaskLossParams(_Section):
    """Weights of stage 1's task losses (pilight.train.map_losses), for objective: task."""

    albedo: float = Field(1.0, ge=0.0, le=100.0, description="scale-invariant albedo MSE (structure)")
    albedo_level: float = Field(
        0.1, ge=0.0, le=100.0, description="(log alpha*)^2, the per-image albedo level, relative to albedo"
    )
    normal: float = Field(1.0, ge=0.0, le=100.0, description="angular error (radians)")
    roughness: float = Field(1.0, ge=0.0, le=100.0, description="L1")
    metallic: float = Field(1.0, ge=0.0, le=100.0, description="binary cross-entropy")


class AugmentParams(_Section):
    """Augmentations that are exact for renders: the flipped image's truth is the flipped truth."""

    flip: bool = Field(False, description="horizontal flip with probability 1/2, normals' x negated")
    crop: int | None = Field(
        None, ge=8, le=8192, description="train on random square crops of this side (pixels); null = whole images"
    )


class IntrinsicsParams(ModelParams):
    albedo_space: Literal["linear", "srgb"] = Field(
        "srgb", description="space the albedo is predicted in (Marigold habit): srgb spreads dark albedos over [-1, 1]"
    )
    objective: Literal["diffusion", "task"] = Field(
        "diffusion",
        description="diffusion = the paper: v-prediction MSE on latents at uniform timesteps; task = one "
        "evaluation at t = T-1 (where single-step inference runs) with losses on the decoded maps (E2E-FT)",
    )
    layout: Literal["domains", "joint"] = Field(
        "domains",
        description="domains = the paper: one UNet item per map, one-hot labels, cross-batch attention; "
        "joint = one UNet item whose output carries all four maps (a quarter of the UNet work)",
    )
    task_loss: TaskLossParams = TaskLossParams()
    augment: AugmentParams = AugmentParams()

    @model_validator(mode="after")
    def _objective(self) -> IntrinsicsParams:
        if self.objective == "task" and self.schedule.terminal_input != "zero":
            raise ValueError(
                "intrinsics.objective 'task' trains the single-step prediction from a zero latent at t = T-1, "
                "so it needs schedule.terminal_input: zero (and rescale_zero_snr: true)"
            )
        if self.layout == "joint" and self.unet.init == "pretrained":
            raise ValueError(
                "intrinsics.layout 'joint' predicts all maps from one UNet output, which a pretrained SD2/GeoWizard "
                "UNet (4 output channels) does not have; use layout: domains with unet.init: pretrained"
            )
        if self.conditioning.kind == "ball_tokens":
            raise ValueError(
                "intrinsics.conditioning.kind 'ball_tokens' reads the target light's ball, which stage 1 does not "
                "have; use learned or clip"
            )
        step = self.codec.factor * 2 ** (len(self.unet.block_out_channels) - 1)
        if self.augment.crop is not None and self.augment.crop % step:
            raise ValueError(
                f"intrinsics.augment.crop {self.augment.crop} must be divisible by {step} "
                "(the codec factor times the UNet's downsampling)"
            )
        return self


class FreeRelitForm(_Section):
    """The paper's form: the relit branch makes the relit image (or, ours, its change of the input);
    D and S are predicted beside it and enter only the loss."""

    kind: Literal["free"] = "free"
    target: Literal["image", "residual", "gain"] = Field(
        "image",
        description="image = the paper's relit branch; residual = its latent minus the input's latent; "
        "gain = the log ratio of relit to input display values (both: 'copy the input' is the zero prediction)",
    )
    resolution: Literal["full", "cell"] = Field(
        "full",
        description="full = a value per pixel (the paper); cell = the relit branch's change is one value "
        "per codec cell, bilinearly interpolated (smooth by construction; needs residual or gain)",
    )

    @model_validator(mode="after")
    def _cell_needs_a_change(self) -> FreeRelitForm:
        if self.resolution == "cell" and self.target == "image":
            raise ValueError(
                "form.resolution 'cell' smooths the relit branch's CHANGE of the input, so it needs "
                "form.target 'residual' or 'gain', not 'image'"
            )
        return self


class PhysicsFirstForm(_Section):
    """Ours (pilight.relight.physics_first): on the mask I_relit = A_x D_pred + S_pred, with D and S
    predicted as gains on their physics lookups D_calc and S_calc; off the mask the relit branch is a
    gain on the input. Light enters through physics."""

    kind: Literal["physics_first"] = "physics_first"
    resolution: Literal["full", "cell"] = Field(
        "cell", description="full = a gain per pixel; cell = one gain per codec cell, bilinearly interpolated"
    )
    albedo_source: Literal["effective", "conditioning"] = Field(
        "effective",
        description="A_x: effective = the albedo that explains the input under its own light (the ratio "
        "form; cancels stage-1 albedo errors); conditioning = the conditioning albedo",
    )
    source_light: Literal["estimated", "rendered"] = Field(
        "estimated",
        description="the input's own light for albedo_source effective: estimated = fitted to the input "
        "(pilight.physics.source_light; what a photo gets); rendered = the shards' ball of the input light",
    )
    specular_anchor: Literal["lookup", "ggx"] = Field(
        "ggx",
        description="S_calc: lookup = the gray ball minus its Lambertian twin read at the normal (knows no "
        "roughness); ggx = a microfacet highlight of the ball's dominant light with the conditioning "
        "roughness and Fresnel (pilight.physics.specular_model)",
    )

    @property
    def target(self) -> str:
        """What the relit branch denoises: always the gain (it is the image off the mask only)."""
        return "gain"


def _form_kind(v: Any) -> str | None:
    return v.get("kind") if isinstance(v, dict) else getattr(v, "kind", None)


# One of the two by its `kind` (a callable discriminator: every field of a section has a before-validator,
# which pydantic's plain `discriminator="kind"` does not allow).
RelitForm = Annotated[
    Annotated[FreeRelitForm, Tag("free")] | Annotated[PhysicsFirstForm, Tag("physics_first")],
    Discriminator(
        _form_kind,
        custom_error_type="relit_form_kind",
        custom_error_message="form.kind must be 'free' (the paper's relit branch) or 'physics_first' (ours)",
    ),
]


# Stage 2's form before it was one choice: six flat keys of `relight` (config.json of older models).
FLAT_FORM_KEYS = (
    "physics_first",
    "relit_target",
    "relit_resolution",
    "albedo_source",
    "source_light",
    "specular_anchor",
)


def form_from_flat(relight: dict) -> dict:
    """The `form` that the flat keys of an earlier version's `relight` section meant (their defaults then:
    the paper's free image branch at full resolution; lookup specular anchor)."""
    if relight.get("physics_first", False):
        return {
            "kind": "physics_first",
            "resolution": relight.get("relit_resolution", "full"),
            "albedo_source": relight.get("albedo_source", "effective"),
            "source_light": relight.get("source_light", "estimated"),
            "specular_anchor": relight.get("specular_anchor", "lookup"),
        }
    return {
        "kind": "free",
        "target": relight.get("relit_target", "image"),
        "resolution": relight.get("relit_resolution", "full"),
    }


def migrate_saved_relight(relight: dict) -> dict:
    """A saved stage-2 config (config.json's params) of any version -> this version's keys: the flat
    form keys become `form`. A config already in this form comes back unchanged."""
    if not any(k in relight for k in FLAT_FORM_KEYS):
        return relight
    kept = {k: v for k, v in relight.items() if k not in FLAT_FORM_KEYS}
    return {**kept, "form": form_from_flat(relight)}


class LevelPrior(_Section):
    """log l' = alpha + beta log l for the input light's estimated level l (pilight.relight.level_prior),
    fitted on the training inputs by benchmarks/fit_level_prior.py."""

    alpha: float = Field(ge=-5.0, le=5.0, description="the line's intercept, in log level")
    beta: float = Field(gt=0.0, le=2.0, description="its slope: < 1 shrinks toward the training lights' level")


class RelightParams(ModelParams):
    """Stage 2: L = L_vpred + (1/t)(lambda_ds L_DS + lambda_ps L_PS + lambda_rec L_rec)."""

    decomposition: bool = Field(True, description="false = the paper's ablation without the diffuse/specular branches")
    lambda_ds: float = Field(1.0, ge=0.0, le=MAX_LOSS_WEIGHT, description="lambda_1, diffuse-shading loss")
    lambda_ps: float = Field(1.0, ge=0.0, le=MAX_LOSS_WEIGHT, description="lambda_2, physical-shading loss")
    lambda_rec: float = Field(0.1, ge=0.0, le=MAX_LOSS_WEIGHT, description="lambda_3, reconstruction (feature) loss")
    t_min: float = Field(1.0, gt=0.0, le=100_000.0, description="floor of t in the 1/t weight")
    lambda_image: float = Field(
        0.0,
        ge=0.0,
        le=MAX_LOSS_WEIGHT,
        description="ours: the formed relit image vs the target (display-space "
        "MSE) on samples at t = T-1, where single-step inference "
        "runs (E2E-FT); 0 = the paper",
    )
    rec_features: Literal["pooled-rgb", "dinov2"] = Field(
        "pooled-rgb", description="dinov2 = the paper (needs dinov2_path)"
    )
    dinov2_path: str | None = None
    conditions: Literal["gt", "pred", "mix"] = Field("mix", description="intrinsics given to the model while training")
    pred_probability: float = Field(
        0.5, ge=0.0, le=1.0, description="share of stage-1 predictions when conditions: mix"
    )
    ds_ball: Literal["gray", "lambertian"] = Field("gray", description="ball unfolded for D_calculated (paper: gray)")
    form: RelitForm = Field(
        FreeRelitForm(),
        description="how the relit image is formed: free = the paper's relit branch; physics_first = ours",
    )
    intensity: Literal["relative", "absolute"] = Field(
        "absolute",
        description="relative = the target light's level is k times the input's own estimated light (k = "
        "level(ball_b) / level(ball_a) for rendered pairs; k = 1 keeps the exposure), in training and at test "
        "(pilight.relight.intensity); absolute = the ball as rendered (the paper)",
    )
    level_prior: LevelPrior | None = Field(
        None,
        description="relative intensity only: the input light's estimated level shrunk by a line fitted on the "
        "training inputs (benchmarks/fit_level_prior.py); train and run a model with the same prior; null = the "
        "estimate as it is",
    )
    identity_pairs: bool = Field(
        True,
        description="train on the shards' identity pairs (a -> a) too; false = cross-light pairs only "
        "(the reconstruction pairs stay in evaluation)",
    )
    d_calc_condition: tuple[Literal["relit", "diffuse", "specular"], ...] = Field(
        (),
        description="branches that also get D_calc (Lambertian lookup of the target ball with the conditioning "
        "normals) as a condition map; () = the paper",
    )

    @model_validator(mode="before")
    @classmethod
    def _one_form(cls, data: Any) -> Any:
        """The flat keys of earlier versions are refused by name, with the form that says the same."""
        if isinstance(data, dict) and (flat := [k for k in FLAT_FORM_KEYS if k in data]):
            if "form" in data:
                raise ValueError(
                    f"{', '.join(flat)}: stage 2's output form is one choice now, relight.form; these are its "
                    "options (physics_first is form.kind, relit_target form.target, relit_resolution "
                    "form.resolution, the rest keep their names): move them into relight.form"
                )
            raise ValueError(
                f"{', '.join(flat)}: stage 2's output form is one choice now, relight.form; the same model is "
                f"form: {json.dumps(form_from_flat(data))}"
            )
        return data

    @field_validator("d_calc_condition")
    @classmethod
    def _d_calc_branches(cls, v: tuple[str, ...]) -> tuple[str, ...]:
        if len(set(v)) != len(v):
            raise ValueError(f"d_calc_condition names a branch twice: {list(v)}")
        return v

    @model_validator(mode="after")
    def _dinov2(self, info: ValidationInfo) -> RelightParams:
        if self.form.kind == "physics_first" and not self.decomposition:
            raise ValueError(
                "relight.form physics_first forms the relit image from the diffuse and specular branches, so "
                "it needs decomposition: true (or form: {kind: free} for the ablation without them)"
            )
        if self.rec_features == "dinov2" and not self.dinov2_path:
            raise ValueError("rec_features is 'dinov2' but dinov2_path is not set (a local DINOv2 folder)")
        if self.rec_features == "dinov2" and not installed("transformers"):
            raise ValueError(missing("transformers", "rec_features: dinov2"))
        _weights_folder(self.dinov2_path, "dinov2_path", info)
        return self


class SamplingParams(_Section):
    mode: Literal["ddim", "single_step"] = "ddim"
    steps: int = Field(10, ge=1, le=10_000)
    cfg_scale: float = Field(1.0, ge=0.0, le=MAX_CFG, description="the paper: 1.0 in stage 1, 1.5 in stage 2")
    timestep_spacing: Literal["leading", "trailing", "linspace"] = "trailing"
    ensemble: int = Field(1, ge=1, le=MAX_ENSEMBLE)
    batch_size: int = Field(4, ge=1, le=MAX_BATCH)

    @model_validator(mode="after")
    def _items_per_call(self) -> SamplingParams:
        # one UNet call holds batch_size x ensemble samples (x2 with CFG, x the views of a sample)
        if self.batch_size * self.ensemble > MAX_BATCH:
            raise ValueError(
                f"batch_size {self.batch_size} x ensemble {self.ensemble} = {self.batch_size * self.ensemble} "
                f"samples in one UNet call, over the limit of {MAX_BATCH}: lower either"
            )
        return self


class RelightInferParams(SamplingParams):
    cfg_scale: float = Field(1.5, ge=0.0, le=MAX_CFG, description="the paper uses 1.5 in stage 2")
    split: Literal["val", "test"] = "test"


class InferIntrinsicsParams(SamplingParams):
    domains: tuple[str, ...] = DOMAINS
    splits: tuple[Literal["train", "val", "test"], ...] = ("train", "test")

    @field_validator("domains")
    @classmethod
    def _domains(cls, v: tuple[str, ...]) -> tuple[str, ...]:
        bad = [d for d in v if d not in DOMAINS]
        if bad or not v or len(set(v)) != len(v):
            raise ValueError(f"domains must be a non-empty subset of {list(DOMAINS)} without repeats; got {list(v)}")
        return tuple(d for d in DOMAINS if d in v)


class TradeParams(_Section):
    """The speed/accuracy sweep (the `trade` stage): one factor at a time around the infer params."""

    images: int = Field(
        4, ge=1, le=10_000, description="test images (stage 1) and test pairs (stage 2) per sweep point"
    )
    steps: tuple[Annotated[int, Field(ge=1, le=10_000)], ...] = Field(
        (1, 2, 4, 10, 25, 50), max_length=MAX_SWEEP, description="DDIM steps, swept for each spacing"
    )
    spacings: tuple[Literal["leading", "trailing", "linspace"], ...] = Field(("leading", "trailing"), max_length=3)
    intrinsics_cfg: tuple[Annotated[float, Field(ge=0.0, le=MAX_CFG)], ...] = Field(
        (1.0, 1.5, 2.0, 2.5), max_length=MAX_SWEEP, description="the paper's Table 5 range"
    )
    relight_cfg: tuple[Annotated[float, Field(ge=0.0, le=MAX_CFG)], ...] = Field((1.0, 1.5, 2.0), max_length=MAX_SWEEP)
    ensemble: tuple[Annotated[int, Field(ge=1, le=MAX_ENSEMBLE)], ...] = Field((1, 2, 4), max_length=MAX_SWEEP)
    render_spp: tuple[Annotated[int, Field(ge=1, le=MAX_SAMPLES)], ...] = Field(
        (4, 16, 64, 256), max_length=MAX_SWEEP, description="render side: samples per pixel"
    )
    render_reference_spp: int = Field(
        1024, ge=1, le=MAX_SAMPLES, description="the noise-free reference the spp points are compared with"
    )

    @field_validator("steps", "ensemble", "render_spp")
    @classmethod
    def _positive(cls, v: tuple[int, ...]) -> tuple[int, ...]:
        if not v or min(v) < 1:
            raise ValueError(f"must be a non-empty list of integers >= 1; got {list(v)}")
        return v

    @field_validator("intrinsics_cfg", "relight_cfg")
    @classmethod
    def _cfg(cls, v: tuple[float, ...]) -> tuple[float, ...]:
        if not v or min(v) < 0:
            raise ValueError(f"must be a non-empty list of CFG scales >= 0; got {list(v)}")
        return v


class EvaluateParams(_Section):
    lpips_net: Literal["alex", "vgg", "squeeze"] = "alex"
    lpips_backbone: str | None = Field(
        None, description="local safetensors of the LPIPS backbone; null = LPIPS reported as null with the reason"
    )
    grid_images: int = Field(
        4, ge=1, le=256, description="test images (pairs) in the intrinsics (relight) grid of reports/"
    )
    relight_lights: int = Field(
        6, ge=1, le=64, description="analytic lights around one test image in the relit-under-several-lights grid"
    )
    trade: TradeParams = TradeParams()

    @field_validator("lpips_backbone")
    @classmethod
    def _exists(cls, v: str | None) -> str | None:
        if v is not None and not Path(v).is_file():
            raise ValueError(f"file {v!r} does not exist")
        return v


from pilight.data.shard_params import ShardParams  # noqa: E402  (the shard stage's own module)

_SHARD_FIELDS = ShardParams.model_fields


class ShardSection(ShardParams, _Section):
    """The shard stage's own ShardParams with the upper bounds every section has (issue 36), refusing
    booleans for numbers and empty sub-sections like every other section."""

    maxcount: int = Field(1000, ge=1, le=10_000_000, description=_SHARD_FIELDS["maxcount"].description)
    maxsize: int = Field(500_000_000, ge=1, le=2**40, description=_SHARD_FIELDS["maxsize"].description)
    pairs_per_view: int | None = Field(
        None, ge=0, le=1_000_000, description=_SHARD_FIELDS["pairs_per_view"].description
    )


SECTIONS: dict[str, type[BaseModel]] = {
    "base": BaseParams,
    "render": RenderParams,
    "shard": ShardSection,
    "intrinsics": IntrinsicsParams,
    "infer_intrinsics": InferIntrinsicsParams,
    "relight": RelightParams,
    "relight_infer": RelightInferParams,
    "evaluate": EvaluateParams,
}


def _format(section: str, err: ValidationError) -> str:
    lines = [f"invalid params in section '{section}':"]
    for e in err.errors():
        key = ".".join(str(p) for p in (section, *e["loc"]))
        got = e.get("input")
        lines.append(f"  {key} = {got!r}: {e['msg']}")
    return "\n".join(lines)


class UniqueKeyLoader(yaml.SafeLoader):
    """SafeLoader that refuses a key given twice in one mapping (plain YAML keeps the last silently)."""

    def construct_mapping(self, node, deep=False):
        seen = {}
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=deep)
            if key in seen:
                raise yaml.constructor.ConstructorError(
                    "while constructing a mapping",
                    node.start_mark,
                    f"found duplicate key {key!r} (first on line {seen[key] + 1})",
                    key_node.start_mark,
                )
            seen[key] = key_node.start_mark.line
        return super().construct_mapping(node, deep=deep)


def read_params(path: str | Path) -> dict:
    """The whole params file: valid YAML, no duplicate keys, only known top-level sections."""
    path = Path(path)
    if not path.is_file():
        raise ParamsError(f"{path}: params file not found")
    try:
        text = path.read_bytes().decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ParamsError(
            f"{path}: not UTF-8 text (byte 0x{exc.object[exc.start]:02x} at offset {exc.start}); save it as UTF-8"
        ) from None
    except OSError as exc:
        raise ParamsError(f"{path}: cannot be read ({exc.strerror or exc})") from None
    try:
        raw = yaml.load(text, Loader=UniqueKeyLoader) or {}
    except yaml.YAMLError as exc:
        raise ParamsError(f"{path}: not valid YAML ({exc})") from exc
    if not isinstance(raw, dict):
        raise ParamsError(f"{path}: want a mapping of sections, got {type(raw).__name__}")
    unknown = [k for k in raw if k not in SECTIONS]
    if unknown:
        raise ParamsError(f"{path}: unknown top-level section(s) {unknown} (a typo?); known: {list(SECTIONS)}")
    return raw


def load_section(
    name: str, path: str | Path = "params.yaml", cls: type[BaseModel] | None = None, *, check_paths: bool = True
):
    """Read one section of params.yaml and validate it; raise ParamsError naming key and value.
    ``check_paths=False`` skips the weight folders' existence checks (their values are still validated)."""
    path = Path(path)
    raw = read_params(path)
    if name not in raw:
        raise ParamsError(f"{path}: missing section '{name}'")
    return _validate(cls or SECTIONS[name], name, raw[name], path, check_paths)


def _validate(model: type[BaseModel], name: str, raw, where: str | Path, check_paths: bool) -> BaseModel:
    # `render: null`, `render: 0`, `render: []` or `render: {}` took the class defaults silently (the render
    # stage then started the class's 144 bundles, not the file's): a section is a mapping with keys.
    if not isinstance(raw, dict):
        kind = {"list": "a list", "int": "a number", "float": "a number", "str": "a string", "bool": "a boolean"}
        shown = "null" if raw is None else f"{kind.get(type(raw).__name__, type(raw).__name__)} ({raw!r})"
        raise ParamsError(f"{where}: section '{name}' is {shown}, not a mapping of its keys")
    if not raw:
        raise ParamsError(f"{where}: section '{name}' is empty; give its keys (params.yaml has them all)")
    try:
        return model.model_validate(raw, context={"check_paths": check_paths, "from_file": True})
    except ValidationError as exc:
        raise ParamsError(f"{where}: " + _format(name, exc)) from None


def validate_sections(raw: dict, where: str | Path, *, check_paths: bool = True) -> dict[str, BaseModel]:
    """Every known section of a whole params mapping, validated; ParamsError naming ``where`` and the key."""
    return {
        name: _validate(model, name, raw[name], where, check_paths) for name, model in SECTIONS.items() if name in raw
    }
