"""Reading photos: sRGB 8/16-bit, EXIF orientation, alpha, gray, EXR/HDR linear, sizes."""

from __future__ import annotations

import struct
import zlib

import numpy as np
import pytest
from PIL import Image, ImageOps

from pilight.photo import PhotoError, as_photo, check_size, probe, processing_size, read_hdr, read_photo, srgb_to_linear


def png16(path, a: np.ndarray) -> None:
    """A 16-bit PNG (gray, gray+alpha, RGB or RGBA) with every row filter type in turn (0..4)."""
    h, w, c = a.shape
    raw = a.astype(">u2").view(np.uint8).reshape(h, w * c * 2).astype(np.int64)
    bpp = c * 2
    rows = []
    for y in range(h):
        f = y % 5
        cur, up = raw[y], raw[y - 1] if y else np.zeros_like(raw[0])
        left = np.concatenate([np.zeros(bpp, np.int64), cur[:-bpp]])
        upleft = np.concatenate([np.zeros(bpp, np.int64), up[:-bpp]])
        if f == 0:
            pred = 0
        elif f == 1:
            pred = left
        elif f == 2:
            pred = up
        elif f == 3:
            pred = (left + up) // 2
        else:
            p = left + up - upleft
            pa, pb, pc = abs(p - left), abs(p - up), abs(p - upleft)
            pred = np.where((pa <= pb) & (pa <= pc), left, np.where(pb <= pc, up, upleft))
        rows.append(bytes([f]) + ((cur - pred) % 256).astype(np.uint8).tobytes())
    ctype = {1: 0, 2: 4, 3: 2, 4: 6}[c]

    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body) & 0xFFFFFFFF)

    path.write_bytes(
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 16, ctype, 0, 0, 0))
        + chunk(b"IDAT", zlib.compress(b"".join(rows)))
        + chunk(b"IEND", b"")
    )


@pytest.mark.parametrize("channels", [1, 3, 4])
def test_16bit_png_keeps_16_bits(tmp_path, channels):
    rng = np.random.default_rng(channels)
    a = rng.integers(0, 65536, (11, 13, channels)).astype(np.uint16)
    png16(tmp_path / "x.png", a)
    photo = read_photo(tmp_path / "x.png")
    colour = a[..., :3] if channels >= 3 else np.repeat(a[..., :1], 3, axis=2)
    np.testing.assert_allclose(photo.rgb, srgb_to_linear(colour / 65535.0), rtol=1e-6, atol=1e-7)
    if channels == 4:
        np.testing.assert_array_equal(photo.mask, (a[..., 3] / 65535.0 >= 0.5).astype(np.float32))
    else:
        assert photo.mask is None


@pytest.mark.parametrize("compression, channels", [(None, 3), ("zlib", 3), ("zlib", 4)])
def test_16bit_tiff_keeps_16_bits(tmp_path, compression, channels):
    tifffile = pytest.importorskip("tifffile")  # installed with scikit-image (the test extra)
    a = np.random.default_rng(0).integers(0, 65536, (9, 7, channels)).astype(np.uint16)
    extra = {"extrasamples": ["unassalpha"]} if channels == 4 else {}
    tifffile.imwrite(tmp_path / "x.tif", a, photometric="rgb", compression=compression, **extra)
    photo = read_photo(tmp_path / "x.tif")
    np.testing.assert_allclose(photo.rgb, srgb_to_linear(a[..., :3] / 65535.0), rtol=1e-6, atol=1e-7)
    if channels == 4:
        np.testing.assert_array_equal(photo.mask, (a[..., 3] / 65535.0 >= 0.5).astype(np.float32))


def test_exif_orientation_is_honoured(tmp_path, astronaut):
    img = Image.fromarray(astronaut[:64, :96])
    exif = Image.Exif()
    exif[0x0112] = 6  # stored sideways: a viewer turns it 90 degrees clockwise
    img.save(tmp_path / "rot.jpg", exif=exif.tobytes(), quality=95)
    assert probe(tmp_path / "rot.jpg") == (96, 64)
    shown = np.asarray(ImageOps.exif_transpose(Image.open(tmp_path / "rot.jpg")))
    photo = read_photo(tmp_path / "rot.jpg")
    np.testing.assert_allclose(photo.rgb, srgb_to_linear(shown / 255.0), atol=1e-6)


