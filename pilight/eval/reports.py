"""The evaluate stage's report files (reports/*.md and *.png). Each is written atomically, and a report
whose input is absent this run (no relit folder, no grid asked for) is removed: last run's file must
not pass for this one's."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pilight import atomic


def write_reports(folder: Path, reports: dict[str, str | np.ndarray | None]) -> list[str]:
    """Write ``reports`` ({file name: markdown text, an (H, W, 3) uint8 image for a .png, or None to
    remove the file}) into ``folder``; the texts written, in order (the stage prints them)."""
    texts = []
    for name, report in reports.items():
        path = Path(folder) / name
        if report is None:
            path.unlink(missing_ok=True)
        elif name.endswith(".png"):
            atomic.write_png(path, report)
        else:
            atomic.write_text(path, report)
            texts.append(report)
    return texts
