"""The photo-level API: decompose and relight any picture with the two trained models.

    from pilight.pipeline import PILightPipeline
    from pilight import lights

    pipe = PILightPipeline.from_pretrained("models")          # models/intrinsics + models/relight
    parts = pipe.decompose("photo.jpg")                       # DecompositionOutput (numpy, input size)
    out = pipe.relight("photo.jpg", [lights.named("left"), lights.named("right")])
    out.relit[0]                                               # (H, W, 3) linear HDR under the first light
    pipe.save_pretrained("my_pilight")                         # the same layout, plus pipeline.json

It follows diffusers' conventions (``from_pretrained`` / ``save_pretrained`` of a folder, output
dataclasses) so the models drop into other people's code. The inference itself is the stages'
own: ``IntrinsicsModel.predict`` and ``RelightModel.predict`` (pilight.models), built from each model's
config.json (the params that trained it), so a saved model needs no params.yaml, and nothing of
training, shards or Blender is imported. This module adds what a
photo needs around them: its size (processing resolution, outputs back at the input's size), a
mask (all ones, or the photo's alpha: a photo has no ground-truth mask), the light balls, and a
memory estimate checked before anything large is allocated.

Stage 1 runs once per photo, however many lights stage 2 is asked for.

Integrity (issue 36): each stage's folder carries its manifest (``pilight.models.folder``: weights and
config.json), and a ``save_pretrained`` folder one more, ``checksums.json`` beside ``pipeline.json``,
covering pipeline.json and both stage manifests. ``from_pretrained`` requires them; a folder made by
hand loads with ``trust_unverified=True``, announced. pipeline.json and any ``from_pretrained``
override are validated by the models params.yaml's keys are (``PipelineSettings``).
"""

from __future__ import annotations

import json
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import torch
import torch.nn.functional as F
from pydantic import Field

from pilight import atomic
from pilight.data.layout import RELIT_MAPS
from pilight.detail import resize, with_input_detail
from pilight.lights import Light
from pilight.params import DOMAINS, BaseParams, RenderParams, SamplingParams, _Section
from pilight.photo import Photo, as_photo, check_size, lcm, processing_size
from pilight.relight.intensity import EXPOSURES, exposure_gain, relative_light

PIPELINE_FILE = "pipeline.json"
STAGES = ("intrinsics", "relight")
DEFAULT_RESOLUTION = 128  # the embedded default's render.resolution, used when no params.yaml says otherwise
GIB = 1024**3

# Memory estimate: the UNet's activations per batch item are ACT_FLOATS_PER_CHANNEL_PIXEL floats
# per (channel x latent pixel) summed over its levels, and the full-size arrays of a photo (decoded
# input, every output, their resized copies) HOST_FLOATS each. Checked against
# benchmarks/bench_cli.py (peak RSS above the loaded models, embedded-default UNets, 2 CPU cores):
# the estimate is 1.3-2.6x the measured peaks at 256^2 and 512^2. It errs high on purpose: the guard
# must refuse a photo that would not fit, and a refused photo can still be forced with --max-memory.
ACT_FLOATS_PER_CHANNEL_PIXEL = 40
HOST_FLOATS_DECOMPOSE = 2 * (4 + 8)  # (rgb + mask + 8 output channels), times 2 for resize copies
HOST_FLOATS_PER_LIGHT = 2 * 9  # relit, D, S
MEMORY_FRACTION = 0.8  # default limit: this share of the machine's (or the GPU's) memory
MAX_PROCESSING_RESOLUTION = 16384  # longer side; the memory guard is the real limit, this one catches typos
MANIFEST = "checksums.json"  # a save_pretrained folder's own manifest (pipeline.json + the stage manifests)
PIPELINE_COVERED = (PIPELINE_FILE, "intrinsics/checksums.json", "relight/checksums.json")


class PipelineError(ValueError):
    """The pipeline cannot run as asked (models, sizes, memory); the message says what to change."""


