"""DVC stage `trade`: the speed/accuracy trade of sampling, for both stages, and a relit-under-
several-lights grid.

    python stages/trade.py

Sweeps steps x spacing, single-step, CFG and ensemble size one factor at a time around
`infer_intrinsics` (stage 1) and `relight_infer` (stage 2) on the first `evaluate.trade.images`
test images / pairs (see pilight/eval/trade.py).  Writes

- metrics/trade.json                  every point (dvc metrics), seconds per image and accuracy;
- plots/trade_intrinsics.json, plots/trade_relight.json and their *_pareto*.json fronts (dvc plots);
- reports/trade.md, reports/trade_intrinsics.png, reports/trade_relight.png;
- reports/relit_lights.png: RELIT_LIGHTS_ROWS test views (the first cross-light pair of each), one row each, relit under
  `evaluate.relight_lights` analytic lights swept around them, each column's ball above it
  (pilight/eval/relit_lights.py).

Timings vary between runs, so this stage is not byte-deterministic; the accuracy columns are.
"""

from __future__ import annotations

import sys
from pathlib import Path

from pilight import atomic
from pilight.stage_cli import fails_on, run_stage


def options(ap) -> None:
    ap.add_argument("--shards", type=Path, default=Path("data/shards"))
    ap.add_argument("--pred", type=Path, default=Path("data/intrinsics_pred"))
    ap.add_argument("--intrinsics-model", type=Path, default=Path("models/intrinsics"))
    ap.add_argument("--relight-model", type=Path, default=Path("models/relight"))
    ap.add_argument("--metrics", type=Path, default=Path("metrics/trade.json"))
    ap.add_argument("--plots", type=Path, default=Path("plots"))
    ap.add_argument("--reports", type=Path, default=Path("reports"))


def body(args, base, p1, ip1, p2, ip2, ev) -> int:
    import torch
    from tqdm import tqdm

    from pilight.data.schema import DataError
    from pilight.data.shards import eval_dataset, make_loader
    from pilight.eval import trade
    from pilight.relight.conditions import choose_intrinsics, optional_predictions
    from pilight.train.build import ModelError, load_model
    from pilight.train.intrinsics import IntrinsicsTask
    from pilight.train.relight import RelightTask

    tp, split = ev.trade, ip2.split
    with fails_on(ModelError, FileNotFoundError, ValueError):
        t1 = IntrinsicsTask(p1, args.shards, seed=base.seed)
        load_model(t1.stack, args.intrinsics_model)
        t2 = RelightTask(p2.model_copy(update={"conditions": "gt"}), args.shards, seed=base.seed)
        load_model(t2.stack, args.relight_model)
        imgs = trade.first_n(make_loader(eval_dataset(args.shards, "test", "intrinsics"), 8), tp.images)
        pairs = trade.first_n(
            make_loader(eval_dataset(args.shards, split, "relight"), 8), tp.images, trade.is_cross_light
        )
        if not imgs or not pairs:
            raise DataError(f"{args.shards}: no test images or no cross-light {split} pairs to sweep")
        preds = optional_predictions(args.shards, args.pred, split, "trade")
    t1.stack.model.eval()
    t2.stack.model.eval()
    n1, n2 = len(imgs["key"]), len(pairs["key"])
    intr = choose_intrinsics(pairs, torch.full((n2,), preds is not None), preds)
    points = len(trade.sweep_settings(ip1, tp, tp.intrinsics_cfg)) + len(trade.sweep_settings(ip2, tp, tp.relight_cfg))
    with tqdm(total=points, desc="trade", unit="point") as bar:
        tick = lambda label: (bar.set_postfix_str(label), bar.update(0))
        rows1 = trade.sweep_intrinsics(t1, imgs, ip1, tp, base.seed, tick)
        bar.update(len(rows1))
        rows2 = trade.sweep_relight(t2, pairs, intr, ip2, tp, base.seed, tick)
        bar.update(len(rows2))
    grid = trade.lights_grid(t2, args.shards, split, ip2, base.seed, preds, ev.relight_lights)
    conditions = "stage-1 predictions" if preds is not None else "ground-truth intrinsics"
    md = trade.write_trade(rows1, rows2, n1, n2, conditions, args.metrics, args.plots, args.reports)
    atomic.write_png(args.reports / "relit_lights.png", grid)
    print(md)
    return 0


def main(argv: list[str] | None = None) -> int:
    sections = ["base", "intrinsics", "infer_intrinsics", "relight", "relight_infer", "evaluate"]
    return run_stage("trade", __doc__, argv, sections, options, body)


if __name__ == "__main__":
    sys.exit(main())
