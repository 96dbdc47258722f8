"""DVC stage `evaluate`: the paper's tables on the held-out split, beside trivial baselines.

    python stages/evaluate.py

Now: stage 1 (intrinsics) in the paper's Table 1 / Table 7 layout -> metrics.json (dvc metrics,
shown by `dvc exp show`) and reports/intrinsics.md. Relighting tables and the speed/accuracy
sweeps join when stage 2 lands (issue #7).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pilight.params import ParamsError, load_section  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--params", default="params.yaml")
    ap.add_argument("--shards", type=Path, default=Path("data/shards"))
    ap.add_argument("--pred", type=Path, default=Path("data/intrinsics_pred"))
    ap.add_argument("--metrics", type=Path, default=Path("metrics/evaluate.json"))
    ap.add_argument("--reports", type=Path, default=Path("reports"))
    args = ap.parse_args(argv)
    try:
        load_section("base", args.params)
    except ParamsError as exc:
        print(f"evaluate: {exc}", file=sys.stderr)
        return 2
    from pilight.data.schema import DataError
    from pilight.eval.intrinsics import evaluate_intrinsics, markdown_table

    try:
        result = evaluate_intrinsics(args.shards, args.pred, "test")
    except DataError as exc:
        print(f"evaluate: {exc}", file=sys.stderr)
        return 1
    args.metrics.parent.mkdir(parents=True, exist_ok=True)
    args.metrics.write_text(json.dumps({"intrinsics": result}, indent=1, sort_keys=True) + "\n")
    args.reports.mkdir(parents=True, exist_ok=True)
    table = markdown_table(result, "test")
    (args.reports / "intrinsics.md").write_text(table)
    print(table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
