"""The shard schema: what one training sample is, and how its values reach the model.

One sample = one (scene, view, light). Shard members are `<key>.<name>.exr` (float16 EXR made
by `pilight.data.exr`) and `<key>.meta.json`, with key `<scene>_v<view:02d>_l<light:02d>`.
In memory (renders, `validate_sample`) maps are H x W x C float32; loaders give C x H x W
float32 tensors. Every map is LINEAR: sRGB appears only in PNG previews for people
(pilight.data.colour: `srgb_preview`, `to_uint8`), never in shards or model inputs.

| key       | C | values                  | meaning                                   | to [-1, 1]       |
|-----------|---|-------------------------|-------------------------------------------|------------------|
| image     | 3 | [0, 65504] linear HDR   | beauty render under this light            | hdr_to_model     |
| diffuse   | 3 | [0, 65504] linear HDR   | D in image = albedo * D + specular        | hdr_to_model     |
| specular  | 3 | [0, 65504] linear HDR   | S (glossy, transmission, emission, bg)    | hdr_to_model     |
| ball      | 3 | [0, 65504] linear HDR   | gray ball lit like the scene (own size)   | hdr_to_model     |
| albedo    | 3 | [0, 1] linear           | Principled Base Color                     | 2x - 1           |
| roughness | 1 | [0, 1]                  | Principled Roughness                      | 2x - 1           |
| metallic  | 1 | [0, 1]                  | Principled Metallic                       | 2x - 1           |
| mask      | 1 | {0, 1}                  | 1 = fully covered by Principled surfaces  | 2x - 1           |
| normal    | 3 | [-1, 1], unit on mask   | camera space: x right, y up, z to camera  | identity         |
| meta      | - | JSON object             | scene, kind, split, view, light, camera, light_params, manifest_extra, render |

hdr_to_model (the tone map) lives with the rest of colour in pilight.data.colour.
65504 is the float16 maximum: shards store float16, so the render must stay below it.
float16 rounding means image = albedo * diffuse + specular holds in shards to ~1e-3 relative,
not exactly (the render folder keeps float32 where it must hold exactly).
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pilight.data.colour import HDR_MAX, hdr_to_model, model_to_hdr

SCHEMA_VERSION = 1
SPLITS = ("train", "val", "test")
META_KEYS = ("scene", "kind", "split", "view", "light", "camera", "light_params")


class DataError(ValueError):
    """Bad input to the shard stage or loaders; the message names the sample and file."""


class SampleError(DataError):
    """One sample breaks the schema (NaN/Inf, shape, range, missing or unreadable file)."""


@dataclass(frozen=True)
class MapSpec:
    channels: int
    lo: float
    hi: float
    encoding: str  # "hdr" | "unit" | "normal": which [-1, 1] mapping applies
    per_light: bool  # True: one per (view, light); False: shared by all lights of a view
    image_sized: bool = True  # False: the ball has its own resolution


SPECS: dict[str, MapSpec] = {
    "image": MapSpec(3, 0.0, HDR_MAX, "hdr", True),
    "diffuse": MapSpec(3, 0.0, HDR_MAX, "hdr", True),
    "specular": MapSpec(3, 0.0, HDR_MAX, "hdr", True),
    "ball": MapSpec(3, 0.0, HDR_MAX, "hdr", True, image_sized=False),
    "ball_lambertian": MapSpec(3, 0.0, HDR_MAX, "hdr", True, image_sized=False),  # optional
    "albedo": MapSpec(3, 0.0, 1.0, "unit", False),
    "roughness": MapSpec(1, 0.0, 1.0, "unit", False),
    "metallic": MapSpec(1, 0.0, 1.0, "unit", False),
    "mask": MapSpec(1, 0.0, 1.0, "unit", False),
    "normal": MapSpec(3, -1.0, 1.0, "normal", False),
}
OPTIONAL_MAPS = frozenset({"ball_lambertian"})
REQUIRED_MAPS = tuple(k for k in SPECS if k not in OPTIONAL_MAPS)
NORMAL_LENGTH_TOL = 1e-2  # float16 rounding of a unit vector stays well inside this
IDENTITY_RTOL, IDENTITY_ATOL = 1e-2, 1e-3  # image vs albedo * diffuse + specular


def unit_to_model(x):
    """[0, 1] maps (albedo, roughness, metallic, mask) -> [-1, 1]."""
    return 2.0 * x - 1.0


def model_to_unit(y):
    return (y.clip(-1.0, 1.0) + 1.0) / 2.0


def to_model(key: str, x):
    """Map one schema key's linear values to the model's [-1, 1] space."""
    enc = SPECS[_base(key)].encoding
    return hdr_to_model(x) if enc == "hdr" else unit_to_model(x) if enc == "unit" else x


def from_model(key: str, y):
    """Inverse of `to_model`; normals are clamped to [-1, 1], not renormalised."""
    enc = SPECS[_base(key)].encoding
    return model_to_hdr(y) if enc == "hdr" else model_to_unit(y) if enc == "unit" else y.clip(-1.0, 1.0)


def _base(key: str) -> str:
    # Loader keys such as "image_a" or "ball_b" share the spec of their base map.
    return key if key in SPECS else key.rsplit("_", 1)[0]


# --- validation ---------------------------------------------------------------------------
def sample_key(scene: str, view: int, light: int) -> str:
    """The webdataset key; no dots allowed, since webdataset splits member names at the first one."""
    return f"{scene}_v{view:02d}_l{light:02d}"


def validate_sample(sample: Mapping[str, Any], where: str | Mapping[str, str | Path]) -> None:
    """Raise SampleError unless `sample` ({key: H x W x C array, "meta": dict}) fits the schema.

    `where` names the origin: one string (e.g. a shard member prefix) or {key: file path}.
    The message names the sample key, the map key and the file.
    """
    name = sample.get("__key__") or _meta_name(sample.get("meta"))

    def fail(key: str, problem: str) -> SampleError:
        file = where.get(key, "?") if isinstance(where, Mapping) else f"{where}:{key}"
        return SampleError(f"sample {name}: {key!r} ({file}): {problem}")

    missing = [k for k in (*REQUIRED_MAPS, "meta") if k not in sample]
    if missing:
        raise fail(missing[0], f"missing; a sample needs {[*REQUIRED_MAPS, 'meta']}")
    # The size most image-sized maps agree on, so the odd map out is the one named.
    sizes = [np.shape(sample[k])[:2] for k, sp in SPECS.items() if sp.image_sized and k in sample]
    hw = max(sizes, key=sizes.count)
    for key, spec in SPECS.items():
        if key not in sample:
            continue
        arr = np.asarray(sample[key])
        want = (*hw, spec.channels) if spec.image_sized else ("H", "W", spec.channels)
        if arr.ndim != 3 or arr.shape[2] != spec.channels or (spec.image_sized and arr.shape[:2] != hw):
            raise fail(key, f"shape {arr.shape}, want {want}")
        bad = ~np.isfinite(arr)
        if bad.any():
            y, x, _ = np.argwhere(bad)[0]
            kind = "NaN" if np.isnan(arr[y, x]).any() else "Inf"
            raise fail(key, f"{int(bad.sum())} non-finite value(s) (NaN/Inf), first {kind} at row {y}, col {x}")
        out = (arr < spec.lo) | (arr > spec.hi)
        if key == "mask":
            out |= (arr != 0) & (arr != 1)
        if out.any():
            raise fail(
                key,
                f"{int(out.sum())} value(s) outside [{spec.lo}, {spec.hi}]"
                f"{' (must be 0 or 1)' if key == 'mask' else ''}: min {arr.min():g}, max {arr.max():g}",
            )
        if key == "normal" and (np.linalg.norm(arr, axis=-1) > 1 + NORMAL_LENGTH_TOL).any():
            raise fail(key, f"normal longer than 1 + {NORMAL_LENGTH_TOL}")
    a, d, s, img = (np.asarray(sample[k], np.float32) for k in ("albedo", "diffuse", "specular", "image"))
    err = np.abs(img - (a * d + s)) - (IDENTITY_ATOL + IDENTITY_RTOL * np.abs(img))
    if (err > 0).any():
        raise fail("image", f"image != albedo * diffuse + specular (worst excess {err.max():g}); passes swapped?")
    _validate_meta(sample["meta"], fail)


def _validate_meta(meta: Any, fail) -> None:
    if not isinstance(meta, Mapping):
        raise fail("meta", f"must be a JSON object, got {type(meta).__name__}")
    missing = [k for k in META_KEYS if k not in meta]
    if missing:
        raise fail("meta", f"missing fields {missing}")
    if meta["split"] not in SPLITS:
        raise fail("meta", f"split {meta['split']!r} not in {SPLITS}")
    try:
        json.dumps(meta, allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise fail("meta", f"not JSON-serialisable ({exc})") from None


def _meta_name(meta: Any) -> str:
    try:
        return sample_key(meta["scene"], meta["view"], meta["light"])
    except Exception:
        return "<unknown>"


__all__ = [
    "SCHEMA_VERSION",
    "HDR_MAX",
    "SPLITS",
    "SPECS",
    "MapSpec",
    "REQUIRED_MAPS",
    "OPTIONAL_MAPS",
    "DataError",
    "SampleError",
    "unit_to_model",
    "model_to_unit",
    "to_model",
    "from_model",
    "sample_key",
    "validate_sample",
]
