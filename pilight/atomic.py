"""Write, then rename: a crash or a full disk never leaves a partial file under a final name.

DVC and the next stage trust whatever sits at an output's path, so metrics, reports, plots and
model configs go through here (large outputs such as EXRs, shards and checkpoints have their
own temporary-folder writers). The temporary file lives in the target's folder, so the final
``os.replace`` is a rename on one filesystem, which is atomic.
"""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any


def _replace_with(path: str | os.PathLike, write: Callable[[str], None]) -> Path:
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
    return _replace_with(path, lambda tmp: Path(tmp).write_text(text, encoding="utf-8"))


def write_json(path: str | os.PathLike, obj: Any, **dumps_kw) -> Path:
    """``obj`` as indented JSON plus a newline (``dumps_kw`` e.g. sort_keys=True)."""
    return write_text(path, json.dumps(obj, indent=1, **dumps_kw) + "\n")


def write_png(path: str | os.PathLike, array) -> Path:
    """An (H, W, 3) uint8 array as PNG."""
    from PIL import Image

    return _replace_with(path, lambda tmp: Image.fromarray(array).save(tmp, format="PNG"))


def save_figure(fig, path: str | os.PathLike, **savefig_kw) -> Path:
    """A matplotlib figure; the format comes from ``path``'s suffix, not the temporary name's."""
    fmt = Path(path).suffix.lstrip(".") or "png"
    return _replace_with(path, lambda tmp: fig.savefig(tmp, format=fmt, **savefig_kw))
