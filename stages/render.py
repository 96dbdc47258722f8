"""DVC stage `render`: Blender renders of procedural (and user) scenes with exact intrinsics.

    python stages/render.py                      # params.yaml -> data/renders
    python stages/render.py --params my.yaml --out /tmp/renders

Reads params sections `base` and `render`; validates them before Blender starts. Resumable:
complete views are skipped on a rerun (see pilight.render.dataset).
"""

from __future__ import annotations

import sys
from pathlib import Path

from pilight.stage_cli import fails_on, run_stage


def options(ap) -> None:
    ap.add_argument("--out", default="data/renders")
    ap.add_argument(
        "--log",
        type=Path,
        default=Path("logs/render.log"),
        help="where Blender's own output goes (appended; not a DVC output: it holds timings)",
    )
    ap.add_argument("--verbose", action="store_true", help="Blender's output on the terminal instead of --log")


def body(args, base, render) -> int:
    # bpy is imported only after the params are known to be good (it takes a second to load).
    from pilight.render.dataset import render_dataset
    from pilight.render.passes import ContractError
    from pilight.render.scene import RenderError

    with fails_on(RenderError, ContractError):
        stats = render_dataset(render, base, Path(args.out), blender_log=None if args.verbose else args.log)
    print(
        f"render: {stats['bundles']} (view, light) bundles in {stats['seconds']:.1f} s "
        f"({60 * stats['bundles'] / max(stats['seconds'], 1e-9):.1f} per minute) -> {args.out}"
        + ("" if args.verbose else f" (Blender's log: {args.log})")
    )
    return 0


def main(argv: list[str] | None = None) -> int:
    return run_stage("render", __doc__, argv, ["base", "render"], options, body, outputs=lambda a: [a.out])


if __name__ == "__main__":
    sys.exit(main())
