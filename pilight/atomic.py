"""Write, then rename: a crash or a full disk never leaves a partial file under a final name.

DVC and the next stage trust whatever sits at an output's path, so every single-file output
goes through here: EXRs, previews and sidecars, models, metrics, reports, plots (multi-file
outputs such as shards, predictions and checkpoints are written into a temporary folder that is
renamed). The temporary file lives in the target's folder, so the final ``os.replace`` is a rename
on one filesystem, which is atomic.

``mkstemp`` creates its file with mode 0600 whatever the umask; the result is given the mode a plain
``open()`` would have given it (0666 less the umask), so colleagues or a web server can read the
outputs wherever the umask allows it. An ``OSError`` (read-only folder, full disk) is re-raised with
the final path as its filename: the temporary's name, or none at all, tells the user nothing.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any, NoReturn


def umask() -> int:
    """The process umask. Read from /proc where it is shown, since ``os.umask`` can only read it by
    setting it, which briefly changes it for every thread of the process."""
    try:
        with open("/proc/self/status", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    old = os.umask(0o022)
    os.umask(old)
    return old


def file_mode() -> int:
    """The mode ``open()`` gives a new file: 0666 less the umask."""
    return 0o666 & ~umask()


def dir_mode() -> int:
    """The mode ``mkdir()`` gives a new folder: 0777 less the umask (``mkdtemp`` makes 0700)."""
    return 0o777 & ~umask()


def path_error(exc: OSError, path: str | os.PathLike, own: Callable[[str], bool] = lambda name: False) -> OSError:
    """``exc`` as the same OSError subclass, naming ``path`` (e.g. "[Errno 28] No space left on
    device: 'data/shards'"). Only an error that names no file, or a temporary of ours (``own``), is
    renamed: one that names some other file (an input that could not be read) already says the right thing."""
    if exc.filename is not None and not own(os.fspath(exc.filename)):
        return exc
    try:
        if exc.errno is not None:
            new = type(exc)(exc.errno, exc.strerror or os.strerror(exc.errno), os.fspath(path))
        else:
            new = type(exc)(f"{os.fspath(path)}: {exc}")
    except TypeError:  # a subclass with a constructor of its own
        new = OSError(exc.errno, f"{exc}", os.fspath(path))
    return new


def sha256_file(path: str | os.PathLike) -> str:
    """Hex sha256 of a file, read in 1 MiB chunks (shards, checkpoints, models)."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def folder_write_error(exc: BaseException, out: Path) -> BaseException:
    """The error to raise when writing the folder ``out`` (through a temporary sibling
    ``.<name>.*``) failed: an OSError (a full disk names no file) is re-raised naming ``out``."""
    if not isinstance(exc, OSError):
        return exc
    prefix = os.path.join(os.fspath(Path(out).parent), f".{Path(out).name}.")
    return path_error(exc, out, lambda name: name.startswith(prefix))


def abandon_folder(exc: BaseException, tmp: str | os.PathLike | None, out: Path) -> NoReturn:
    """Inside ``except BaseException as exc`` of a folder write: remove the temporary ``tmp`` (when it
    was made) and raise, naming ``out`` when the error is an OSError (folder_write_error)."""
    if tmp is not None:
        shutil.rmtree(tmp, ignore_errors=True)
    err = folder_write_error(exc, out)  # a full disk names no file: say which output failed
    if err is exc:
        raise exc
    raise err from exc


def write_with(path: str | os.PathLike, write: Callable[[str], None]) -> Path:
    """Call ``write(temporary path)``, then rename the result to ``path``; on any error the
    temporary is removed and ``path`` keeps what it held."""
    path = Path(path)
    tmp = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
        os.close(fd)
        write(tmp)
        os.chmod(tmp, file_mode())
        os.replace(tmp, path)
    except BaseException as exc:
        if tmp is not None:
            Path(tmp).unlink(missing_ok=True)
        if isinstance(exc, OSError):
            prefix = os.path.join(os.fspath(path.parent), f".{path.name}.")
            raise path_error(exc, path, lambda name: name.startswith(prefix)) from exc
        raise
    return path


# What a killed write leaves (issue 36), by writer: write_with's `.<name>.<8 random>.tmp` beside its file; a
# folder written under `.<name>.tmp-<random>` (shards, predictions, the CLI's light folders) or moved aside as
# `.<name>.old-<pid>` (shards); export's `.<name>.tmp` and `.<name>.old`; inside an output folder, the render's
# scratch `.render_tmp_*` and the checkpoints' `.tmp-*`.
_FILE_TEMP = re.compile(r"^\..+\.[A-Za-z0-9_]{8}\.tmp$")
_INNER_TEMP = re.compile(r"^\.(render_tmp_|tmp-)")


def _beside(name: str) -> re.Pattern:
    n = re.escape(name)
    return re.compile(rf"^\.{n}\.(tmp-.+|old-.+|tmp|old|[A-Za-z0-9_]{{8}}\.tmp)$")


def sweep_temporaries(*outputs: str | os.PathLike | None) -> list[Path]:
    """Remove the temporaries that killed writes of ``outputs`` (files or folders; None is skipped) left:
    beside each output, those of its own name; inside an output folder, write_with's (at any depth) and
    the render's and checkpoints' scratch (its top level). A stage calls this at its start (its outputs
    are its own while it runs); returns what was removed."""
    removed: list[Path] = []

    def drop(p: Path) -> None:
        shutil.rmtree(p, ignore_errors=True) if p.is_dir() and not p.is_symlink() else p.unlink(missing_ok=True)
        removed.append(p)

    for out in outputs:
        if out is None:
            continue
        out = Path(out)
        if out.parent.is_dir():
            beside = _beside(out.name)
            for p in sorted(out.parent.iterdir()):
                if beside.match(p.name):
                    drop(p)
        if out.is_dir() and not out.is_symlink():
            for p in sorted(out.iterdir()):
                if _INNER_TEMP.match(p.name):
                    drop(p)
            for root, _dirs, files in os.walk(out):
                for f in sorted(files):
                    if _FILE_TEMP.match(f):
                        drop(Path(root) / f)
    return removed


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
