"""Which light-following probes does a relit model read backwards, and is it stage 2 or stage 1's normals?

    python benchmarks/direction_probes.py [--shards data/shards] [--pred data/intrinsics_pred]
                                          [--relit data/relit] [--split test] [--json FILE]

The evaluation's ``direction`` (pilight.eval.light_following) is one share over the probe images: is
the relit image's left/right asymmetry larger under the light from camera-right than from camera-left?
A miss can come from stage 2, or from stage 1's normals, which physics-first relighting shades. This
prints, per probe image the relight stage relit (``--relit``'s probes split):

  model        the relit image's asymmetry under the right and the left probe light (the evaluation's)
  normals      stage 1's mean angular error on the mask (degrees)
  lambert      the same asymmetry of a pure Lambertian shading n . l of STAGE 1's normals under the two
               probe directions: what physics alone would read from those normals
  lambert gt   the same with the ground-truth normals (always right unless the probe is degenerate)

then the direction share of each column, overall and per scene. A probe that ``lambert`` already reads
backwards is lost to stage 1's normals, whatever stage 2 does. No model runs; one CPU thread is enough.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import defaultdict
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pilight.data.predictions import read_predictions  # noqa: E402
from pilight.data.schema import sample_key  # noqa: E402
from pilight.data.shard_reader import eval_dataset, make_loader  # noqa: E402
from pilight.eval.light_following import (  # noqa: E402
    PROBE_AZIMUTH_DEG,
    PROBE_ELEVATION_DEG,
    PROBE_SPLIT,
    lr_asymmetry,
    probe_key,
    select_probes,
)
from pilight.eval.metrics import angular_errors  # noqa: E402
from pilight.eval.relight import PROBE_COUNT_MAX  # noqa: E402
from pilight.lights import direction  # noqa: E402


def lambert_asymmetry(normal: torch.Tensor, normal_gt: torch.Tensor, mask: torch.Tensor) -> tuple[float, float]:
    """(right, left): lr_asymmetry of max(0, n . l) for the probe lights from camera-right and camera-left,
    with ``normal`` shaded and ``normal_gt`` classifying the sides, as the evaluation classifies them."""
    n = torch.nn.functional.normalize(normal.float(), dim=1)
    out = []
    for sign in (1.0, -1.0):
        light = direction(sign * PROBE_AZIMUTH_DEG, PROBE_ELEVATION_DEG).float().view(1, 3, 1, 1)
        shading = (n * light).sum(1, keepdim=True).clamp_min(0).expand(-1, 3, -1, -1)
        out.append(float(lr_asymmetry(shading, normal_gt, mask)[0]))
    return out[0], out[1]


def mean_angle_deg(normal: torch.Tensor, normal_gt: torch.Tensor, mask: torch.Tensor) -> float:
    """Mean angular error (degrees) of ``normal`` against ``normal_gt`` over the mask, one image."""
    return float(angular_errors(normal.float(), normal_gt.float(), mask).mean())  # the masked pixels only


def probe_rows(shards: Path, pred: Path, relit: Path, split: str) -> list[dict]:
    """One row per probe image that ``relit`` holds: the module docstring's columns."""
    probes = select_probes(make_loader(eval_dataset(shards, split, "relight"), 8), PROBE_COUNT_MAX)
    relit_maps = read_predictions(relit, PROBE_SPLIT)
    stage1 = read_predictions(pred, split)
    rows = []
    for p in probes:
        if probe_key(p, "right") not in relit_maps:
            continue
        meta = json.loads(p["meta_a"][0])
        image = sample_key(meta["scene"], meta["view"], meta["light"])
        if image not in stage1:
            raise SystemExit(f"{pred}: no stage-1 prediction for probe image {image} (split {split!r})")
        normal_gt, mask = p["normal"], p["mask"]
        normal = torch.from_numpy(stage1[image]["normal"]).permute(2, 0, 1)[None]
        relit = {
            s: torch.from_numpy(relit_maps[probe_key(p, s)]["relit"]).permute(2, 0, 1)[None] for s in ("right", "left")
        }
        rows.append(
            {
                "image": image,
                "scene": meta["scene"],
                "model": [float(lr_asymmetry(relit[s], normal_gt, mask)[0]) for s in ("right", "left")],
                "normal_deg": mean_angle_deg(normal, normal_gt, mask),
                "lambert": list(lambert_asymmetry(normal, normal_gt, mask)),
                "lambert_gt": list(lambert_asymmetry(normal_gt, normal_gt, mask)),
            }
        )
    if not rows:
        raise SystemExit(f"{relit}: no relit probe images for split {split!r}; run the relight stage first")
    return rows


COLUMNS = ("model", "lambert", "lambert_gt")


def shares(rows: list[dict]) -> dict[str, float]:
    """The direction share of each column: right asymmetry > left, as light_following.direction_score."""
    return {c: sum(r[c][0] > r[c][1] for r in rows) / len(rows) for c in COLUMNS}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--shards", type=Path, default=Path("data/shards"))
    ap.add_argument("--pred", type=Path, default=Path("data/intrinsics_pred"))
    ap.add_argument("--relit", type=Path, default=Path("data/relit"))
    ap.add_argument("--split", default="test")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    torch.set_num_threads(1)
    rows = probe_rows(args.shards, args.pred, args.relit, args.split)
    mark = lambda pair: "ok   " if pair[0] > pair[1] else "WRONG"
    print(f"{'probe image':20s} {'model R / L':>16s}       {'normals':>7s}  {'lambert R / L':>16s}       lambert gt")
    for r in rows:
        print(
            f"{r['image']:20s} {r['model'][0]:+.3f} / {r['model'][1]:+.3f} {mark(r['model'])} {r['normal_deg']:6.1f}°"
            f"  {r['lambert'][0]:+.3f} / {r['lambert'][1]:+.3f} {mark(r['lambert'])} {mark(r['lambert_gt'])}"
        )
    by_scene = defaultdict(list)
    for r in rows:
        by_scene[r["scene"]].append(r)
    summary = {"all": shares(rows), **{s: shares(rs) for s, rs in sorted(by_scene.items())}}
    print(f"\ndirection share ({len(rows)} probe images): model / lambert (stage-1 normals) / lambert (ground truth)")
    for name, s in summary.items():
        print(f"  {name:12s} {s['model']:.2f} / {s['lambert']:.2f} / {s['lambert_gt']:.2f}")
    if args.json:
        tmp = args.json.with_suffix(args.json.suffix + ".tmp")
        tmp.write_text(json.dumps({"rows": rows, "direction": summary}, indent=1))
        tmp.replace(args.json)


if __name__ == "__main__":
    main()
