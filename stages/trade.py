"""DVC stage `trade`: the speed/accuracy trade of sampling, for both stages, and a relit-lights grid.

    python stages/trade.py

Sweeps steps x spacing, single-step, CFG and ensemble size one factor at a time around
`infer_intrinsics` (stage 1) and `relight_infer` (stage 2) on the first `evaluate.trade.images` test
images / pairs (pilight/eval/trade.py). Timings vary between runs, so this stage is not
byte-deterministic; the accuracy columns are. Writes
- metrics/trade.json (every point, dvc metrics) and plots/trade_{intrinsics,relight}[_pareto_*].json;
- reports/trade.md, reports/trade_intrinsics.png, reports/trade_relight.png;
- reports/relit_lights.png: the first cross-light pair of RELIT_LIGHTS_ROWS test views relit under
  `evaluate.relight_lights` analytic lights, each column's ball above it (pilight/eval/relit_lights.py).
"""

from __future__ import annotations

import sys
from pathlib import Path

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
    from pilight.eval import trade
    from pilight.models.folder import load_model
    from pilight.models.intrinsics import IntrinsicsModel
    from pilight.models.relight import RelightModel
    from pilight.models.stack import ModelError

    with fails_on(ModelError, FileNotFoundError, ValueError):
        t1, t2 = IntrinsicsModel(p1), RelightModel(p2)
        load_model(t1.stack, args.intrinsics_model)
        load_model(t2.stack, args.relight_model)
        imgs, pairs, preds = trade.sweep_samples(args.shards, args.pred, ip2.split, ev.trade.images)
    t1.stack.model.eval()
    t2.stack.model.eval()
    rows1, rows2 = trade.sweep_both(t1, imgs, ip1, t2, pairs, ip2, preds, ev.trade, base.training_seed)
    grid = trade.lights_grid(t2, args.shards, ip2.split, ip2, base.training_seed, preds, ev.relight_lights)
    conditions = "stage-1 predictions" if preds is not None else "ground-truth intrinsics"
    n1, n2 = len(imgs["key"]), len(pairs["key"])
    print(trade.write_trade(rows1, rows2, n1, n2, conditions, grid, args.metrics, args.plots, args.reports))
    return 0


def main(argv: list[str] | None = None) -> int:
    sections = ["base", "intrinsics", "infer_intrinsics", "relight", "relight_infer", "evaluate"]
    return run_stage("trade", __doc__, argv, sections, options, body, outputs=lambda a: [a.metrics, a.plots, a.reports])


if __name__ == "__main__":
    sys.exit(main())