class MemoryLimitError(PipelineError):
    """Processing would need more memory than allowed; raised before anything large is allocated."""


class PipelineSettings(_Section):
    """pipeline.json's keys, validated as params.yaml's are (the same constraints as render.ball_resolution,
    base.seed and the sampling sections): a saved ``processing_resolution: -5`` was a torch traceback."""

    processing_resolution: int = Field(
        DEFAULT_RESOLUTION, ge=0, le=MAX_PROCESSING_RESOLUTION, description="longer side; 0 = the photo's own"
    )
    ball_resolution: Annotated[int, *RenderParams.model_fields["ball_resolution"].metadata] = 32
    seed: Annotated[int, *BaseParams.model_fields["seed"].metadata] = 42
    intrinsics_sampling: SamplingParams
    relight_sampling: SamplingParams


def _settings_error(where: str, exc) -> str:
    return "; ".join(f"{'.'.join(map(str, e['loc']))} = {e.get('input')!r}: {e['msg']}" for e in exc.errors())


@dataclass(frozen=True)
class PipelineConfig:
    """What the pipeline adds to the two models; saved as pipeline.json by ``save_pretrained``."""

    processing_resolution: int = DEFAULT_RESOLUTION  # longer side the models run at; 0 = the photo's own size
    ball_resolution: int = 32  # the embedded default's render.ball_resolution
    seed: int = 42
    intrinsics_sampling: SamplingParams = SamplingParams(mode="single_step", cfg_scale=1.0)
    relight_sampling: SamplingParams = SamplingParams(mode="single_step", cfg_scale=1.5)

    def to_json(self) -> dict:
        return {
            "processing_resolution": self.processing_resolution,
            "ball_resolution": self.ball_resolution,
            "seed": self.seed,
            "intrinsics_sampling": self.intrinsics_sampling.model_dump(mode="json"),
            "relight_sampling": self.relight_sampling.model_dump(mode="json"),
        }

    @classmethod
    def from_json(cls, d: dict, where: str) -> PipelineConfig:
        """``d`` (pipeline.json's content) validated by ``PipelineSettings``; PipelineError naming ``where`` and the key."""
        from pydantic import ValidationError

        if not isinstance(d, dict):
            raise PipelineError(f"{where}: not a valid pipeline config (want an object, got {type(d).__name__})")
        try:
            s = PipelineSettings.model_validate(d)
        except ValidationError as exc:
            raise PipelineError(f"{where}: not a valid pipeline config: {_settings_error(where, exc)}") from None
        return cls(**{k: getattr(s, k) for k in PipelineSettings.model_fields})

    def validated(self, where: str) -> PipelineConfig:
        """This config checked by ``PipelineSettings`` (after overrides): PipelineError naming the key."""
        from pydantic import ValidationError

        try:
            PipelineSettings.model_validate(
                {
                    **{k: getattr(self, k) for k in PipelineSettings.model_fields},
                    "intrinsics_sampling": self.intrinsics_sampling.model_dump(),
                    "relight_sampling": self.relight_sampling.model_dump(),
                }
            )
        except ValidationError as exc:
            raise PipelineError(f"{where}: {_settings_error(where, exc)}") from None
        return self

    @classmethod
    def from_params(cls, params_path: str | Path) -> PipelineConfig:
        """The defaults a DVC checkout implies: base.seed, render.resolution / ball_resolution,
        infer_intrinsics and relight_infer (sampling). ParamsError when the file is invalid."""
        from pilight.params import load_section

        base, render = load_section("base", params_path), load_section("render", params_path)
        ii, ri = load_section("infer_intrinsics", params_path), load_section("relight_infer", params_path)
        keep = set(SamplingParams.model_fields)
        return cls(
            processing_resolution=render.resolution,
            ball_resolution=render.ball_resolution,
            seed=base.seed,
            intrinsics_sampling=SamplingParams(**{k: getattr(ii, k) for k in keep}),
            relight_sampling=SamplingParams(**{k: getattr(ri, k) for k in keep}),
        )


