"""`pilight.cli._say_warnings`: every warning raised inside it is said once, after the block. It once
re-showed other libraries' warnings while still recording them, appending to the list it was reading:
an endless loop that grew the test process to 24 GB (CI's OOM kills). Run in a child process with a
memory cap and a timeout, so the broken version fails this test instead of the machine."""

from __future__ import annotations

import resource
import subprocess
import sys

from fixtures.stage_scripts import REPO, stage_env

CHILD = """
import warnings
from pilight.cli import _say_warnings
from pilight.photo import PhotoWarning
with _say_warnings():
    warnings.warn("a library's deprecation", DeprecationWarning)
    warnings.warn("read with a change", PhotoWarning)
print("done")
"""


def _cap_memory():
    resource.setrlimit(resource.RLIMIT_AS, (3 * 1024**3, 3 * 1024**3))


def test_each_warning_is_said_once_after_the_block():
    r = subprocess.run(
        [sys.executable, "-c", CHILD],
        capture_output=True,
        text=True,
        cwd=REPO,
        env=stage_env(),
        timeout=60,
        preexec_fn=_cap_memory,
    )
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.strip() == "done"
    assert r.stderr.count("a library's deprecation") == 1
    assert r.stderr.count("pilight: warning: read with a change") == 1
