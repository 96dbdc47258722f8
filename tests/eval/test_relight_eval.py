"""Pieces of the stage-2 evaluation that need no shards."""

import numpy as np
import pytest
import torch

from pilight.data.colour import tonemap01
from pilight.eval.grids import LABEL_HEIGHT, labelled_grid
from pilight.eval.relight import GRID_COLUMNS, grid_row


def _u8(x: torch.Tensor) -> np.ndarray:
    return (tonemap01(x[None])[0].clamp(0, 1).permute(1, 2, 0) * 255 + 0.5).byte().numpy()


def test_grid_row_tiles_ball_input_target_relit_then_d_and_s():
    g = torch.Generator().manual_seed(0)
    img = lambda: torch.rand(3, 16, 16, generator=g) * 2
    ball, a, b = torch.rand(3, 8, 8, generator=g), img(), img()
    relit_only = grid_row(ball, a, b, {"relit": img()}, img(), img())
    assert len(relit_only) == 4 and all(t.shape == (16, 16, 3) for t in relit_only)
    pred = {"relit": img(), "diffuse": img(), "specular": img()}
    gt_d, gt_s = img(), img()
    row = grid_row(ball, a, b, pred, gt_d, gt_s)
    assert len(row) == len(GRID_COLUMNS)
    for tile, want in zip(row[1:], (a, b, pred["relit"], gt_d, pred["diffuse"], gt_s, pred["specular"])):
        np.testing.assert_array_equal(tile, _u8(want))
    # the 8x8 ball is blown up by nearest neighbour, so each ball pixel is a 2x2 block
    np.testing.assert_array_equal(row[0][::2, ::2], _u8(ball))


def test_labelled_grid_places_tiles_under_their_labels():
    red, blue = np.zeros((8, 8, 3), np.uint8), np.zeros((8, 8, 3), np.uint8)
    red[..., 0], blue[..., 2] = 255, 255
    out = labelled_grid([[red, blue], [blue, None]], ["input", "relit"], gap=2)
    assert out.shape == (LABEL_HEIGHT + 2 * (8 + 2) + 2, 2 + 2 * (8 + 2), 3)
    y0, x0, x1 = LABEL_HEIGHT + 2, 2, 2 + 8 + 2
    np.testing.assert_array_equal(out[y0 : y0 + 8, x0 : x0 + 8], red)
    np.testing.assert_array_equal(out[y0 : y0 + 8, x1 : x1 + 8], blue)
    assert (out[y0 + 10 : y0 + 18, x1 : x1 + 8] == 255).all()  # an empty cell stays background
    assert (out[:LABEL_HEIGHT] < 128).any()  # the labels are drawn (dark text on white)
    with pytest.raises(ValueError, match="one per column label"):
        labelled_grid([[red]], ["input", "relit"])


def test_tight_unlabelled_grid_is_a_strip():
    """The render preview's and the CLI contact sheet's layout: no label band, each column as wide as its
    tile, a smaller tile at the top left of its cell on black, ``gap`` white columns between, no margin."""
    big = np.full((8, 6, 3), 100, np.uint8)
    ball = np.full((4, 4, 1), 50, np.uint8)  # one channel: gray
    out = labelled_grid([[big, ball, big]], None, gap=3, margin=0, tight=True)
    assert out.shape == (8, 6 + 3 + 4 + 3 + 6, 3)
    np.testing.assert_array_equal(out[:, :6], big)
    assert (out[:, 6:9] == 255).all() and (out[:, 13:16] == 255).all()
    assert (out[:4, 9:13] == 50).all() and (out[4:, 9:13] == 0).all()
    np.testing.assert_array_equal(out[:, 16:], big)
    np.testing.assert_array_equal(
        labelled_grid([[big, ball]], None, gap=0, tight=True),
        np.concatenate([big, np.pad(np.repeat(ball, 3, 2), ((0, 4), (0, 0), (0, 0)))], 1),
    )
