"""Write, then rename: a crash or a full disk never leaves a partial file under a final name.

DVC and the next stage trust whatever sits at an output's path, so every single-file output
goes through here: EXRs, previews and sidecars, models, metrics, reports, plots (multi-file
outputs such as shards, predictions and checkpoints are written into a temporary folder that is
renamed). The temporary file lives in the target's folder, so the final ``os.replace`` is a rename
on one filesystem, which is atomic.
"""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any


def write_with(path: str | os.PathLike, write: Callable[[str], None]) -> Path:
    """Call ``write(temporary path)``, then rename the result to ``path``; on any error the
    temporary is removed and ``path`` keeps what it held."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    os.close(fd)
    try:
        write(tmp)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def write_text(path: str | os.PathLike, text: str) -> Path:
    return write_with(path, lambda tmp: Path(tmp).write_text(text, encoding="utf-8"))


def write_json(path: str | os.PathLike, obj: Any, **dumps_kw) -> Path:
    """``obj`` as indented JSON plus a newline (``dumps_kw`` e.g. sort_keys=True)."""
    return write_text(path, json.dumps(obj, indent=1, **dumps_kw) + "\n")


def write_png(path: str | os.PathLike, array, **save_kw) -> Path:
    """An (H, W, 3) uint8 array as PNG (``save_kw`` e.g. compress_level=1)."""
    from PIL import Image

    return write_with(path, lambda tmp: Image.fromarray(array).save(tmp, format="PNG", **save_kw))


def save_figure(fig, path: str | os.PathLike, **savefig_kw) -> Path:
    """A matplotlib figure; the format comes from ``path``'s suffix, not the temporary name's."""
    fmt = Path(path).suffix.lstrip(".") or "png"
    return write_with(path, lambda tmp: fig.savefig(tmp, format=fmt, **savefig_kw))
