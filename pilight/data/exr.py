"""EXR I/O through the OpenEXR package: the one place the project reads or writes EXR.

Arrays are H x W x C float32 in memory, row 0 = top of the image. On disk:
- 1 channel -> "Y", 3 channels -> "R", "G", "B" (normals too: R=x, G=y, B=z);
- `half=True` stores float16 (enough for maps used as network inputs), `half=False` float32
  (needed where an identity must hold to float precision, e.g. image = A * D + S).
Writes are atomic (temporary file, then rename) and byte-deterministic: the header carries
no date, time or host, so the same array always gives the same bytes.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np
import OpenEXR

from pilight import atomic

_CHANNELS = {1: ("Y",), 3: ("R", "G", "B"), 4: ("R", "G", "B", "A")}
# Blender names its pass channels with these suffixes; the order we want them in.
_SUFFIX_ORDER = "RGBAXYZV"


class ExrError(ValueError):
    """An EXR file is missing, unreadable, truncated or has unexpected channels."""


def write_exr(path: str | os.PathLike, array: np.ndarray, *, half: bool) -> None:
    """Write an H x W x C (C in 1, 3, 4) or H x W array atomically to `path`."""
    path = Path(path)
    arr = np.asarray(array)
    if arr.ndim == 2:
        arr = arr[..., None]
    if arr.ndim != 3 or arr.shape[2] not in _CHANNELS:
        raise ExrError(f"{path}: cannot write array of shape {arr.shape}; want HxW or HxWx{{1,3,4}}")
    if not np.all(np.isfinite(arr)):
        raise ExrError(f"{path}: refusing to write non-finite values (NaN/Inf)")
    dtype = np.float16 if half else np.float32
    channels = {name: np.ascontiguousarray(arr[..., i].astype(dtype)) for i, name in enumerate(_CHANNELS[arr.shape[2]])}
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}

    def write(tmp: str) -> None:
        try:
            with OpenEXR.File(header, channels) as f:
                f.write(tmp)
        except OSError:
            raise
        except Exception as exc:  # OpenEXR raises a bare Exception (a full disk among others) naming the temporary
            raise ExrError(f"{path}: cannot write EXR ({str(exc).replace(tmp, str(path))})") from exc

    atomic.write_with(path, write)


def read_exr(path: str | os.PathLike) -> np.ndarray:
    """Read a single-part EXR written by `write_exr` into H x W x C float32."""
    path = Path(path)
    if not path.is_file():
        raise ExrError(f"{path}: file not found")
    try:
        with OpenEXR.File(str(path), separate_channels=True) as f:
            chans = {name: ch.pixels for name, ch in f.channels().items()}
    except Exception as exc:  # OpenEXR raises a bare Exception on corrupt/truncated data
        raise ExrError(f"{path}: unreadable EXR ({exc})") from exc
    for names in _CHANNELS.values():
        if set(chans) == set(names):
            return np.stack([chans[n].astype(np.float32) for n in names], axis=-1)
    raise ExrError(f"{path}: unexpected channels {sorted(chans)}; want one of {list(_CHANNELS.values())}")


def read_exr_bytes(data: bytes, name: str = "<bytes>") -> np.ndarray:
    """Decode EXR bytes (a webdataset payload) the same way as `read_exr`."""
    fd, tmp = tempfile.mkstemp(suffix=".exr")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        try:
            return read_exr(tmp)
        except ExrError as exc:
            raise ExrError(str(exc).replace(tmp, name)) from exc
    finally:
        os.unlink(tmp)


def read_render_passes(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Read Blender's multi-part multilayer EXR into {pass name: H x W x C float32}.

    Blender 5.0 writes one part per pass, named "<ViewLayer>.<Pass>", with channels
    "<ViewLayer>.<Pass>.<R|G|B|A|X|Y|Z>". Alpha is dropped from colour passes.
    """
    path = Path(path)
    try:
        f = OpenEXR.File(str(path), separate_channels=True)
    except Exception as exc:
        raise ExrError(f"{path}: unreadable render EXR ({exc})") from exc
    passes: dict[str, np.ndarray] = {}
    for part in f.parts:
        by_suffix = {key.rsplit(".", 1)[1]: ch.pixels for key, ch in part.channels.items()}
        order = sorted(by_suffix, key=_SUFFIX_ORDER.index)
        if len(order) == 4 and "A" in order:
            order.remove("A")
        name = part.name().split(".", 1)[1]
        passes[name] = np.stack([by_suffix[k].astype(np.float32) for k in order], axis=-1)
    return passes
