"""pilight.eval.trade: the sweep's settings and the Pareto front."""

from __future__ import annotations

import torch

from pilight.eval import trade
from pilight.params import InferIntrinsicsParams, TradeParams


def test_pareto_front_of_known_points():
    pts = [
        {"s": 1.0, "acc": 10.0},
        {"s": 2.0, "acc": 12.0},
        {"s": 3.0, "acc": 11.0},  # 3 is dominated by 2
        {"s": 0.5, "acc": 9.0},
        {"s": 2.0, "acc": 12.0},
        {"s": 4.0, "acc": None},
    ]
    assert trade.pareto(pts, "s", "acc", higher_is_better=True) == [True, True, False, True, True, False]
    err = [{"s": 1.0, "e": 30.0}, {"s": 2.0, "e": 35.0}, {"s": 3.0, "e": 20.0}]
    assert trade.pareto(err, "s", "e", higher_is_better=False) == [True, False, True]


def test_sweep_is_one_factor_at_a_time_without_duplicates():
    base = InferIntrinsicsParams(mode="single_step", cfg_scale=1.0, ensemble=1)
    tp = TradeParams(steps=(1, 4), spacings=("leading", "trailing"), ensemble=(1, 2))
    settings = trade.sweep_settings(base, tp, (1.0, 2.0))
    labels = [(f, trade.describe(sp)) for f, sp in settings]
    assert labels == [
        ("steps", "DDIM 1 leading, cfg 1, ens 1"),
        ("steps", "DDIM 4 leading, cfg 1, ens 1"),
        ("steps", "DDIM 1 trailing, cfg 1, ens 1"),
        ("steps", "DDIM 4 trailing, cfg 1, ens 1"),
        ("mode", "1-step, cfg 1, ens 1"),  # cfg 1.0 and ensemble 1 at the base are this same point
        ("cfg", "1-step, cfg 2, ens 1"),
        ("ensemble", "1-step, cfg 1, ens 2"),
    ]


def test_run_sweep_times_and_scores_every_point():
    base = InferIntrinsicsParams(mode="ddim", steps=2)
    settings = trade.sweep_settings(base, TradeParams(steps=(1, 2), spacings=("trailing",), ensemble=(1,)), (1.0,))
    seen = []

    def predict(sp, gen):
        seen.append(sp.steps)
        return torch.full((1,), float(sp.steps))

    rows = trade.run_sweep(settings, predict, lambda out: {"acc": float(out[0])}, count=2, seed=0)
    assert [r["acc"] for r in rows] == [1.0, 2.0, 1.0]  # steps 1, steps 2, single-step (counted as 1)
    assert all(r["seconds_per_image"] >= 0 for r in rows) and len(seen) == len(rows) + 1  # + the warm-up call


def test_progress_hears_each_point_before_and_after_it_runs():
    """The stage's bar advances once per point (its ETA), not once per sweep."""
    base = InferIntrinsicsParams(mode="ddim", steps=2)
    settings = trade.sweep_settings(base, TradeParams(steps=(1, 2), spacings=("trailing",), ensemble=(1,)), (1.0,))
    heard, calls = [], []

    def predict(sp, gen):
        calls.append(len(heard))
        return torch.zeros(1)

    trade.run_sweep(settings, predict, lambda out: {}, count=1, seed=0, progress=heard.append)
    labels = [trade.describe(sp) for _, sp in settings]
    assert heard == [x for label in labels for x in (label, None)]
    assert calls[1:] == [1, 3, 5]  # each point runs after its label and before its None


def test_mark_fronts_marks_each_metric_by_its_direction():
    rows = [
        {"factor": "steps", "label": f"DDIM {n}", "seconds_per_image": s, "acc": a, "err": e}
        for n, s, a, e in ((3, 3.0, 1.0, 5.0), (2, 2.0, 2.0, 6.0), (1, 1.0, 1.0, 7.0))
    ]
    trade.mark_fronts(rows, {"acc": True, "err": False})
    assert [r["pareto_acc"] for r in rows] == [False, True, True]  # 3 s for accuracy 1 is beaten by 1 s
    assert [r["pareto_err"] for r in rows] == [True, True, True]  # each slower point has a lower error
    table = trade.markdown_table(rows, {"acc": "acc"}, "t")
    assert "| steps | DDIM 3 | 3.000 | 1.000 |" in table and "| steps | DDIM 2 | 2.000 | 2.000 * |" in table
