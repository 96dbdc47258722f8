"""Blender's C-level output goes to the log; the progress stream stays on the terminal."""

import ctypes
import os

from pilight.render.blender_log import blender_output_to

LIBC = ctypes.CDLL(None)


def test_c_level_output_goes_to_the_log_and_the_terminal_stream_stays(tmp_path, capfd):
    log = tmp_path / "logs" / "render.log"
    with blender_output_to(log) as terminal:
        os.write(1, b"fd1: Saved: pilight_main.exr\n")
        os.write(2, b"fd2: render | Saved: pilight_ball.exr\n")
        LIBC.printf(b"stdio: buffered in C\n")  # through C stdio, as Blender prints
        terminal.write("bar 3/10\n")
    print("after")
    out, err = capfd.readouterr()
    text = log.read_text()
    for line in ("fd1: Saved", "fd2: render | Saved", "stdio: buffered in C"):
        assert line in text
        assert line not in out + err
    assert "bar 3/10" in err and "bar 3/10" not in text
    assert "after" in out  # descriptors restored


def test_none_leaves_the_terminal_alone(capfd):
    with blender_output_to(None) as terminal:
        os.write(1, b"visible\n")
        terminal.write("bar\n")
    out, err = capfd.readouterr()
    assert "visible" in out and "bar" in err


def test_appends(tmp_path):
    log = tmp_path / "b.log"
    for word in (b"one\n", b"two\n"):
        with blender_output_to(log):
            os.write(1, word)
    assert log.read_text() == "one\ntwo\n"
