"""Pieces of the stage-2 evaluation that need no shards."""

import torch

from pilight.eval.relight import grid_row, tonemap01


def test_grid_row_tiles_ball_input_target_relit_then_d_and_s():
    g = torch.Generator().manual_seed(0)
    img = lambda: torch.rand(3, 16, 16, generator=g) * 2
    ball, a, b = torch.rand(3, 8, 8, generator=g), img(), img()
    relit_only = grid_row(ball, a, b, {"relit": img()}, img(), img())
    assert relit_only.shape == (3, 16, 4 * 16)
    pred = {"relit": img(), "diffuse": img(), "specular": img()}
    gt_d, gt_s = img(), img()
    row = grid_row(ball, a, b, pred, gt_d, gt_s)
    assert row.shape == (3, 16, 8 * 16)
    tiles = row.split(16, dim=2)
    for tile, want in zip(tiles[1:], (a, b, pred["relit"], gt_d, pred["diffuse"], gt_s, pred["specular"])):
        torch.testing.assert_close(tile, tonemap01(want[None])[0])
    # the 8x8 ball is blown up by nearest neighbour, so each ball pixel is a 2x2 block
    torch.testing.assert_close(tiles[0][:, ::2, ::2], tonemap01(ball[None])[0])
