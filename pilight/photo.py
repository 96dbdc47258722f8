"""Photos in and out of the model: reading, colour space, alpha, orientation, processing size.

The one place a user's picture becomes the pipeline's linear HDR image (and back into files):

* PNG / JPEG / TIFF (and anything else Pillow reads) are sRGB, 8- or 16-bit; they are decoded to
  linear with the sRGB curve. EXR and Radiance HDR are linear already and are read as they are.
* EXIF orientation is honoured (the picture is turned the way a viewer shows it).
* Grayscale is replicated to RGB; an alpha channel becomes the mask (1 where alpha >= 0.5, the
  project's mask is 0 or 1) and the colour is kept as stored (not premultiplied).
* ``probe`` reads the header only, so a huge image is refused before its pixels are allocated.
* Refused, naming the file (issue 36): an animation or a multi-page file (which frame?), an alpha
  channel below 0.5 everywhere (nothing marked to process). Said, as a ``PhotoWarning``: negative
  values of a linear file, set to 0 (light is never negative).

Pillow decodes 16-bit RGB PNG and TIFF to 8 bits, and Radiance HDR not at all, so those go through
OpenCV's decoders (the headless wheel; BGR order turned to RGB here); Pillow reads the rest and every
file's EXIF orientation. ``probe`` reads a Radiance header itself, as it reads no pixels.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

PHOTO_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".exr", ".hdr", ".webp", ".bmp")
LINEAR_SUFFIXES = (".exr", ".hdr")
MIN_SIDE = 8  # below this a photo has no structure to decompose; also the smallest processing size
EXIF_ORIENTATION = 0x0112


class PhotoError(ValueError):
    """A photo (or light file) cannot be read or used; the message names the file."""


class PhotoWarning(UserWarning):
    """A photo was read with a change the user should know of (negative linear values set to 0)."""


def _check_frames(im, path) -> None:
    frames = getattr(im, "n_frames", 1)
    if frames > 1:
        raise PhotoError(
            f"{path}: {frames} frames (an animation or a multi-page file); save the frame to process as a still image"
        )


@dataclass
class Photo:
    """A picture as the pipeline sees it: linear RGB (H, W, 3) float32 and an optional mask (H, W)."""

    rgb: np.ndarray
    mask: np.ndarray | None = None
    name: str = "<array>"

    @property
    def size(self) -> tuple[int, int]:
        return self.rgb.shape[0], self.rgb.shape[1]


# --- colour -------------------------------------------------------------------------------
def srgb_to_linear(y: np.ndarray) -> np.ndarray:
    """Stored sRGB values in [0, 1] -> linear float32 (clipped first: the curve's domain)."""
    from pilight.data.colour import srgb_to_linear as curve

    return curve(np.clip(np.asarray(y, dtype=np.float32), 0.0, 1.0)).astype(np.float32)


# --- headers --------------------------------------------------------------------------------
def probe(path: str | Path) -> tuple[int, int]:
    """(height, width) as displayed (EXIF orientation applied), from the header only."""
    path = Path(path)
    if not path.is_file():
        raise PhotoError(f"{path}: file not found")
    if path.stat().st_size == 0:
        raise PhotoError(f"{path}: empty file (0 bytes)")
    suffix = path.suffix.lower()
    try:
        if suffix == ".exr":
            import OpenEXR

            with OpenEXR.File(str(path), header_only=True) as f:
                lo, hi = f.header()["dataWindow"]
            return int(hi[1] - lo[1] + 1), int(hi[0] - lo[0] + 1)
        if suffix == ".hdr":
            with open(path, "rb") as f:
                return _hdr_header(f, path)[:2]

        with _open_pil(path) as im:
            _check_frames(im, path)
            w, h = im.size
            return (w, h) if _orientation(im, header_only=True) in (5, 6, 7, 8) else (h, w)
    except PhotoError:
        raise
    except Exception as exc:  # Pillow and OpenEXR raise many types for a bad file
        raise PhotoError(f"{path}: not a readable image ({type(exc).__name__}: {exc})") from None


def _open_pil(path: Path):
    from PIL import Image

    # The pipeline's own memory guard decides what is too large, with a flag to change it;
    # Pillow's decompression-bomb check would refuse large photos with a message that names neither.
    Image.MAX_IMAGE_PIXELS = None
    return Image.open(path)


def _orientation(im, header_only: bool = False) -> int:
    """EXIF orientation, 1 when absent. ``header_only``: never decode pixels to find it. Pillow's PNG
    reader loads the whole image to look for an eXIf chunk after the pixel data; for the 60000^2 header
    of a test that allocated the full buffer before the memory guard could refuse it (CI was OOM-killed).
    An eXIf chunk after the pixels is rare, and the pixel count the guard checks does not depend on it."""
    if header_only and im.format == "PNG" and "exif" not in im.info:
        return 1
    try:
        return int(im.getexif().get(EXIF_ORIENTATION, 1))
    except Exception:
        return 1  # a broken EXIF block does not make the picture unreadable


def orient(a: np.ndarray, orientation: int) -> np.ndarray:
    """Turn a stored (H, W, C) array the way EXIF ``orientation`` (1..8) says a viewer shows it."""
    ops = {
        1: lambda x: x,
        2: lambda x: x[:, ::-1],
        3: lambda x: x[::-1, ::-1],
        4: lambda x: x[::-1],
        5: lambda x: x.transpose(1, 0, 2),
        6: lambda x: np.rot90(x, -1),
        7: lambda x: x[::-1, ::-1].transpose(1, 0, 2),
        8: lambda x: np.rot90(x, 1),
    }
    return np.ascontiguousarray(ops.get(orientation, ops[1])(a))


# --- reading ----------------------------------------------------------------------------------
def read_photo(path: str | Path) -> Photo:
    """Any supported file -> Photo (linear RGB + mask from alpha). PhotoError naming the file otherwise."""
    path = Path(path)
    probe(path)  # the clear messages for missing, empty and unreadable files
    suffix = path.suffix.lower()
    try:
        if suffix == ".exr":
            from pilight.data.exr import read_exr

            a = read_exr(path)
            return _from_channels(a, linear=True, name=str(path))
        if suffix == ".hdr":
            return _from_channels(read_hdr(path), linear=True, name=str(path))
        return _read_pil(path)
    except PhotoError:
        raise
    except Exception as exc:
        raise PhotoError(f"{path}: not a readable image ({type(exc).__name__}: {exc})") from None


def _read_pil(path: Path) -> Photo:
    with _open_pil(path) as im:
        _check_frames(im, path)
        orientation = _orientation(im)
        a = _opencv_array(path) if _sixteen_bit(im) else _pil_array(im, path)
    a = orient(a, orientation)
    if a.dtype == np.float32:  # float TIFF ('F'): linear values, as EXR
        return _from_channels(a, linear=True, name=str(path))
    scale = 65535.0 if a.dtype == np.uint16 else 255.0
    return _from_channels(a.astype(np.float32) / scale, linear=False, name=str(path))


def _pil_array(im, path: Path) -> np.ndarray:
    """Pillow image -> (H, W, C) uint8 / uint16 / float32 array with C in 1..4."""
    mode = im.mode
    if mode in ("I;16", "I;16L", "I;16B", "I;16N"):
        return np.asarray(im).astype(np.uint16)[..., None]
    if mode == "I":  # 32-bit integer: Pillow's mode for 16-bit grayscale PNG on some versions
        return np.clip(np.asarray(im), 0, 65535).astype(np.uint16)[..., None]
    if mode == "F":
        return np.asarray(im, dtype=np.float32)[..., None]
    if mode in ("L", "LA", "RGB", "RGBA"):
        return np.asarray(im)
    if mode == "P" and "transparency" in im.info:
        return np.asarray(im.convert("RGBA"))
    if mode in ("PA", "RGBa", "La"):
        return np.asarray(im.convert("RGBA"))
    return np.asarray(im.convert("RGB"))  # P, 1, CMYK, YCbCr, LAB, HSV


def _from_channels(a: np.ndarray, *, linear: bool, name: str) -> Photo:
    a = np.asarray(a, dtype=np.float32)
    if a.ndim == 2:
        a = a[..., None]
    c = a.shape[2]
    if c not in (1, 2, 3, 4):
        raise PhotoError(f"{name}: {c} channels; want gray, gray+alpha, RGB or RGBA")
    bad = ~np.isfinite(a)
    if bad.any():
        raise PhotoError(f"{name}: {int(bad.sum())} non-finite value(s) (NaN/Inf)")
    colour, alpha = (a[..., :1], a[..., 1]) if c == 2 else (a[..., :3], a[..., 3]) if c == 4 else (a, None)
    if colour.shape[2] == 1:
        colour = np.repeat(colour, 3, axis=2)
    if linear and (negative := int((colour < 0).sum())):
        warnings.warn(
            f"{name}: {negative} negative value(s), down to {float(colour.min()):.4g}, set to 0 (light is never negative)",
            PhotoWarning,
            stacklevel=3,
        )
    rgb = np.clip(colour, 0.0, None) if linear else srgb_to_linear(colour)
    mask = None if alpha is None else (alpha >= 0.5).astype(np.float32)
    if mask is not None and not mask.any():
        raise PhotoError(
            f"{name}: its alpha channel is below 0.5 everywhere, so no pixel is marked to process; "
            "remove the alpha channel to use the whole picture"
        )
    return Photo(np.ascontiguousarray(rgb, dtype=np.float32), mask, name)


def as_photo(image, name: str = "<array>") -> Photo:
    """What the Python API accepts -> Photo.

    * a path (str / Path): read with ``read_photo``;
    * a PIL image: sRGB (mode 'F': linear);
    * a numpy array (H, W[, C]): uint8 / uint16 are sRGB, floats are LINEAR (as read from an EXR);
    * a torch tensor: (C, H, W) or (H, W, C), the same dtype rules as numpy;
    * a Photo: as is.
    C may be 1 (gray), 2 (gray + alpha), 3 (RGB) or 4 (RGBA).
    """
    if isinstance(image, Photo):
        return image
    if isinstance(image, (str, Path)):
        return read_photo(image)
    try:
        from PIL import Image

        if isinstance(image, Image.Image):
            _check_frames(image, name)
            a = _pil_array(image, Path(name))
            if a.dtype == np.float32:
                return _from_channels(a, linear=True, name=name)
            return _from_channels(
                a.astype(np.float32) / (65535.0 if a.dtype == np.uint16 else 255.0), linear=False, name=name
            )
    except ImportError:
        pass
    try:
        import torch

        if isinstance(image, torch.Tensor):
            t = image.detach().cpu()
            if t.ndim == 4 and t.shape[0] == 1:
                t = t[0]
            # (C, H, W) is torch's layout; (H, W, C) is accepted when the last axis is clearly channels.
            if t.ndim == 3 and t.shape[0] in (1, 2, 3, 4) and t.shape[2] not in (1, 2, 3, 4):
                t = t.permute(1, 2, 0)
            elif t.ndim == 3 and t.shape[0] in (1, 2, 3, 4) and t.shape[2] in (1, 2, 3, 4) and t.shape[0] <= t.shape[2]:
                t = t.permute(1, 2, 0)
            image = t.numpy()
    except ImportError:
        pass
    a = np.asarray(image)
    if a.ndim not in (2, 3):
        raise PhotoError(f"{name}: array of shape {a.shape}; want (H, W), (H, W, C) or a (C, H, W) tensor")
    if a.dtype == np.uint8:
        return _from_channels(a.astype(np.float32) / 255.0, linear=False, name=name)
    if a.dtype == np.uint16:
        return _from_channels(a.astype(np.float32) / 65535.0, linear=False, name=name)
    if np.issubdtype(a.dtype, np.floating):
        return _from_channels(a, linear=True, name=name)
    raise PhotoError(f"{name}: array dtype {a.dtype}; want uint8 / uint16 (sRGB) or float (linear)")


# --- 16-bit PNG and TIFF, Radiance HDR: OpenCV ----------------------------------------------------
def _sixteen_bit(im) -> bool:
    """A PNG or TIFF stored at 16 bits per channel (Pillow would give 8 bits of its RGB)."""
    if im.format == "PNG":
        with open(im.filename, "rb") as f:
            return f.read(25)[24:25] == b"\x10"  # IHDR's bit depth, right after the signature and width/height
    if im.format == "TIFF":
        bits = im.tag_v2.get(258, (8,))  # BitsPerSample
        return 16 in (bits if isinstance(bits, tuple) else (bits,))
    return False


def _opencv_array(path: Path) -> np.ndarray:
    """A file OpenCV decodes as stored (16-bit integers, Radiance floats) -> (H, W, C) in RGB(A) order."""
    import cv2

    a = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)  # as stored: no EXIF turn, no 8-bit conversion
    if a is None:
        raise PhotoError(f"{path}: OpenCV cannot decode it (a truncated or unsupported file)")
    if a.ndim == 2:
        return a[..., None]
    return np.ascontiguousarray(a[..., [2, 1, 0, 3][: a.shape[2]]] if a.shape[2] in (3, 4) else a)


