"""DVC stage `evaluate`: the paper's tables on the held-out split, beside trivial baselines.

    python stages/evaluate.py

Stage 1 (intrinsics: the paper's Table 1 / Table 7 layout; albedo raw, si-PSNR, LMSE and light-invariance
beside the input image; roughness and metallic beside the training mean and median) and stage 2
(relighting in three tiers, absolute, relative and scale-invariant, each with copy, exposure-matched copy,
physics anchor and oracles; the A D + S residual, the flipped-normal check, the probes' direction and
linearity, the physics-first identity) -> metrics/evaluate.json (every figure, numbers only),
metrics/headline.json (the figures two runs are compared on; pilight.eval.metrics_files),
reports/intrinsics.md, reports/relight.md (the notes: spaces, conditions, why LPIPS is absent),
reports/intrinsics_grid.png (input | ground truth | prediction for each intrinsic) and
reports/relight_grid.png (target ball | input | target | relit, then ground truth | model for D and S).
LPIPS needs local backbone weights (`evaluate.lpips_backbone`), else it is absent, with the reason in the
reports. The relit predictions default to the `relit` folder beside the shards (data/relit); without it
the relighting part is skipped (absent from the metrics, no relight report).
"""

from __future__ import annotations

import sys
from pathlib import Path

from pilight import atomic
from pilight.failure import CommandFailure
from pilight.stage_cli import run_stage


def options(ap) -> None:
    ap.add_argument("--shards", type=Path, default=Path("data/shards"))
    ap.add_argument("--pred", type=Path, default=Path("data/intrinsics_pred"))
    ap.add_argument("--relit", type=Path, default=None, help="relit pairs (default: <shards>/../relit)")
    ap.add_argument("--metrics", type=Path, default=Path("metrics/evaluate.json"))
    ap.add_argument(
        "--headline",
        type=Path,
        default=None,
        help="headline figures (default: beside --metrics, its name's 'evaluate' replaced by 'headline', "
        "else 'headline_' + its name)",
    )
    ap.add_argument("--reports", type=Path, default=Path("reports"))


def headline_path(metrics: Path) -> Path:
    """metrics/evaluate.json -> metrics/headline.json, metrics/evaluate_heldout.json -> metrics/headline_heldout.json:
    beside the metrics it summarises, so two evaluations (base/dvc.yaml's test and held-out) never share one."""
    name = metrics.name
    return metrics.with_name(name.replace("evaluate", "headline", 1) if "evaluate" in name else f"headline_{name}")


def body(args, base, ev) -> int:
    from pilight.eval.intrinsics import intrinsics_report
    from pilight.eval.lpips import load_lpips
    from pilight.eval.metrics_files import headline, numbers_only
    from pilight.eval.relight import relight_report
    from pilight.eval.reports import write_reports

    relit_dir = args.relit if args.relit is not None else args.shards.parent / "relit"
    try:
        lpips, lpips_note = load_lpips(ev.lpips_net, ev.lpips_backbone)
    except (OSError, ValueError) as exc:  # a params value that does not load: a params error
        raise CommandFailure(f"evaluate.lpips_backbone: {exc}", code=2) from exc
    intr, intr_md, intr_grid = intrinsics_report(args.shards, args.pred, "test", lpips, lpips_note, ev.grid_images)
    relight, relight_md, relight_grid = relight_report(args.shards, relit_dir, lpips, lpips_note, ev.grid_images)
    if relight_md is None:
        print(f"evaluate: relighting skipped: {relit_dir}/index.json not found (run the relight stage)")
    metrics = numbers_only({"intrinsics": intr, "relight": relight})
    atomic.write_json(args.metrics, metrics, sort_keys=True)
    atomic.write_json(
        args.headline or headline_path(args.metrics),
        headline(metrics.get("intrinsics", {}), metrics.get("relight", {})),
    )
    reports = {"intrinsics.md": intr_md, "intrinsics_grid.png": intr_grid}
    reports |= {"relight.md": relight_md, "relight_grid.png": relight_grid}
    for text in write_reports(args.reports, reports):
        print(text)
    return 0


def main(argv: list[str] | None = None) -> int:
    return run_stage(
        "evaluate",
        __doc__,
        argv,
        ["base", "evaluate"],
        options,
        body,
        outputs=lambda a: [a.metrics, a.headline or headline_path(a.metrics), a.reports],
    )


if __name__ == "__main__":
    sys.exit(main())
