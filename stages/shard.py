"""DVC stage `shard`: data/renders -> data/shards (webdataset tars, split lists, relighting pairs).

    python stages/shard.py                      # params.yaml, data/renders -> data/shards
    python stages/shard.py --renders R --out O  # elsewhere (tests)

Reads params.yaml `base.seed`, the `shard:` section (pilight.data.shard_params.ShardParams) and
`render.hdri.test_holdout` (checked: no train/val scene may use those HDRIs).
Bad input exits 1 with one line naming the sample and file; nothing is left under --out.
"""

from __future__ import annotations

import sys
from pathlib import Path

from pilight.stage_cli import fails_on, run_stage


def options(ap) -> None:
    ap.add_argument("--renders", type=Path, default=Path("data/renders"))
    ap.add_argument("--out", type=Path, default=Path("data/shards"))


def body(args, base, shard, render) -> int:
    from pilight.data.exr import ExrError
    from pilight.data.shard_writer import write_shards

    with fails_on(ExrError, OSError):
        index = write_shards(
            args.renders, args.out, shard, seed=base.seed, heldout_hdris=render.hdri.test_holdout, progress=True
        )
    counts = ", ".join(f"{s} {v['samples']} samples / {len(v['shards'])} shards" for s, v in index["splits"].items())
    print(f"shard: wrote {args.out}: {counts}")
    return 0


def main(argv: list[str] | None = None) -> int:
    return run_stage("shard", __doc__, argv, ["base", "shard", "render"], options, body, outputs=lambda a: [a.out])


if __name__ == "__main__":
    sys.exit(main())
