"""DVC stage `render`: Blender renders of procedural (and user) scenes with exact intrinsics.

    python stages/render.py                      # params.yaml -> data/renders
    python stages/render.py --params my.yaml --out /tmp/renders

Reads params sections `base` and `render`; validates them before Blender starts. Resumable:
complete views are skipped on a rerun (see pilight.render.dataset).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pilight.params import ParamsError, load_section  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--params", default="params.yaml")
    ap.add_argument("--out", default="data/renders")
    ap.add_argument("--log", type=Path, default=Path("logs/render.log"),
                    help="where Blender's own output goes (appended; not a DVC output: it holds timings)")
    ap.add_argument("--verbose", action="store_true", help="Blender's output on the terminal instead of --log")
    args = ap.parse_args(argv)
    try:
        base = load_section("base", args.params)
        render = load_section("render", args.params)
    except ParamsError as exc:
        print(f"render: {exc}", file=sys.stderr)
        return 2
    # bpy is imported only after the params are known to be good (it takes a second to load).
    from pilight.render.dataset import render_dataset
    from pilight.render.passes import ContractError
    from pilight.render.scene import RenderError

    try:
        stats = render_dataset(render, base, Path(args.out), blender_log=None if args.verbose else args.log)
    except (RenderError, ContractError) as exc:
        print(f"render: {exc}", file=sys.stderr)
        return 1
    print(f"render: {stats['bundles']} (view, light) bundles in {stats['seconds']:.1f} s "
          f"({60 * stats['bundles'] / max(stats['seconds'], 1e-9):.1f} per minute) -> {args.out}"
          + ("" if args.verbose else f" (Blender's log: {args.log})"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
