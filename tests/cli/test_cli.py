"""`pilight decompose | relight | ball` as a user runs them, on a real photo with a tiny model."""

from __future__ import annotations

import struct
import time
import zlib

import numpy as np
import pytest
from PIL import Image

from pilight.cli import main
from pilight.data.exr import read_exr
from pilight.data.schema import NORMAL_LENGTH_TOL
from pilight.params import DOMAINS

FAST = ["--resolution", "32", "--device", "cpu"]  # tiny model at 32^2: milliseconds per sample


def run(capsys, *argv):
    rc = main([str(a) for a in argv])
    err = capsys.readouterr().err
    return rc, err


def final_files(folder):
    """Everything under a final (non-temporary) name."""
    return sorted(p for p in folder.rglob("*") if p.is_file() and not p.name.startswith("."))


def test_decompose_writes_every_map_at_the_input_size_with_unit_normals(tmp_path, capsys, tiny_models, astronaut_png):
    out = tmp_path / "out"
    rc, err = run(capsys, "decompose", astronaut_png, "-o", out, "--models", tiny_models, *FAST)
    assert rc == 0, err
    folder = out / "astronaut"
    for m in DOMAINS:
        exr = read_exr(folder / f"{m}.exr")
        assert exr.shape[:2] == (512, 512), m
        assert exr.shape[2] == (3 if m in ("albedo", "normal") else 1)
        assert np.asarray(Image.open(folder / f"{m}.png")).shape[:2] == (512, 512)
    n = read_exr(folder / "normal.exr")
    assert np.abs(np.linalg.norm(n, axis=-1) - 1).max() < NORMAL_LENGTH_TOL


def test_relight_several_lights_one_output_each_and_rerun_skips(tmp_path, capsys, tiny_models, astronaut_png):
    out = tmp_path / "out"
    argv = [
        "relight",
        astronaut_png,
        "-o",
        out,
        "--models",
        tiny_models,
        "--light",
        "left",
        "--light",
        "right",
        "--azimuth",
        "30",
        "--elevation",
        "45",
        *FAST,
    ]
    rc, err = run(capsys, *argv)
    assert rc == 0, err
    for light in ("left", "right", "az30_el45"):
        folder = out / "astronaut" / light
        for b in ("relit", "diffuse", "specular"):
            assert read_exr(folder / f"{b}.exr").shape == (512, 512, 3)
            assert np.asarray(Image.open(folder / f"{b}.png")).shape == (512, 512, 3)
        sheet = np.asarray(Image.open(folder / "contact.png"))
        assert sheet.shape[0] == 512 and sheet.shape[1] == 512 + 4 + 512 + 4 + 512  # input | ball | relit
        assert read_exr(folder / "ball.exr").shape == (32, 32, 3)  # what the model was given
    before = {p: p.stat().st_mtime_ns for p in final_files(out)}
    rc, err = run(capsys, *argv)
    assert rc == 0 and "already complete" in err and "skipped" in err
    assert {p: p.stat().st_mtime_ns for p in final_files(out)} == before


def test_folder_and_glob_inputs(tmp_path, capsys, tiny_models, astronaut):
    photos = tmp_path / "photos"
    photos.mkdir()
    Image.fromarray(astronaut[::8, ::8]).save(photos / "a.png")
    Image.fromarray(astronaut[::4, ::8]).save(photos / "b.jpg")
    rc, err = run(capsys, "decompose", photos, "-o", tmp_path / "o1", "--models", tiny_models, *FAST)
    assert rc == 0, err
    assert (tmp_path / "o1" / "a" / "albedo.exr").is_file() and (tmp_path / "o1" / "b" / "albedo.exr").is_file()
    assert read_exr(tmp_path / "o1" / "b" / "albedo.exr").shape[:2] == (128, 64)  # non-square: back at its own size
    rc, err = run(capsys, "decompose", str(photos / "*.png"), "-o", tmp_path / "o2", "--models", tiny_models, *FAST)
    assert rc == 0, err
    assert sorted(p.name for p in (tmp_path / "o2").iterdir()) == ["a"]


def test_ball_command_writes_the_light_ball(tmp_path, capsys):
    rc, _ = run(capsys, "ball", "-o", tmp_path, "--light", "left", "--size", "64")
    assert rc == 0
    ball = read_exr(tmp_path / "left.exr")
    assert ball.shape == (64, 64, 3)
    assert ball[:, :32].mean() > 2 * ball[:, 32:].mean()  # lit from the picture's left


def test_missing_models_say_how_to_make_them(tmp_path, capsys, astronaut_png):
    rc, err = run(capsys, "decompose", astronaut_png, "-o", tmp_path / "out", "--models", tmp_path / "nope", *FAST)
    assert rc == 1 and "dvc repro train_relight" in err and "nope" in err


