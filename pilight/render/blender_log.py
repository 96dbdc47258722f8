"""Blender's own output goes to a log file, not the terminal.

Blender writes a line per saved file ("render | Saved: '.../pilight_main.exr'") from C, through its
logger, straight to the process's file descriptors 1 and 2; Python's sys.stdout cannot catch that.
With 300 bundles that is 600 lines interleaved with the progress bar, so a reader cannot see what
is happening. `blender_output_to(path)` points descriptors 1 and 2 at `path` for the duration, and
hands back a stream on the ORIGINAL terminal for the progress bar and messages meant for people.
`path=None` (the stages' `--verbose`) changes nothing.
"""

from __future__ import annotations

import ctypes
import os
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO

_LIBC = ctypes.CDLL(None)


def _flush_all() -> None:
    """Flush Python's streams and C's stdio buffers, so nothing written before a switch lands after it."""
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):
            pass
    _LIBC.fflush(None)


@contextmanager
def blender_output_to(path: Path | None) -> Iterator[IO[str]]:
    """Redirect fds 1 and 2 to `path` (appended); yield a text stream on the original stderr."""
    if path is None:
        yield sys.stderr
        return
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    _flush_all()
    saved = {fd: os.dup(fd) for fd in (1, 2)}
    terminal = os.fdopen(os.dup(saved[2]), "w", buffering=1)
    log = open(path, "ab")
    try:
        for fd in (1, 2):
            os.dup2(log.fileno(), fd)
        yield terminal
    finally:
        _flush_all()
        for fd, orig in saved.items():
            os.dup2(orig, fd)
            os.close(orig)
        log.close()
        terminal.close()