@dataclass
class DecompositionOutput:
    """Stage 1 at the input's size. All maps linear, float32, (H, W, C)."""

    albedo: np.ndarray  # (H, W, 3) in [0, 1]
    normal: np.ndarray  # (H, W, 3) unit, camera space (x right, y up, z toward the camera); 0 off the mask
    roughness: np.ndarray  # (H, W, 1) in [0, 1]
    metallic: np.ndarray  # (H, W, 1) in [0, 1]
    mask: np.ndarray | None  # (H, W) from the photo's alpha, or None (all of the picture)
    processing_size: tuple[int, int]
    # The processing-size tensors stage 2 is conditioned on, so relight() after decompose() reuses them.
    conditions: dict[str, torch.Tensor] = field(default_factory=dict, repr=False)


@dataclass
class RelightOutput:
    """Stage 2 at the input's size, one entry per light along the first axis. Linear HDR, float32."""

    relit: np.ndarray  # (K, H, W, 3)
    diffuse: np.ndarray | None  # (K, H, W, 3) D; None when the model has no decomposition branches
    specular: np.ndarray | None  # (K, H, W, 3) S
    balls: np.ndarray  # (K, S, S, 3) the light balls the model was given
    lights: list[Light]
    exposure_gain: np.ndarray  # (K,) what ``exposure="photo"`` multiplied each light by (1 with "light" or absolute)
    intrinsics: DecompositionOutput  # what stage 2 was conditioned on


def pick_device(device: str = "auto") -> torch.device:
    if device == "auto":
        if torch.cuda.is_available():
            return torch.device("cuda")
        if getattr(torch.backends, "mps", None) is not None and torch.backends.mps.is_available():
            return torch.device("mps")
        return torch.device("cpu")
    if device not in ("cpu", "cuda", "mps") and not device.startswith("cuda:"):
        raise PipelineError(f"unknown device {device!r}; use auto, cpu, cuda or mps")
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise PipelineError(
            f"device {device!r} asked for, but this torch has no CUDA device (torch {torch.__version__})"
        )
    if device == "mps" and not (getattr(torch.backends, "mps", None) is not None and torch.backends.mps.is_available()):
        raise PipelineError("device 'mps' asked for, but MPS is not available here")
    return torch.device(device)


