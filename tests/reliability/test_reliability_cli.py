"""Issue 36 on the photo CLI: options checked before anything is loaded or created, photos and balls that
are not what they claim, and outputs per light that appear whole or not at all (killed mid-write, full disk)."""

from __future__ import annotations

import errno
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from fixtures.stage_scripts import REPO, stage_env
from pilight import cli
from pilight.cli import main
from pilight.data.exr import write_exr

FAST = ["--resolution", "32", "--device", "cpu"]


def run(capsys, *argv):
    rc = main([str(a) for a in argv])
    return rc, capsys.readouterr().err


def _no_model_load(monkeypatch):
    from pilight.pipeline import PILightPipeline

    def refuse(*a, **k):
        raise AssertionError("the models were loaded before the options were checked")

    monkeypatch.setattr(PILightPipeline, "from_pretrained", refuse)


# --- options, before anything is loaded or created -----------------------------------------------------
@pytest.mark.parametrize(
    "option, message",
    [
        (["--cfg", "nan"], "--cfg nan: Input should be a finite number"),
        (["--cfg", "1e9"], "--cfg 1000000000.0: Input should be less than or equal to 50"),
        (["--steps", "0"], "--steps 0: Input should be greater than or equal to 1"),
        (["--ensemble", "100000"], "--ensemble 100000: Input should be less than or equal to 256"),
        (["--resolution", "1000000"], "--resolution must lie in [0, 16384]"),
        (["--max-memory", "inf"], "--max-memory must be a finite number of GiB > 0"),
    ],
)
@pytest.mark.parametrize("command", ["decompose", "relight"])
def test_bad_options_exit_2_before_models_load_or_out_is_made(
    tmp_path, capsys, monkeypatch, astronaut_png, tiny_models, command, option, message
):
    _no_model_load(monkeypatch)
    out = tmp_path / "out"
    light = ["--light", "left"] if command == "relight" else []
    rc, err = run(capsys, command, astronaut_png, "-o", out, "--models", tiny_models, *light, *option)
    # Before: --cfg nan was a sampler traceback after the models loaded, and -o was created first.
    assert rc == 2 and message in err and "Traceback" not in err, err
    assert not out.exists()


def test_a_refused_photo_leaves_no_output_folder(tmp_path, capsys, tiny_models):
    out = tmp_path / "deep" / "out"
    rc, err = run(capsys, "decompose", tmp_path / "missing.png", "-o", out, "--models", tiny_models, *FAST)
    assert rc == 1 and "missing.png: file not found" in err
    assert not (tmp_path / "deep").exists()


# --- photos and balls that are not what they claim ------------------------------------------------------
def test_an_animated_gif_is_refused_naming_it(tmp_path, capsys, tiny_models, astronaut):
    gif = tmp_path / "anim.gif"
    frames = [Image.fromarray(astronaut[::8, ::8]), Image.fromarray(astronaut[::8, ::8][::-1])]
    frames[0].save(gif, save_all=True, append_images=frames[1:], duration=100, loop=0)
    rc, err = run(capsys, "decompose", gif, "-o", tmp_path / "out", "--models", tiny_models, *FAST)
    # Before: its first frame was used without a word.
    assert rc == 1 and f"{gif}: 2 frames (an animation or a multi-page file)" in err, err
    assert not (tmp_path / "out").exists()


def test_negative_hdr_values_are_said(tmp_path, capsys, tiny_models):
    exr = tmp_path / "neg.exr"
    a = np.full((32, 32, 3), 0.5, np.float32)
    a[:2, :3] = -0.25
    write_exr(exr, a, half=False)
    rc, err = run(capsys, "decompose", exr, "-o", tmp_path / "out", "--models", tiny_models, *FAST)
    # Before: clamped to 0 silently.
    assert rc == 0 and f"pilight: warning: {exr}: 18 negative value(s), down to -0.25, set to 0" in err, err


def test_a_photo_whose_alpha_is_all_zero_is_refused(tmp_path, capsys, tiny_models, astronaut):
    png = tmp_path / "clear.png"
    rgba = np.concatenate([astronaut[::8, ::8], np.zeros((64, 64, 1), np.uint8)], axis=2)
    Image.fromarray(rgba).save(png)
    rc, err = run(capsys, "relight", png, "-o", tmp_path / "out", "--models", tiny_models, "--light", "left", *FAST)
    # Before: relit as if empty, exit 0.
    assert rc == 1 and f"{png}: its alpha channel is below 0.5 everywhere" in err, err
    assert not (tmp_path / "out").exists()


