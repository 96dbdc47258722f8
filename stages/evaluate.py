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

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pilight import atomic  # noqa: E402
from pilight.params import ParamsError, load_section  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--params", default="params.yaml")
    ap.add_argument("--shards", type=Path, default=Path("data/shards"))
    ap.add_argument("--pred", type=Path, default=Path("data/intrinsics_pred"))
    ap.add_argument("--relit", type=Path, default=None, help="relit pairs (default: <shards>/../relit)")
    ap.add_argument("--metrics", type=Path, default=Path("metrics/evaluate.json"))
    ap.add_argument("--reports", type=Path, default=Path("reports"))
    args = ap.parse_args(argv)
    try:
        load_section("base", args.params)
        ev = load_section("evaluate", args.params)
    except ParamsError as exc:
        print(f"evaluate: {exc}", file=sys.stderr)
        return 2
    from pilight.data.schema import DataError
    from pilight.eval.intrinsics import evaluate_intrinsics, markdown_table
    from pilight.eval.lpips import load_lpips

    relit_dir = args.relit if args.relit is not None else args.shards.parent / "relit"
    try:
        lpips, lpips_note = load_lpips(ev.lpips_net, ev.lpips_backbone)
    except (OSError, ValueError) as exc:
        print(f"evaluate: evaluate.lpips_backbone: {exc}", file=sys.stderr)
        return 2
    try:
        result = evaluate_intrinsics(args.shards, args.pred, "test", lpips=lpips, grid_images=ev.grid_images)
        result["lpips_note"] = lpips_note
        grid = result.pop("grid", None)
        if (relit_dir / "index.json").is_file():
            from pilight.eval.relight import evaluate_relight, markdown_table as relight_table

            split = json.loads((relit_dir / "index.json").read_text()).get("sampling", {}).get("split", "test")
            relight = evaluate_relight(args.shards, relit_dir, split, lpips=lpips, lpips_note=lpips_note,
                                       grid_pairs=ev.grid_images)
        else:
            relight = {"skipped": f"{relit_dir}/index.json not found (run the relight stage)"}
            print(f"evaluate: relighting skipped: {relight['skipped']}")
        relight_grid = relight.pop("grid", None)
    except DataError as exc:
        print(f"evaluate: {exc}", file=sys.stderr)
        return 1
    atomic.write_json(args.metrics, {"intrinsics": result, "relight": relight}, sort_keys=True)
    table = markdown_table(result, "test")
    atomic.write_text(args.reports / "intrinsics.md", table)
    _write_or_remove(args.reports / "intrinsics_grid.png", grid)
    print(table)
    if "skipped" not in relight:
        table = relight_table(relight, split)
        atomic.write_text(args.reports / "relight.md", table)
        print(table)
    else:
        (args.reports / "relight.md").unlink(missing_ok=True)
    _write_or_remove(args.reports / "relight_grid.png", relight_grid)
    return 0


def _write_or_remove(path: Path, image) -> None:
    """A report whose input is absent this run is removed: last run's file must not pass for this one's."""
    if image is None:
        path.unlink(missing_ok=True)
    else:
        atomic.write_png(path, image)


if __name__ == "__main__":
    sys.exit(main())
