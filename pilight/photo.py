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

Pillow decodes 16-bit RGB PNG and TIFF to 8 bits. A non-interlaced 16-bit PNG is therefore decoded
here (zlib and PNG's row filters in numpy), and so is an uncompressed 16-bit TIFF; other 16-bit
RGB files fall back to Pillow's 8 bits with a warning that says so.
"""

from __future__ import annotations

import math
import struct
import warnings
import zlib
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


def linear_to_srgb8(x: np.ndarray, alpha: np.ndarray | None = None) -> np.ndarray:
    """Linear values (clipped at 1) -> sRGB uint8 (H, W, 3), or (H, W, 4) with ``alpha`` (H, W) in [0, 1]."""
    from pilight.data.colour import srgb_preview

    x = np.asarray(x, dtype=np.float32)
    if x.ndim == 2:
        x = x[..., None]
    if x.shape[2] == 1:
        x = np.repeat(x, 3, axis=2)
    out = srgb_preview(x)
    if alpha is not None:
        out = np.concatenate([out, np.round(np.clip(alpha, 0, 1) * 255)[..., None].astype(np.uint8)], axis=2)
    return out


def normal_preview(n: np.ndarray, alpha: np.ndarray | None = None) -> np.ndarray:
    """Unit normals (H, W, 3) -> the usual RGB picture (n + 1) / 2, stored as is (not sRGB-encoded)."""
    u8 = np.round(np.clip((np.asarray(n, np.float32) + 1) / 2, 0, 1) * 255).astype(np.uint8)
    if alpha is not None:
        u8 = np.concatenate([u8, np.round(np.clip(alpha, 0, 1) * 255)[..., None].astype(np.uint8)], axis=2)
    return u8


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
            return (w, h) if _orientation(im) in (5, 6, 7, 8) else (h, w)
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


def _orientation(im) -> int:
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
            return Photo(read_hdr(path), None, str(path))
        return _read_pil(path)
    except PhotoError:
        raise
    except Exception as exc:
        raise PhotoError(f"{path}: not a readable image ({type(exc).__name__}: {exc})") from None


def _read_pil(path: Path) -> Photo:
    with _open_pil(path) as im:
        _check_frames(im, path)
        orientation = _orientation(im)
        a = None
        if im.format == "PNG":
            a = _png16(path)
        elif im.format == "TIFF":
            a = _tiff16_raw(im, path)
        if a is None:
            a = _pil_array(im, path)
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


# --- 16-bit PNG and TIFF ------------------------------------------------------------------------
_PNG_SIG = b"\x89PNG\r\n\x1a\n"
_PNG_CHANNELS = {0: 1, 2: 3, 4: 2, 6: 4}  # colour type -> channels


def _png16(path: Path) -> np.ndarray | None:
    """A 16-bit non-interlaced PNG -> (H, W, C) uint16; None for any other PNG (Pillow reads those)."""
    data = path.read_bytes()
    if not data.startswith(_PNG_SIG):
        return None
    pos, idat, ihdr = 8, [], None
    while pos + 8 <= len(data):
        length, kind = struct.unpack(">I4s", data[pos : pos + 8])
        body = data[pos + 8 : pos + 8 + length]
        if kind == b"IHDR":
            ihdr = struct.unpack(">IIBBBBB", body)
            if ihdr[2] != 16 or ihdr[3] not in _PNG_CHANNELS:
                return None
            if ihdr[6] != 0:
                warnings.warn(
                    f"{path}: interlaced 16-bit PNG is read at 8 bits per channel (Pillow); "
                    "save it without interlacing to keep 16 bits",
                    stacklevel=3,
                )
                return None
        elif kind == b"IDAT":
            idat.append(body)
        elif kind == b"IEND":
            break
        pos += 12 + length
    if ihdr is None or not idat:
        raise PhotoError(f"{path}: PNG without IHDR or image data")
    w, h, _, ctype = ihdr[:4]
    c = _PNG_CHANNELS[ctype]
    try:
        raw = zlib.decompress(b"".join(idat))
    except zlib.error as exc:
        raise PhotoError(f"{path}: corrupt PNG image data ({exc})") from None
    stride = w * c * 2
    if len(raw) < h * (stride + 1):
        raise PhotoError(f"{path}: truncated PNG image data ({len(raw)} of {h * (stride + 1)} bytes)")
    rows = np.frombuffer(raw, np.uint8, h * (stride + 1)).reshape(h, stride + 1)
    out = _png_unfilter(rows[:, 0], rows[:, 1:], bpp=c * 2, path=path)
    return out.view(">u2").reshape(h, w, c).astype(np.uint16)


def _png_unfilter(ftype: np.ndarray, rows: np.ndarray, bpp: int, path: Path) -> np.ndarray:
    """PNG's per-row filters undone. None, Sub and Up are vectorised; Average and Paeth depend on
    the byte to their left, so they run per pixel (a few seconds for a 12-megapixel Paeth image)."""
    h, stride = rows.shape
    out = np.zeros((h, stride), np.uint8)
    prev = np.zeros(stride, np.int64)
    for y in range(h):
        f, cur = int(ftype[y]), rows[y].astype(np.int64)
        if f == 0:
            r = cur
        elif f == 1:
            r = np.cumsum(cur.reshape(-1, bpp), axis=0).reshape(-1) % 256
        elif f == 2:
            r = (cur + prev) % 256
        elif f in (3, 4):
            r = _png_sequential(f, cur.tolist(), prev.tolist(), bpp)
        else:
            raise PhotoError(f"{path}: corrupt PNG (row {y} has filter type {f})")
        out[y] = r
        prev = np.asarray(r, np.int64)
    return out


def _png_sequential(f: int, cur: list[int], up: list[int], bpp: int) -> np.ndarray:
    r = [0] * len(cur)
    for i, x in enumerate(cur):
        a = r[i - bpp] if i >= bpp else 0
        b = up[i]
        if f == 3:
            r[i] = (x + ((a + b) >> 1)) & 255
        else:
            c = up[i - bpp] if i >= bpp else 0
            p = a + b - c
            pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
            r[i] = (x + (a if pa <= pb and pa <= pc else b if pb <= pc else c)) & 255
    return np.asarray(r, np.int64)


def _tiff16_raw(im, path: Path) -> np.ndarray | None:
    """An uncompressed 16-bit RGB(A) TIFF -> (H, W, C) uint16, from the strips Pillow located.
    None when Pillow reads the file at full depth itself; a warning when it can only read 8 bits."""
    if im.mode not in ("RGB", "RGBA") or not im.tile:
        return None
    args = im.tile[0][3]
    rawmode = args[0] if isinstance(args, tuple) and args else args
    if ";16" not in str(rawmode):
        return None
    codec = im.tile[0][0]
    c = 4 if str(rawmode).startswith("RGBA") else 3
    if codec != "raw" or any(t[0] != "raw" for t in im.tile):
        warnings.warn(
            f"{path}: compressed 16-bit TIFF is read at 8 bits per channel (Pillow); save it "
            "uncompressed or as a 16-bit PNG to keep 16 bits",
            stacklevel=3,
        )
        return None
    dtype = ">u2" if str(rawmode).endswith("B") else "<u2"
    w, h = im.size
    out = np.zeros((h, w, c), np.uint16)
    with open(path, "rb") as f:
        for t in im.tile:
            x0, y0, x1, y1 = t[1]
            f.seek(t[2])
            n = (x1 - x0) * (y1 - y0) * c
            buf = np.frombuffer(f.read(n * 2), dtype)
            if buf.size != n:
                raise PhotoError(f"{path}: truncated TIFF strip at byte {t[2]}")
            out[y0:y1, x0:x1] = buf.reshape(y1 - y0, x1 - x0, c)
    return out


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
    """Radiance RGBE (.hdr) -> (H, W, 3) float32 linear radiance."""
    path = Path(path)
    with open(path, "rb") as f:
        h, w, flip = _hdr_header(f, path)
        data = f.read()
    rgbe = np.zeros((h, w, 4), np.uint8)
    pos = 0
    for y in range(h):
        if 8 <= w < 32768 and data[pos : pos + 2] == b"\x02\x02" and (data[pos + 2] << 8 | data[pos + 3]) == w:
            pos += 4
            for ch in range(4):  # new-style RLE: each channel of the scanline on its own
                x = 0
                while x < w:
                    if pos >= len(data):
                        raise PhotoError(f"{path}: truncated Radiance pixel data at row {y}")
                    n = data[pos]
                    pos += 1
                    if n > 128:
                        n -= 128
                        rgbe[y, x : x + n, ch] = data[pos]
                        pos += 1
                    else:
                        rgbe[y, x : x + n, ch] = np.frombuffer(data, np.uint8, n, pos)
                        pos += n
                    x += n
        else:  # flat scanline
            n = w * 4
            if pos + n > len(data):
                raise PhotoError(f"{path}: truncated Radiance pixel data at row {y}")
            rgbe[y] = np.frombuffer(data, np.uint8, n, pos).reshape(w, 4)
            pos += n
    e = rgbe[..., 3].astype(np.int32)
    scale = np.where(e > 0, np.ldexp(1.0, e - 136), 0.0).astype(np.float32)  # 2^(e - 128) / 256
    out = rgbe[..., :3].astype(np.float32) * scale[..., None]
    return np.ascontiguousarray(out[:, ::-1] if flip else out)


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
