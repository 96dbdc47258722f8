"""The one exception for "stop with this message and this exit code", raised by the `pilight` command
(pilight.cli) and the DVC stage scripts (pilight.stage_cli) alike: the message is printed as one line
naming the file, sample or params key, never a traceback, and the process exits with ``code``."""

from __future__ import annotations


class CommandFailure(Exception):
    """``code``: 1 for bad input, a model or an output folder (nothing was written under a final name);
    2 for a bad option or a params value that turns out unusable once used (a weights folder that does
    not load)."""

    def __init__(self, message: str, code: int = 1):
        super().__init__(message)
        self.code = code
