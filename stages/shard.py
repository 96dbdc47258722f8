"""DVC stage `shard`: data/renders -> data/shards (webdataset tars, split lists, relighting pairs).

    python stages/shard.py                      # params.yaml, data/renders -> data/shards
    python stages/shard.py --renders R --out O  # elsewhere (tests)

Reads params.yaml `base.seed`, the `shard:` section (pilight.data.shard_params.ShardParams) and
`render.hdri.test_holdout` (checked: no train/val scene may use those HDRIs).
Bad input exits 1 with one line naming the sample and file; nothing is left under --out.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a checkout without install

from pilight.data.exr import ExrError  # noqa: E402
from pilight.data.schema import DataError  # noqa: E402
from pilight.params import ParamsError, load_section  # noqa: E402
from pilight.data.shards import write_shards  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--params", type=Path, default=Path("params.yaml"))
    ap.add_argument("--renders", type=Path, default=Path("data/renders"))
    ap.add_argument("--out", type=Path, default=Path("data/shards"))
    args = ap.parse_args(argv)
    try:
        seed = load_section("base", args.params).seed
        shard = load_section("shard", args.params)
        heldout = load_section("render", args.params).hdri.test_holdout
    except ParamsError as exc:
        print(f"shard: error: {exc}", file=sys.stderr)
        return 2
    try:
        index = write_shards(args.renders, args.out, shard, seed=seed, heldout_hdris=heldout, progress=True)
    except (DataError, ExrError, OSError) as exc:
        print(f"shard: error: {exc}", file=sys.stderr)
        return 1
    counts = ", ".join(f"{s} {v['samples']} samples / {len(v['shards'])} shards" for s, v in index["splits"].items())
    print(f"shard: wrote {args.out}: {counts}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
