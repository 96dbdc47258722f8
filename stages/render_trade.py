"""DVC stage `render_trade`: the render side of the speed/accuracy trade, samples per pixel against
noise and seconds.

    python stages/render_trade.py

For the first object scene and the first room scene of the test split (view 0, light 0, the
render params' resolution and bounces), the beauty pass is rendered at each
`evaluate.trade.render_spp` with adaptive sampling OFF (so spp means spp), and once at
`evaluate.trade.render_reference_spp` with another seed as the reference (pilight/render/spp_sweep.py).
Noise error = PSNR of the tone-mapped image against the reference; seconds are wall-clock per
render (pilight/eval/render_trade.py). The pipeline's own setting (`render.cycles.samples` with its
adaptive threshold) is measured too.

Writes metrics/render_trade.json, plots/render_trade.json (dvc plots) and reports/render_trade.md / .png.
"""

from __future__ import annotations

import sys
from pathlib import Path

from pilight.stage_cli import fails_on, run_stage


def options(ap) -> None:
    ap.add_argument("--metrics", type=Path, default=Path("metrics/render_trade.json"))
    ap.add_argument("--plots", type=Path, default=Path("plots"))
    ap.add_argument("--reports", type=Path, default=Path("reports"))
    ap.add_argument("--log", type=Path, default=Path("logs/render_trade.log"), help="where Blender's own output goes")
    ap.add_argument("--verbose", action="store_true", help="Blender's output on the terminal instead of --log")


def body(args, base, p, ev) -> int:
    # bpy is imported only after the params are known to be good (it takes a second to load).
    from pilight.eval.render_trade import score_renders, write_render_trade
    from pilight.render.scene import RenderError
    from pilight.render.spp_sweep import render_spp_sweep

    with fails_on(RenderError):
        renders = render_spp_sweep(p, base, ev.trade, blender_log=None if args.verbose else args.log)
    md = write_render_trade(
        score_renders(renders), p.resolution, ev.trade.render_reference_spp, args.metrics, args.plots, args.reports
    )
    print(md)
    return 0


def main(argv: list[str] | None = None) -> int:
    return run_stage(
        "render_trade",
        __doc__,
        argv,
        ["base", "render", "evaluate"],
        options,
        body,
        outputs=lambda a: [a.metrics, a.plots, a.reports],
    )


if __name__ == "__main__":
    sys.exit(main())
