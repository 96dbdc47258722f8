"""DVC stage `evaluate`: the paper's tables on the held-out split, beside trivial baselines.

    python stages/evaluate.py

Stage 1 (intrinsics) in the paper's Table 1 / Table 7 layout, and stage 2 (relighting: PSNR/SSIM
in the relight and reconstruction settings beside "copy the input" and analytic A * D_calc, the
A D + S residual, the flipped-normal check, light-following: change_r2 with stage-1 and with
ground-truth conditions, direction and linearity of the probes, the physics-first identity)
-> metrics.json (dvc metrics, shown by `dvc exp show`),
reports/intrinsics.md, reports/relight.md, reports/intrinsics_grid.png (input | ground truth |
prediction for each intrinsic) and reports/relight_grid.png (target ball | input | target | relit,
then ground truth | model for D and S).  LPIPS needs local backbone weights (`evaluate.lpips_backbone`);
without them it is null in every table, with the reason. The relit predictions default to the `relit` folder
beside the shards (data/relit); when that folder does not exist the relighting part is skipped and
metrics.json says so.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from pilight import atomic
from pilight.stage_cli import StageFailure, run_stage


def options(ap) -> None:
    ap.add_argument("--shards", type=Path, default=Path("data/shards"))
    ap.add_argument("--pred", type=Path, default=Path("data/intrinsics_pred"))
    ap.add_argument("--relit", type=Path, default=None, help="relit pairs (default: <shards>/../relit)")
    ap.add_argument("--metrics", type=Path, default=Path("metrics/evaluate.json"))
    ap.add_argument("--reports", type=Path, default=Path("reports"))


def body(args, base, ev) -> int:
    from pilight.eval.intrinsics import evaluate_intrinsics, markdown_table
    from pilight.eval.lpips import load_lpips
    from pilight.eval.relight import evaluate_relight
    from pilight.eval.relight import markdown_table as relight_table

    relit_dir = args.relit if args.relit is not None else args.shards.parent / "relit"
    try:
        lpips, lpips_note = load_lpips(ev.lpips_net, ev.lpips_backbone)
    except (OSError, ValueError) as exc:  # a params value that does not load: a params error
        raise StageFailure(f"evaluate.lpips_backbone: {exc}", code=2) from exc
    result = evaluate_intrinsics(args.shards, args.pred, "test", lpips=lpips, grid_images=ev.grid_images)
    result["lpips_note"] = lpips_note
    grid = result.pop("grid", None)
    if (relit_dir / "index.json").is_file():
        split = json.loads((relit_dir / "index.json").read_text()).get("sampling", {}).get("split", "test")
        relight = evaluate_relight(
            args.shards, relit_dir, split, lpips=lpips, lpips_note=lpips_note, grid_pairs=ev.grid_images
        )
    else:
        relight = {"skipped": f"{relit_dir}/index.json not found (run the relight stage)"}
        print(f"evaluate: relighting skipped: {relight['skipped']}")
    relight_grid = relight.pop("grid", None)
    atomic.write_json(args.metrics, {"intrinsics": result, "relight": relight}, sort_keys=True)
    reports = {
        "intrinsics.md": markdown_table(result, "test"),
        "intrinsics_grid.png": grid,
        "relight.md": None if "skipped" in relight else relight_table(relight, split),
        "relight_grid.png": relight_grid,
    }
    for name, report in reports.items():
        # A report whose input is absent this run is removed: last run's file must not pass for this one's.
        path = args.reports / name
        if report is None:
            path.unlink(missing_ok=True)
        elif name.endswith(".png"):
            atomic.write_png(path, report)
        else:
            atomic.write_text(path, report)
            print(report)
    return 0


def main(argv: list[str] | None = None) -> int:
    return run_stage("evaluate", __doc__, argv, ["base", "evaluate"], options, body)


if __name__ == "__main__":
    sys.exit(main())