# --- Radiance HDR ---------------------------------------------------------------------------------
def _hdr_header(f, path: Path) -> tuple[int, int, bool]:
    """(height, width, flip_x) from a Radiance header; the file position is left at the pixels."""
    first = f.readline()
    if not first.startswith(b"#?"):
        raise PhotoError(f"{path}: not a Radiance HDR file (no '#?' signature)")
    fmt = None
    while True:
        line = f.readline()
        if not line:
            raise PhotoError(f"{path}: truncated Radiance header")
        line = line.strip()
        if not line:
            break
        if line.startswith(b"FORMAT="):
            fmt = line[7:]
    if fmt not in (None, b"32-bit_rle_rgbe"):
        raise PhotoError(f"{path}: Radiance format {fmt.decode(errors='replace')}; only 32-bit_rle_rgbe is read")
    res = f.readline().split()
    if len(res) != 4 or res[0] != b"-Y" or res[2] not in (b"+X", b"-X"):
        raise PhotoError(
            f"{path}: Radiance resolution line {b' '.join(res).decode(errors='replace')!r}; "
            "only the standard '-Y H +X W' is read"
        )
    return int(res[1]), int(res[3]), res[2] == b"-X"


def read_hdr(path: str | Path) -> np.ndarray:
    """Radiance RGBE (.hdr) -> (H, W, 3) float32 linear radiance (the header checked first)."""
    path = Path(path)
    with open(path, "rb") as f:
        _hdr_header(f, path)
    return _opencv_array(path).astype(np.float32)


# --- sizes ----------------------------------------------------------------------------------------
def processing_size(h: int, w: int, resolution: int, multiple: int) -> tuple[int, int]:
    """The size the model runs at: longer side ``resolution`` (0 = the photo's own), the shorter
    side in proportion, both rounded to a multiple of ``multiple`` (codec factor x UNet downsampling)."""
    if resolution < 0:
        raise ValueError(f"resolution must be >= 0, got {resolution}")
    scale = 1.0 if resolution == 0 else resolution / max(h, w)
    snap = lambda v: max(multiple, int(v * scale / multiple + 0.5) * multiple)  # half up, not to even
    return snap(h), snap(w)


def check_size(h: int, w: int, name: str) -> None:
    if min(h, w) < MIN_SIDE:
        raise PhotoError(f"{name}: {w}x{h} pixels is too small to process; each side needs at least {MIN_SIDE} pixels")


def lcm(*values: int) -> int:
    out = 1
    for v in values:
        out = out * v // math.gcd(out, v)
    return out
