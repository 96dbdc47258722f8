"""Issue 18: atomically written files get the umask's mode, and a failed write names the final path."""

from __future__ import annotations

import errno
import os
import stat
import tempfile
from pathlib import Path

import pytest

from pilight import atomic


@pytest.fixture
def umask_027():
    old = os.umask(0o027)
    try:
        yield
    finally:
        os.umask(old)


def _mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def test_written_files_follow_the_umask(tmp_path, umask_027):
    # mkstemp alone would leave 0600: group members could not read renders, models or reports.
    atomic.write_text(tmp_path / "report.md", "x\n")
    atomic.write_json(tmp_path / "m.json", {"a": 1})
    assert _mode(tmp_path / "report.md") == 0o640
    assert _mode(tmp_path / "m.json") == 0o640
    os.umask(0o022)
    atomic.write_text(tmp_path / "report.md", "y\n")
    assert _mode(tmp_path / "report.md") == 0o644


def test_exr_follows_the_umask(tmp_path, umask_027):
    import numpy as np

    from pilight.data.exr import write_exr

    write_exr(tmp_path / "a.exr", np.zeros((2, 2, 3), np.float32), half=True)
    assert _mode(tmp_path / "a.exr") == 0o640


def test_full_disk_names_the_output_and_leaves_nothing(tmp_path):
    def write(tmp: str) -> None:
        Path(tmp).write_bytes(b"partial")
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    target = tmp_path / "out" / "metrics.json"
    with pytest.raises(OSError, match="No space left on device") as info:
        atomic.write_with(target, write)
    assert str(target) in str(info.value) and info.value.errno == errno.ENOSPC
    assert list((tmp_path / "out").iterdir()) == []


def test_read_only_folder_names_the_output(tmp_path, monkeypatch):
    # Simulated: the tests may run as root, for whom a 0555 folder is still writable.
    def refuse(dir, prefix, suffix):
        name = os.path.join(dir, f"{prefix}abc{suffix}")
        raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), name)

    monkeypatch.setattr(tempfile, "mkstemp", refuse)
    target = tmp_path / "grid.png"
    with pytest.raises(PermissionError) as info:
        atomic.write_text(target, "x")
    assert info.value.filename == str(target)
    assert str(target) in str(info.value)


def test_an_error_naming_an_input_is_kept(tmp_path):
    # A writer that fails reading its own input must not be reported as the output's fault.
    missing = tmp_path / "input.exr"
    with pytest.raises(FileNotFoundError) as info:
        atomic.write_with(tmp_path / "out.txt", lambda tmp: Path(tmp).write_bytes(missing.read_bytes()))
    assert info.value.filename == str(missing)


def test_exr_write_failure_names_the_output(tmp_path, monkeypatch):
    import numpy as np
    import OpenEXR

    from pilight.data import exr

    class Full:  # what OpenEXR raises when the disk fills: a bare Exception naming the temporary
        def __init__(self, *a, **kw):
            pass

        def __enter__(self):
            return self

        def __exit__(self, *a):
            return False

        def write(self, name):
            raise Exception(f'Cannot write image file "{name}". No space left on device.')

    monkeypatch.setattr(OpenEXR, "File", Full)
    target = tmp_path / "a.exr"
    with pytest.raises(exr.ExrError, match=rf"{target}: cannot write EXR .*No space left on device"):
        exr.write_exr(target, np.zeros((2, 2, 3), np.float32), half=True)
    assert list(tmp_path.iterdir()) == []