# --- bad input: a clear message naming the file, a non-zero exit, nothing under a final name ------
def huge_png(path, width: int, height: int) -> None:
    """A valid PNG header for a huge image with (almost) no pixel data: refused from the header."""

    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body) & 0xFFFFFFFF)

    path.write_bytes(
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0))
        + chunk(b"IDAT", zlib.compress(b"\x00" * 16))
        + chunk(b"IEND", b"")
    )


def bad_inputs(tmp_path):
    empty = tmp_path / "empty.png"
    empty.write_bytes(b"")
    garbage = tmp_path / "garbage.jpg"
    garbage.write_bytes(b"this is not a JPEG at all" * 10)
    tiny = tmp_path / "one_pixel.png"
    Image.fromarray(np.zeros((1, 1, 3), np.uint8)).save(tiny)
    huge = tmp_path / "huge.png"
    huge_png(huge, 60000, 60000)
    return {
        "empty": (empty, "0 bytes"),
        "garbage": (garbage, "not a readable image"),
        "one_pixel": (tiny, "too small"),
        "huge": (huge, "--max-memory"),
    }


@pytest.mark.parametrize("case", ["empty", "garbage", "one_pixel", "huge"])
@pytest.mark.parametrize("command", ["decompose", "relight"])
def test_bad_photo_is_refused_naming_the_file(tmp_path, capsys, tiny_models, case, command):
    path, words = bad_inputs(tmp_path)[case]
    out = tmp_path / "out"
    light = ["--light", "left"] if command == "relight" else []
    t0 = time.perf_counter()
    rc, err = run(capsys, command, path, "-o", out, "--models", tiny_models, *light, *FAST)
    assert rc == 1
    assert str(path) in err and words in err
    assert final_files(out) == []
    if case == "huge":  # refused from the header: 60000^2 pixels were never decoded
        assert time.perf_counter() - t0 < 20 and "GiB" in err


def test_memory_limit_names_the_flag_and_can_be_raised(tmp_path, capsys, tiny_models, astronaut_png):
    out = tmp_path / "out"
    base = ["decompose", astronaut_png, "-o", out, "--models", tiny_models, *FAST]
    rc, err = run(capsys, *base, "--max-memory", "0.001")
    assert rc == 1 and "--max-memory" in err and "astronaut.png" in err and final_files(out) == []
    rc, err = run(capsys, *base, "--max-memory", "4")
    assert rc == 0, err


def test_one_bad_photo_stops_the_batch_before_any_work(tmp_path, capsys, tiny_models, astronaut_png):
    empty = tmp_path / "broken.png"
    empty.write_bytes(b"")
    out = tmp_path / "out"
    rc, err = run(capsys, "decompose", astronaut_png, empty, "-o", out, "--models", tiny_models, *FAST)
    assert rc == 1 and "broken.png" in err and "nothing was written" in err
    assert final_files(out) == []


def test_unknown_light_name(tmp_path, capsys, tiny_models, astronaut_png):
    rc, err = run(
        capsys, "relight", astronaut_png, "-o", tmp_path / "out", "--models", tiny_models, "--light", "upstairs", *FAST
    )
    assert rc == 2 and "upstairs" in err and "left|right|top|bottom|front" in err
    assert not (tmp_path / "out").exists()


def test_hdri_that_is_not_2_to_1(tmp_path, capsys, tiny_models, astronaut_png):
    from pilight.data.exr import write_exr

    hdri = tmp_path / "square.exr"
    write_exr(hdri, np.ones((32, 32, 3), np.float32), half=True)
    rc, err = run(
        capsys, "relight", astronaut_png, "-o", tmp_path / "out", "--models", tiny_models, "--hdri", hdri, *FAST
    )
    assert rc == 2 and str(hdri) in err and "2:1" in err
    assert not (tmp_path / "out").exists()


def test_output_folder_that_cannot_be_written(tmp_path, capsys, tiny_models, astronaut_png):
    blocker = tmp_path / "a_file"
    blocker.write_text("a file where the output folder should be")
    rc, err = run(capsys, "decompose", astronaut_png, "-o", blocker / "out", "--models", tiny_models, *FAST)
    assert rc == 1 and str(blocker / "out") in err and "cannot write" in err


def test_same_name_photos_would_collide(tmp_path, capsys, tiny_models, astronaut):
    for sub in ("x", "y"):
        (tmp_path / sub).mkdir()
        Image.fromarray(astronaut[::8, ::8]).save(tmp_path / sub / "shot.png")
    rc, err = run(
        capsys,
        "decompose",
        tmp_path / "x" / "shot.png",
        tmp_path / "y" / "shot.png",
        "-o",
        tmp_path / "out",
        "--models",
        tiny_models,
        *FAST,
    )
    assert rc == 1 and "shot" in err and "rename" in err
