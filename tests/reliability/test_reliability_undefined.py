"""Issue 36, undefined is not perfect: a figure over an empty mask is missing (None: "n/a" in the reports,
null in the JSON), not 1.0 or 0 or NaN, and the reports and trade plots handle it whole."""

from __future__ import annotations

import json

import torch

from pilight.eval.intrinsics import table1
from pilight.params import InferIntrinsicsParams, TradeParams


def _maps(b: int, seed: int = 0) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    n = torch.nn.functional.normalize(torch.randn(b, 3, 16, 16, generator=g), dim=1)
    return {
        "albedo": torch.rand(b, 3, 16, 16, generator=g),
        "normal": n,
        "roughness": torch.rand(b, 1, 16, 16, generator=g),
        "metallic": torch.rand(b, 1, 16, 16, generator=g),
    }


def test_ssim_over_zero_pixels_is_missing_not_perfect():
    pred, gt = _maps(2, 0), _maps(2, 1)
    empty = torch.zeros(2, 1, 16, 16)
    t = table1(pred, gt, empty)
    # Before: SSIM 1.000 for every map (both maps zeroed off the mask match exactly).
    assert all(t[d]["ssim"] is None and t[d]["psnr"] is None for d in ("albedo", "normal", "roughness"))
    assert t["average"]["ssim"] is None


def test_an_image_with_an_empty_mask_does_not_count():
    pred, gt = _maps(3, 0), _maps(3, 1)
    mask = torch.ones(3, 1, 16, 16)
    with_empty = mask.clone()
    with_empty[2] = 0
    both = table1(pred, gt, with_empty)["albedo"]["ssim"]
    alone = table1({k: v[:2] for k, v in pred.items()}, {k: v[:2] for k, v in gt.items()}, mask[:2])["albedo"]["ssim"]
    # Before: the empty image's 1.0 was averaged in.
    assert abs(both - alone) < 1e-6


class FakeIntrinsics:
    def predict(self, image, domains, sp, generator):
        return {k: v[: image.shape[0]] for k, v in _maps(image.shape[0], 2).items() if k in domains}


def test_the_trade_sweep_reports_a_missing_angle_and_plots_it(tmp_path):
    from pilight.eval import trade

    imgs = {"key": ["a", "b"], "image": torch.rand(2, 3, 16, 16), "mask": torch.zeros(2, 1, 16, 16), **_maps(2, 1)}
    ip = InferIntrinsicsParams(mode="single_step")
    tp = TradeParams(steps=(1,), spacings=("trailing",), intrinsics_cfg=(1.0,), ensemble=(1,))
    rows = trade.sweep_intrinsics(FakeIntrinsics(), imgs, ip, tp, seed=0)
    # Before: NaN (a mean over no pixel), then "nan" in the table and a NaN point in the plot.
    assert all(r["normal_mean_deg"] is None and r["albedo_psnr"] is None for r in rows), rows
    md = trade.markdown_table(rows, {k: v for k, (v, _) in trade.INTRINSICS_METRICS.items()}, "t")
    assert "nan" not in md and "n/a" in md
    trade.plot_png(rows, trade.INTRINSICS_METRICS, tmp_path / "trade.png", "t")
    assert (tmp_path / "trade.png").stat().st_size > 0
    json.loads(json.dumps(rows, allow_nan=False))  # valid JSON: no NaN anywhere
