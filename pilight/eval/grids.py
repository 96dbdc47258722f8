"""Labelled image grids for reports: tiles in rows and columns, a label above each column and
optionally before each row, so a reader knows what each picture is without the README."""

from __future__ import annotations

import numpy as np
from PIL import Image, ImageDraw, ImageFont

LABEL_HEIGHT = 14
BACKGROUND = 255  # white margins and label bands


def _font(size: int = 11):
    try:
        return ImageFont.load_default(size=size)  # Pillow >= 10.1: a scalable bundled font
    except TypeError:
        return ImageFont.load_default()


def _fit(tile: np.ndarray, h: int, w: int) -> np.ndarray:
    """A uint8 H x W x 3 tile, centred on a black h x w canvas (smaller tiles, e.g. balls, are padded)."""
    t = np.asarray(tile)
    if t.ndim == 2:
        t = np.repeat(t[..., None], 3, axis=2)
    if t.shape[:2] == (h, w):
        return t
    out = np.zeros((h, w, 3), dtype=np.uint8)
    th, tw = min(t.shape[0], h), min(t.shape[1], w)
    y, x = (h - th) // 2, (w - tw) // 2
    out[y:y + th, x:x + tw] = t[:th, :tw]
    return out


def labelled_grid(rows: list[list[np.ndarray | None]], column_labels: list[str],
                  row_labels: list[str] | None = None, gap: int = 2) -> np.ndarray:
    """(H, W, 3) uint8: ``rows`` of uint8 tiles (None = an empty cell), each column headed by its
    label, each row led by its label when given. Every cell takes the largest tile's size."""
    if not rows or any(len(r) != len(column_labels) for r in rows):
        raise ValueError(f"labelled_grid: every row needs {len(column_labels)} tiles, one per column label")
    if row_labels is not None and len(row_labels) != len(rows):
        raise ValueError(f"labelled_grid: {len(rows)} rows but {len(row_labels)} row labels")
    tiles = [t for r in rows for t in r if t is not None]
    h = max(t.shape[0] for t in tiles)
    w = max(t.shape[1] for t in tiles)
    font = _font()
    left = 0
    if row_labels:
        probe = ImageDraw.Draw(Image.new("RGB", (1, 1)))
        left = max(int(probe.textlength(s, font=font)) for s in row_labels) + 2 * gap
    width = left + len(column_labels) * (w + gap) + gap
    height = LABEL_HEIGHT + len(rows) * (h + gap) + gap
    canvas = Image.new("RGB", (width, height), (BACKGROUND,) * 3)
    draw = ImageDraw.Draw(canvas)
    for j, label in enumerate(column_labels):
        x = left + gap + j * (w + gap)
        draw.text((x + w / 2, LABEL_HEIGHT / 2), label, fill=(0, 0, 0), font=font, anchor="mm")
    for i, row in enumerate(rows):
        y = LABEL_HEIGHT + gap + i * (h + gap)
        if row_labels:
            draw.text((gap, y + h / 2), row_labels[i], fill=(0, 0, 0), font=font, anchor="lm")
        for j, tile in enumerate(row):
            if tile is not None:
                canvas.paste(Image.fromarray(_fit(tile, h, w)), (left + gap + j * (w + gap), y))
    return np.asarray(canvas)