def test_a_picture_without_a_ball_is_said_and_a_black_one_refused(tmp_path, capsys, tiny_models, astronaut_png):
    from pilight.lights import ball_preview, named

    rc, err = run(capsys, "ball", "-o", tmp_path / "x", "--ball", astronaut_png)
    # Before: any square picture was a light, without a word.
    assert rc == 0 and f"pilight: warning: {astronaut_png}: no round silhouette" in err, err
    ball = tmp_path / "ball.png"
    Image.fromarray(ball_preview(named("left").ball)).save(ball)
    rc, err = run(capsys, "ball", "-o", tmp_path / "y", "--ball", ball)
    assert rc == 0 and "warning" not in err, err
    black = tmp_path / "black.png"
    Image.fromarray(np.zeros((64, 64, 3), np.uint8)).save(black)
    rc, err = run(capsys, "ball", "-o", tmp_path / "z", "--ball", black)
    assert rc == 2 and f"{black}: the light ball's disk is black" in err, err


# --- whole or nothing -----------------------------------------------------------------------------------
def _relight_argv(photo, out, models):
    return ["relight", str(photo), "-o", str(out), "--models", str(models), "--light", "left", "--light", "right"]


def _files(out: Path) -> dict[str, bytes]:
    return {str(p.relative_to(out)): p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()}


def test_relight_killed_mid_write_leaves_nothing_under_a_final_name(tmp_path, tiny_models, astronaut_png):
    """SIGKILL as soon as the first output file exists: no light folder may hold part of its files. The
    rerun sweeps the killed run's temporary and ends with the bytes of an uninterrupted run."""
    clean = tmp_path / "clean"
    assert main(_relight_argv(astronaut_png, clean, tiny_models) + FAST) == 0
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "pilight.cli", *_relight_argv(astronaut_png, out, tiny_models), *FAST]
    proc = subprocess.Popen(cmd, cwd=REPO, env=stage_env(), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 300
    while time.time() < deadline and proc.poll() is None:
        if any(p.is_file() for p in (out / "astronaut").rglob("*")) if (out / "astronaut").is_dir() else False:
            os.kill(proc.pid, signal.SIGKILL)
            break
        time.sleep(0.001)
    proc.wait()
    assert proc.returncode == -signal.SIGKILL, "the run ended before it could be killed mid-write"
    # Before: relit.exr, relit.png and diffuse.exr under left/, without specular, ball or contact sheet.
    for light in ("left", "right"):
        folder = out / "astronaut" / light
        assert not folder.exists() or len(list(folder.iterdir())) == 9, sorted(folder.iterdir())
    left_over = [p for p in (out / "astronaut").iterdir() if p.name.startswith(".")]
    assert left_over, "the kill should have left the temporary of the light being written"
    r = subprocess.run(cmd, cwd=REPO, env=stage_env(), capture_output=True, text=True, timeout=600)
    assert r.returncode == 0 and "removed 1 temporary output(s) left by a killed run" in r.stderr, r.stderr
    assert _files(out) == _files(clean)


def test_a_full_disk_names_the_light_and_tells_what_was_kept(tmp_path, capsys, monkeypatch, tiny_models, astronaut_png):
    real = cli.write_group

    def full_on_the_second_light(files):
        if any("right" in Path(p).parent.name for p in files):  # right/ before, .right.tmp-... now
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        real(files)

    monkeypatch.setattr(cli, "write_group", full_on_the_second_light)
    out = tmp_path / "out"
    rc, err = run(capsys, *_relight_argv(astronaut_png, out, tiny_models), *FAST)
    # Before: "nothing of this photo was kept" while left/ was complete.
    assert rc == 1, err
    assert f"{out / 'astronaut' / 'right'}: cannot write this light's outputs (No space left on device)" in err
    assert "nothing of this light was kept; its light(s) left are complete" in err, err
    assert sorted(p.name for p in (out / "astronaut").iterdir()) == ["left"]
    assert len(list((out / "astronaut" / "left").iterdir())) == 9


def test_a_live_processs_temporary_is_never_swept(tmp_path):
    folder = tmp_path / "photo"
    folder.mkdir()
    mine = folder / f".left.tmp-{cli._HOST}-{os.getpid()}-abc"
    other_host = folder / ".left.tmp-elsewhere-1-abc"
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    stale = folder / f".left.tmp-{cli._HOST}-{dead.pid}-abc"
    for p in (mine, other_host, stale):
        p.mkdir()
    assert cli.sweep_stale(folder) == [stale]
    assert mine.is_dir() and other_host.is_dir()
