"""Image grids, the one tiling every picture for people goes through: training previews, evaluation
and trade reports (labelled), the render stage's preview strips and the CLI's contact sheets
(unlabelled, ``tight``). Tiles in rows and columns, a label above each column and optionally before
each row, so a reader knows what each picture is without the README."""

from __future__ import annotations

import numpy as np
from PIL import Image, ImageDraw, ImageFont

LABEL_HEIGHT = 14
BACKGROUND = 255  # white margins, gaps and label bands; cells a tile does not fill are black


def _font(size: int = 11):
    try:
        return ImageFont.load_default(size=size)  # Pillow >= 10.1: a scalable bundled font
    except TypeError:
        return ImageFont.load_default()


def _fit(tile: np.ndarray, h: int, w: int, centre: bool = True) -> np.ndarray:
    """A uint8 H x W x 3 tile on a black h x w canvas, centred or at the top left (smaller tiles,
    e.g. balls, are padded)."""
    t = np.asarray(tile)
    if t.ndim == 2:
        t = t[..., None]
    if t.shape[2] == 1:
        t = np.repeat(t, 3, axis=2)
    if t.shape[:2] == (h, w):
        return t
    out = np.zeros((h, w, 3), dtype=np.uint8)
    th, tw = min(t.shape[0], h), min(t.shape[1], w)
    y, x = ((h - th) // 2, (w - tw) // 2) if centre else (0, 0)
    out[y : y + th, x : x + tw] = t[:th, :tw]
    return out


def labelled_grid(
    rows: list[list[np.ndarray | None]],
    column_labels: list[str] | None,
    row_labels: list[str] | None = None,
    gap: int = 2,
    margin: int | None = None,
    tight: bool = False,
) -> np.ndarray:
    """(H, W, 3) uint8: ``rows`` of uint8 tiles (H x W x 3 or 1, or H x W; None = an empty cell), each
    column headed by its label (``column_labels`` None: no label band), each row led by its label
    when given; ``gap`` white pixels between cells, ``margin`` (default ``gap``) around them.
    Every cell takes the largest tile's size and holds its tile centred; ``tight``: each column is
    as wide as its widest tile and each row as tall as its tallest, tiles at the cell's top left."""
    columns = len(column_labels) if column_labels is not None else len(rows[0]) if rows else 0
    if not rows or any(len(r) != columns for r in rows):
        raise ValueError(f"labelled_grid: every row needs {columns} tiles, one per column label")
    if row_labels is not None and len(row_labels) != len(rows):
        raise ValueError(f"labelled_grid: {len(rows)} rows but {len(row_labels)} row labels")
    margin = gap if margin is None else margin
    size = lambda ts, axis: max((t.shape[axis] for t in ts if t is not None), default=0)
    if tight:
        widths = [size([r[j] for r in rows], 1) for j in range(columns)]
        heights = [size(r, 0) for r in rows]
    else:
        tiles = [t for r in rows for t in r]
        widths, heights = [size(tiles, 1)] * columns, [size(tiles, 0)] * len(rows)
    font = _font()
    left = 0
    if row_labels:
        probe = ImageDraw.Draw(Image.new("RGB", (1, 1)))
        left = max(int(probe.textlength(s, font=font)) for s in row_labels) + 2 * gap
    top = (LABEL_HEIGHT if column_labels is not None else 0) + margin
    xs = [left + margin + sum(widths[:j]) + j * gap for j in range(columns)]
    ys = [top + sum(heights[:i]) + i * gap for i in range(len(rows))]
    canvas = Image.new("RGB", (xs[-1] + widths[-1] + margin, ys[-1] + heights[-1] + margin), (BACKGROUND,) * 3)
    draw = ImageDraw.Draw(canvas)
    for j, label in enumerate(column_labels or []):
        draw.text((xs[j] + widths[j] / 2, LABEL_HEIGHT / 2), label, fill=(0, 0, 0), font=font, anchor="mm")
    for i, row in enumerate(rows):
        if row_labels:
            draw.text((gap, ys[i] + heights[i] / 2), row_labels[i], fill=(0, 0, 0), font=font, anchor="lm")
        for j, tile in enumerate(row):
            if tile is not None:
                canvas.paste(Image.fromarray(_fit(tile, heights[i], widths[j], centre=not tight)), (xs[j], ys[i]))
    return np.asarray(canvas)