def _flatten(d: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(d, dict):
        out: dict[str, Any] = {}
        for k, v in d.items():
            out.update(_flatten(v, f"{prefix}.{k}" if prefix else str(k)))
        return out
    return {prefix: list(d) if isinstance(d, tuple) else d}


def _format_validation(stage: str, exc) -> str:
    return "; ".join(f"{'.'.join(map(str, (stage, *e['loc'])))} = {e.get('input')!r}: {e['msg']}" for e in exc.errors())


def load_stage(folder: Path, stage: str, device: torch.device, *, trust_unverified: bool = False):
    """One trained model (config.json + model.safetensors, verified by its manifest before either is read)
    -> its inference model (pilight.models), in eval mode on ``device``, and the params dict it was saved with."""
    from pydantic import ValidationError

    from pilight.models.folder import load_model, verify_model_folder
    from pilight.models.intrinsics import IntrinsicsModel
    from pilight.models.relight import RelightModel
    from pilight.models.stack import ModelError
    from pilight.params import IntrinsicsParams, RelightParams, migrate_saved_relight

    d = Path(folder) / stage
    cfg, weights = d / "config.json", d / "model.safetensors"
    if not cfg.is_file() or not weights.is_file():
        missing = cfg if not cfg.is_file() else weights
        raise PipelineError(
            f"{missing}: no trained {stage} model there. Run `dvc repro train_relight` first "
            "(it trains both stages into models/), or point --models at a folder holding "
            "intrinsics/ and relight/ (each config.json + model.safetensors)"
        )
    try:
        verify_model_folder(d, trust_unverified=trust_unverified)
    except ModelError as exc:
        raise PipelineError(
            str(exc).replace("rerun the training stage", "retrain with `dvc repro train_relight`")
        ) from None
    try:
        saved = json.loads(cfg.read_text(encoding="utf-8"))["params"]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise PipelineError(f"{cfg}: unreadable model config ({exc}); retrain with `dvc repro train_relight`") from None
    if stage == "relight":
        saved = migrate_saved_relight(saved)  # a model saved before stage 2's form was one choice
    raw = dict(saved)
    if stage == "relight":
        # Training-only keys that name files of the training machine (the conditions' predictions, the
        # L_rec features' weights): inference reads neither, so they must not fail validation here.
        raw.update(conditions="gt", rec_features="pooled-rgb", dinov2_path=None)
    try:
        p = (IntrinsicsParams if stage == "intrinsics" else RelightParams).model_validate(raw)
    except ValidationError as exc:
        raise PipelineError(f"{cfg}: {_format_validation(stage, exc)}") from None
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # e.g. decomposition: false is reported by the stages, not here
            model = IntrinsicsModel(p) if stage == "intrinsics" else RelightModel(p)
        load_model(model.stack, d, verified=True)
    except ModelError as exc:
        raise PipelineError(f"{exc} (the weights do not fit {cfg}: retrain with `dvc repro train_relight`)") from None
    model.stack.model.eval()
    return model.to(device), saved


class PILightPipeline:
    """Stage 1 (photo -> albedo, normal, roughness, metallic) and stage 2 (+ light -> relit, D, S)."""

    def __init__(
        self,
        intrinsics,
        relight,
        config: PipelineConfig = PipelineConfig(),
        device: str | torch.device = "cpu",
        saved_params: dict[str, dict] | None = None,
    ):
        self.intrinsics_model, self.relight_model, self.config = intrinsics, relight, config
        self.device = torch.device(device)
        self.saved_params = saved_params or {}

    # --- loading and saving -------------------------------------------------------------------
    @classmethod
    def from_pretrained(
        cls,
        folder: str | Path = "models",
        *,
        device: str = "auto",
        params: str | Path | None = None,
        trust_unverified: bool = False,
        **overrides,
    ) -> PILightPipeline:
        """Load ``folder/intrinsics`` and ``folder/relight``.

        Settings come from ``folder/pipeline.json`` (written by ``save_pretrained``), else from
        ``params`` (a params.yaml: render.resolution, infer_intrinsics, relight_infer), else the
        defaults; ``overrides`` (PipelineConfig fields) win over all three. Every file that decides what
        the pipeline computes is checked against its manifest first (module docstring); a folder made by
        hand, without manifests, loads with ``trust_unverified=True`` and an UnverifiedModelWarning."""
        from pilight.models.folder import verify_manifest
        from pilight.models.stack import ModelError

        folder = Path(folder)
        if not folder.is_dir():
            raise PipelineError(
                f"{folder}: models folder not found. Run `dvc repro train_relight` first (it trains "
                "both stages into models/), or pass --models DIR"
            )
        config = PipelineConfig()
        pipeline_file = folder / PIPELINE_FILE
        if pipeline_file.is_file() or (folder / MANIFEST).is_file():
            # a save_pretrained folder: its manifest vouches for pipeline.json and both stage manifests
            try:
                verify_manifest(folder, PIPELINE_COVERED, trust_unverified=trust_unverified, fix="save it again")
            except ModelError as exc:
                raise PipelineError(str(exc)) from None
        if pipeline_file.is_file():
            try:
                raw = json.loads(pipeline_file.read_text(encoding="utf-8"))
            except (OSError, ValueError) as exc:
                raise PipelineError(f"{pipeline_file}: unreadable ({exc})") from None
            config = PipelineConfig.from_json(raw, str(pipeline_file))
        elif params is not None and Path(params).is_file():
            config = PipelineConfig.from_params(params)
        unknown = sorted(set(overrides) - set(PipelineSettings.model_fields))
        if unknown:
            raise PipelineError(
                f"from_pretrained: unknown setting(s) {unknown}; known: {list(PipelineSettings.model_fields)}"
            )
        config = replace(config, **overrides).validated("from_pretrained" if overrides else str(folder))
        dev = pick_device(device) if isinstance(device, str) else torch.device(device)
        t1, s1 = load_stage(folder, "intrinsics", dev, trust_unverified=trust_unverified)
        t2, s2 = load_stage(folder, "relight", dev, trust_unverified=trust_unverified)
        return cls(t1, t2, config, dev, {"intrinsics": s1, "relight": s2})

    def save_pretrained(self, folder: str | Path, dtype: torch.dtype | None = None) -> Path:
        """``folder/intrinsics``, ``folder/relight`` (each model.safetensors + config.json + checksums.json,
        the layout of the pipeline's models/), ``folder/pipeline.json`` and, last, ``folder/checksums.json``
        over pipeline.json and both stage manifests; every file written, then renamed, so what this writes
        always loads with ``from_pretrained``. ``dtype`` (e.g. torch.float16): the weights' storage type
        (they load back as float32)."""
        from pilight.models.folder import save_model, write_manifest

        folder = Path(folder)
        self.config.validated("save_pretrained")
        for stage, task in (("intrinsics", self.intrinsics_model), ("relight", self.relight_model)):
            params = self.saved_params.get(stage) or task.p.model_dump(mode="json")
            save_model(task.stack, folder / stage, params, dtype=dtype)
        atomic.write_json(folder / PIPELINE_FILE, self.config.to_json(), sort_keys=True)
        write_manifest(folder, PIPELINE_COVERED)
        return folder

    def stale_keys(self, params_path: str | Path) -> dict[str, list[str]]:
        """Per stage, the params.yaml keys whose value differs from what the saved model was trained
        with (the model is then older than params.yaml: `dvc repro` would retrain it)."""
        from pilight.params import load_section

        out = {}
        for stage in STAGES:
            now = _flatten(load_section(stage, params_path).model_dump(mode="json"))
            then = _flatten(self.saved_params.get(stage, {}))
            out[stage] = sorted(f"{stage}.{k}" for k in set(now) | set(then) if now.get(k) != then.get(k))
        return out

    # --- sizes and memory ---------------------------------------------------------------------
    @property
    def size_multiple(self) -> int:
        """Processing sizes are multiples of this: each codec's factor times its UNet's downsampling."""
        m = []
        for task in (self.intrinsics_model, self.relight_model):
            levels = len(task.stack.model.unet.config.block_out_channels)
            m.append(task.stack.codec.factor * 2 ** (levels - 1))
        return lcm(*m)

    def processing_size(self, h: int, w: int, resolution: int | None = None) -> tuple[int, int]:
        res = self.config.processing_resolution if resolution is None else resolution
        return processing_size(h, w, res, self.size_multiple)

    def _items(self, task, views: int, sp: SamplingParams, samples: int) -> int:
        return samples * views * sp.ensemble * (2 if sp.cfg_scale != 1.0 else 1)

    def _activation_bytes(self, task, ph: int, pw: int, items: int) -> int:
        f = task.stack.codec.factor
        chans = task.stack.model.unet.config.block_out_channels
        per_item = sum(c * (ph // f) * (pw // f) / 4**i for i, c in enumerate(chans)) * ACT_FLOATS_PER_CHANNEL_PIXEL
        return int(items * per_item * 4)

    def estimate_memory(self, h: int, w: int, lights: int = 0, resolution: int | None = None) -> dict[str, int]:
        """Bytes a photo of h x w needs: ``host`` (full-size arrays) and ``device`` (the UNet's
        activations at the processing size); lights = 0 for decompose only."""
        ph, pw = self.processing_size(h, w, resolution)
        c = self.config
        dev = self._activation_bytes(
            self.intrinsics_model, ph, pw, self._items(self.intrinsics_model, len(DOMAINS), c.intrinsics_sampling, 1)
        )
        if lights:
            chunk = min(lights, c.relight_sampling.batch_size)
            dev = max(
                dev,
                self._activation_bytes(
                    self.relight_model,
                    ph,
                    pw,
                    self._items(self.relight_model, self.relight_model.V, c.relight_sampling, chunk),
                ),
            )
        host = 4 * h * w * (HOST_FLOATS_DECOMPOSE + HOST_FLOATS_PER_LIGHT * lights)
        if self.device.type == "cpu":
            host += dev
        return {"host": host, "device": dev if self.device.type != "cpu" else 0, "processing": (ph, pw)}

    def memory_limits(self, max_memory: float | None = None) -> dict[str, int]:
        """Bytes allowed on the host and on the device: ``max_memory`` (bytes) for both, else
        MEMORY_FRACTION of the machine's RAM and of the GPU's memory."""
        if max_memory is not None:
            return {"host": int(max_memory), "device": int(max_memory)}
        import psutil

        host = int(psutil.virtual_memory().total * MEMORY_FRACTION)
        device = host
        if self.device.type == "cuda":
            device = int(torch.cuda.get_device_properties(self.device).total_memory * MEMORY_FRACTION)
        return {"host": host, "device": device}

    def check_memory(
        self,
        h: int,
        w: int,
        lights: int = 0,
        name: str = "image",
        resolution: int | None = None,
        max_memory: float | None = None,
    ) -> None:
        """MemoryLimitError, before anything is allocated, when ``estimate_memory`` exceeds the limits."""
        est, lim = self.estimate_memory(h, w, lights, resolution), self.memory_limits(max_memory)
        ph, pw = est["processing"]
        for where in ("host", "device"):
            if est[where] > lim[where]:
                raise MemoryLimitError(
                    f"{name}: {w}x{h} pixels, processed at {pw}x{ph}, needs about {est[where] / GIB:.1f} GiB of "
                    f"{'memory' if where == 'host' else self.device.type + ' memory'}, over the limit of "
                    f"{lim[where] / GIB:.1f} GiB. Use a smaller --resolution, or raise the limit with --max-memory GIB"
                )

    # --- inference ----------------------------------------------------------------------------
    def _prepare(self, image, resolution: int | None, name: str) -> tuple[Photo, torch.Tensor, torch.Tensor]:
        photo = as_photo(image, name)
        h, w = photo.size
        check_size(h, w, photo.name)
        ph, pw = self.processing_size(h, w, resolution)
        x = torch.from_numpy(photo.rgb).permute(2, 0, 1)[None]
        x = resize(x, (ph, pw)).clamp_min(0)
        if photo.mask is None:
            m = torch.ones(1, 1, ph, pw)
        else:
            m = (resize(torch.from_numpy(photo.mask)[None, None], (ph, pw)) >= 0.5).float()
            if not bool(m.any()):  # relit as if empty before (issue 36)
                from pilight.photo import PhotoError

                raise PhotoError(
                    f"{photo.name}: its alpha mask ({int(photo.mask.sum())} pixel(s)) vanishes at the processing "
                    f"size {pw}x{ph}: nothing is left to process; use a larger --resolution or a larger mask"
                )
        return photo, x, m

    def to(self, device: str | torch.device) -> PILightPipeline:
        """Both models on ``device`` (diffusers' habit); returns the pipeline."""
        dev = pick_device(device) if isinstance(device, str) else torch.device(device)
        self.intrinsics_model.to(dev)
        self.relight_model.to(dev)
        self.device = dev
        return self

    def _sampling(
        self, saved: SamplingParams, steps: int | None, guidance: float | None, ensemble: int | None
    ) -> SamplingParams:
        """The saved config's sampling with a call's own settings on top (diffusers' per-call arguments):
        ``num_inference_steps`` 1 is single-step, more is DDIM with that many steps."""
        update: dict[str, Any] = {}
        if steps is not None:
            update |= {"mode": "single_step" if steps == 1 else "ddim", "steps": steps}
        if guidance is not None:
            update["cfg_scale"] = guidance
        if ensemble is not None:
            update["ensemble"] = ensemble
        if not update:
            return saved
        from pydantic import ValidationError

        try:
            return SamplingParams.model_validate(saved.model_dump() | update)
        except ValidationError as exc:
            raise PipelineError(f"sampling settings of this call: {_format_validation('sampling', exc)}") from None

    @torch.no_grad()
    def decompose(
        self,
        image,
        *,
        resolution: int | None = None,
        name: str = "<image>",
        num_inference_steps: int | None = None,
        guidance_scale: float | None = None,
        ensemble_size: int | None = None,
        generator: torch.Generator | None = None,
    ) -> DecompositionOutput:
        """A photo (path, PIL, numpy, tensor: ``photo.as_photo``) -> its intrinsics at the input's size.

        Sampling defaults to the saved config's (``pipeline.json``: single step); ``num_inference_steps``,
        ``guidance_scale`` and ``ensemble_size`` change it for this call, and ``generator`` replaces the
        config's seed (the default makes every call give the same bytes)."""
        photo, x, m = self._prepare(image, resolution, name)
        sp = self._sampling(self.config.intrinsics_sampling, num_inference_steps, guidance_scale, ensemble_size)
        gen = generator if generator is not None else torch.Generator().manual_seed(self.config.seed)
        pred = self.intrinsics_model.predict(x.to(self.device), DOMAINS, sp, gen)
        cond = {d: pred[d].float().cpu() for d in DOMAINS}
        cond["normal"] = cond["normal"] * m  # the contract: normals are 0 off the mask
        cond["image"], cond["mask"] = x, m
        return self._decomposition(photo, cond)

    def _decomposition(self, photo: Photo, cond: dict[str, torch.Tensor]) -> DecompositionOutput:
        h, w = photo.size
        up = {d: resize(cond[d], (h, w)) for d in DOMAINS}
        n = F.normalize(up["normal"], dim=1, eps=1e-6)
        if photo.mask is not None:
            n = n * torch.from_numpy(photo.mask)[None, None]
        hwc = lambda t: np.ascontiguousarray(t[0].permute(1, 2, 0).numpy(), dtype=np.float32)
        return DecompositionOutput(
            albedo=hwc(up["albedo"].clamp(0, 1)),
            normal=hwc(n),
            roughness=hwc(up["roughness"].clamp(0, 1)),
            metallic=hwc(up["metallic"].clamp(0, 1)),
            mask=photo.mask,
            processing_size=tuple(cond["image"].shape[-2:]),
            conditions=cond,
        )

    @torch.no_grad()
    def relight(
        self,
        image,
        lights: Light | Sequence[Light],
        *,
        resolution: int | None = None,
        intrinsics: DecompositionOutput | None = None,
        name: str = "<image>",
        absolute: bool = False,
        exposure: str = "photo",
        num_inference_steps: int | None = None,
        guidance_scale: float | None = None,
        ensemble_size: int | None = None,
        generator: torch.Generator | None = None,
    ) -> RelightOutput:
        """A photo under each of ``lights``: stage 1 once (or ``intrinsics`` from ``decompose`` of the
        same photo at the same resolution), then stage 2 for all lights in batches of
        ``relight_sampling.batch_size``.

        Intensity is relative by default: a light of intensity k gets k times the photo's own estimated
        light (k = 1 keeps the exposure; pilight.relight.intensity). ``absolute``: the lights' balls as
        they are (a calibrated plate).

        ``exposure`` (relative intensity only): ``photo`` scales each relit image (its light, by linearity)
        so that its mean luminance on the mask is k times the photo's; ``light`` keeps the light's level,
        so a light from the side darkens the picture (pilight.relight.intensity).

        ``num_inference_steps``, ``guidance_scale``, ``ensemble_size`` and ``generator`` are stage 2's
        for this call, as in ``decompose`` (stage 1 runs with the config's; pass ``intrinsics`` from a
        ``decompose`` call to choose its own)."""
        lights = [lights] if isinstance(lights, Light) else list(lights)
        if not lights:
            raise PipelineError("relight needs at least one light")
        if exposure not in EXPOSURES:
            raise PipelineError(f"exposure must be one of {', '.join(EXPOSURES)}, got {exposure!r}")
        photo, x, m = self._prepare(image, resolution, name)
        if intrinsics is None:
            intrinsics = self.decompose(photo, resolution=resolution, name=name)
        elif intrinsics.processing_size != tuple(x.shape[-2:]):
            raise PipelineError(
                f"intrinsics were computed at {intrinsics.processing_size}, but this call processes "
                f"at {tuple(x.shape[-2:])}; pass the same resolution"
            )
        cond = intrinsics.conditions
        s = self.config.ball_resolution
        balls = torch.stack([resize(l.ball.float()[None], (s, s))[0] for l in lights]).clamp_min(0)
        intensity = "absolute" if absolute else "relative"
        levels = torch.tensor([float(l.intensity) for l in lights])
        given = balls if absolute else relative_light(balls, levels)
        sp = self._sampling(self.config.relight_sampling, num_inference_steps, guidance_scale, ensemble_size)
        outs: dict[str, list[torch.Tensor]] = {}
        for start in range(0, len(lights), sp.batch_size):
            b = given[start : start + sp.batch_size]
            k = b.shape[0]
            rep = lambda t: t.expand(k, *t.shape[1:]).to(self.device)  # noqa: B023 (called within this iteration)
            batch = {"image_a": rep(x), "ball_b": b.to(self.device), "mask": rep(m)}
            intr = {d: rep(cond[d]) for d in DOMAINS}
            gen = generator if generator is not None else torch.Generator().manual_seed(self.config.seed)
            pred = self.relight_model.predict(batch, sp, gen, intr, intensity=intensity)
            for key, v in pred.items():
                outs.setdefault(key, []).append(v.float().cpu())
        h, w = photo.size
        cat = {key: torch.cat(v) for key, v in outs.items()}
        lit = {key: cat[key] for key in RELIT_MAPS if key in cat}  # what the light makes (not A_x)
        gain = torch.ones(len(lights))
        if not absolute and exposure == "photo":
            gain = exposure_gain(lit["relit"], x, m, levels)
            lit = {key: v * gain[:, None, None, None] for key, v in lit.items()}
        hwc = lambda t: t.clamp_min(0).permute(0, 2, 3, 1).contiguous().numpy()
        full = {key: hwc(resize(v, (h, w))) for key, v in lit.items() if key != "relit"}
        # the relit image keeps the photo's full-resolution detail: the change is carried at the processing
        # size and applied to the full-size input (pilight.detail)
        full_input = torch.from_numpy(photo.rgb).permute(2, 0, 1)[None]
        full["relit"] = hwc(with_input_detail(lit["relit"], lit.get("specular"), x, full_input))
        return RelightOutput(
            relit=full["relit"],
            diffuse=full.get("diffuse"),
            specular=full.get("specular"),
            balls=balls.permute(0, 2, 3, 1).contiguous().numpy(),
            lights=lights,
            intrinsics=intrinsics,
            exposure_gain=gain.numpy(),
        )