def test_probe_reads_a_png_header_without_decoding_its_pixels(tmp_path, astronaut, monkeypatch):
    """Pillow's PNG reader decodes the whole image to look for EXIF after the pixels; the probe must not
    (a 60000^2 header once allocated its full buffer in CI before the memory guard refused it)."""
    from PIL import ImageFile

    plain = tmp_path / "plain.png"
    Image.fromarray(astronaut[:64, :96]).save(plain)
    turned = tmp_path / "turned.png"
    exif = Image.Exif()
    exif[0x0112] = 6
    Image.fromarray(astronaut[:64, :96]).save(turned, exif=exif.tobytes())  # Pillow writes eXIf before IDAT
    decoded = []
    real_load = ImageFile.ImageFile.load
    monkeypatch.setattr(ImageFile.ImageFile, "load", lambda self: decoded.append(self.filename) or real_load(self))
    assert probe(plain) == (64, 96)
    assert probe(turned) == (96, 64)  # its orientation is still read, from the header
    assert decoded == []


def test_alpha_becomes_the_mask_and_gray_becomes_rgb(tmp_path):
    rgba = np.zeros((8, 10, 4), np.uint8)
    rgba[..., :3] = 200
    rgba[:, 5:, 3] = 255
    Image.fromarray(rgba).save(tmp_path / "a.png")
    photo = read_photo(tmp_path / "a.png")
    np.testing.assert_array_equal(photo.mask, (np.arange(10) >= 5)[None].repeat(8, 0).astype(np.float32))
    Image.fromarray(np.full((8, 10), 128, np.uint8)).save(tmp_path / "g.png")
    g = read_photo(tmp_path / "g.png")
    assert g.rgb.shape == (8, 10, 3) and np.ptp(g.rgb) == 0 and g.mask is None


def test_exr_is_linear_and_hdr_is_read(tmp_path):
    from pilight.data.exr import write_exr

    a = np.random.default_rng(1).uniform(0, 8, (6, 12, 3)).astype(np.float32)
    write_exr(tmp_path / "x.exr", a, half=False)
    np.testing.assert_array_equal(read_photo(tmp_path / "x.exr").rgb, a)
    # Radiance RGBE (OpenCV decodes it), flat and run-length encoded scanlines, channels told apart:
    # 128/256 * 2^(129-128) = 1.0, 64 -> 0.5, 32 -> 0.25
    w, rgb = 12, np.array([1.0, 0.5, 0.25], np.float32)
    header = b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 2 +X 12\n"
    (tmp_path / "flat.hdr").write_bytes(header + bytes([128, 64, 32, 129]) * (2 * w))
    rle_row = b"\x02\x02\x00\x0c" + b"".join(bytes([128 + w, v]) for v in (128, 64, 32, 129))
    (tmp_path / "x.hdr").write_bytes(header + rle_row * 2)
    for name in ("flat.hdr", "x.hdr"):
        np.testing.assert_allclose(read_hdr(tmp_path / name), np.broadcast_to(rgb, (2, w, 3)), rtol=0)
        np.testing.assert_allclose(read_photo(tmp_path / name).rgb, np.broadcast_to(rgb, (2, w, 3)), rtol=0)
    (tmp_path / "cut.hdr").write_bytes(header + rle_row)  # one row of two
    with pytest.raises(PhotoError, match="cut.hdr: OpenCV cannot decode it"):
        read_photo(tmp_path / "cut.hdr")
    assert probe(tmp_path / "x.hdr") == (2, 12)


def test_api_accepts_pil_numpy_and_tensors(astronaut):
    import torch

    ref = as_photo(astronaut)
    np.testing.assert_array_equal(as_photo(Image.fromarray(astronaut)).rgb, ref.rgb)
    np.testing.assert_array_equal(as_photo(torch.from_numpy(astronaut).permute(2, 0, 1)).rgb, ref.rgb)
    lin = torch.from_numpy(ref.rgb).permute(2, 0, 1)  # float tensors are linear, (C, H, W)
    np.testing.assert_array_equal(as_photo(lin).rgb, ref.rgb)
    with pytest.raises(PhotoError, match="dtype"):
        as_photo(np.zeros((8, 8, 3), np.int8))


def test_processing_size_keeps_aspect_on_the_multiple():
    assert processing_size(512, 512, 128, 16) == (128, 128)
    assert processing_size(3000, 4000, 512, 16) == (384, 512)
    assert processing_size(100, 1000, 128, 16) == (16, 128)  # never below one multiple
    assert processing_size(100, 200, 0, 16) == (96, 208)  # 0 = the photo's own size, snapped
    with pytest.raises(PhotoError, match="too small"):
        check_size(1, 1, "x.png")
