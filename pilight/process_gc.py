"""The cyclic garbage collector of the ``pilight`` command's own process, kept off its start and its exit.

Why: ``pilight relight photo.jpg`` is about half a second of work behind seconds of imports. Importing
torch and diffusers creates about 360,000 objects the collector tracks; with CPython's default
thresholds it runs about 900 collections during those imports and frees about 9,000 objects, and at
exit it walks them all once more. On a 2-core AVX2-only EPYC (2026-12-08) that was about 0.6 s of the
imports and 0.8 s of the exit, of a 5.9 s command (``benchmarks/cli_startup.py``).

So the console entry point holds collection back while it imports and loads models, then freezes what
exists by then (``gc.freeze``: those objects live as long as the process, and the collector never
walks them again) and restores the thresholds for the work itself, so that a long batch or the app's
server collects as usual. ``pilight.cli.main`` called in-process (the tests, a notebook) leaves the
caller's thresholds alone.

Every DVC stage process pays the exit too (about 0.8 s each once torch is imported); the command and
the stages (``pilight.stage_cli.run_stage``) register a freeze to run at the interpreter's exit, after
the program's own exit handlers, which leaves the last collection nothing to walk. In an in-process
caller that runs only when the caller itself exits.
"""

from __future__ import annotations

import atexit
import gc

# Collect the youngest generation every 100,000 allocations instead of 700 while importing: still
# bounded, should a command never reach release_collection().
STARTUP_THRESHOLD = 100_000

_held_thresholds: tuple[int, ...] | None = None
_freeze_registered = False


def hold_collection() -> None:
    """Raise the collector's first threshold for an import-heavy start; release_collection() undoes it."""
    global _held_thresholds
    if _held_thresholds is None:
        _held_thresholds = gc.get_threshold()
        gc.set_threshold(STARTUP_THRESHOLD, *_held_thresholds[1:])


def release_collection() -> None:
    """After imports and model loading: freeze what exists (kept for the process's life) and restore the
    thresholds held back. Does nothing where hold_collection() was not called (an in-process caller)."""
    global _held_thresholds
    if _held_thresholds is None:
        return
    gc.freeze()
    gc.set_threshold(*_held_thresholds)
    _held_thresholds = None


def freeze_at_exit() -> None:
    """Freeze everything when the interpreter exits (registered once): at that point nothing is worth a
    last walk of every object. Exit handlers run last-registered first, so one registered at the start
    runs after the program's own."""
    global _freeze_registered
    if not _freeze_registered:
        atexit.register(gc.freeze)
        _freeze_registered = True
