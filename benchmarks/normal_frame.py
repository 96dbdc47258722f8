"""Are stage 1's normals tilted as a whole? The rotation about the camera's x axis that best aligns each
image's predicted normals with the truth, by scene kind and camera pitch.

    python benchmarks/normal_frame.py                                   # data/intrinsics_pred, data/shards, test
    python benchmarks/normal_frame.py --pred base/data/intrinsics_pred --shards base/data/shards --split test
    python benchmarks/normal_frame.py --fixed -15                       # every image turned by the same angle

Normals are camera-space (x right, y up, z toward the camera). A floor seen by a camera pitched down by
theta has the normal (0, cos theta, sin theta); a model that misjudges the pitch by phi predicts every
normal of the image turned by phi about x:

    y' = y cos phi - z sin phi,    z' = y sin phi + z cos phi

For each image (its mask's pixels) this searches phi in whole degrees over [-MAX_DEG, MAX_DEG] for the
smallest mean angular error, and prints per group (scene kind, and the camera's pitch from the render's
meta, in PITCH_BINS) the images, the mean error as predicted and at each image's best phi, and the best
phi's mean with its 95 % t-interval over images. ``--fixed`` turns every image by one angle instead: what a
constant correction would buy. A phi whose interval excludes 0 is a tilt the model makes, not noise.
Nothing is written.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
from pathlib import Path

import torch
import torch.nn.functional as F

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pilight.data.predictions import read_predictions  # noqa: E402
from pilight.data.schema import DataError  # noqa: E402
from pilight.data.shard_reader import intrinsics_dataset, make_loader  # noqa: E402
from pilight.seeds import t_quantile  # noqa: E402

MAX_DEG = 40
PITCH_BINS = ((-90.0, -15.0), (-15.0, -5.0), (-5.0, 90.0))  # degrees, the camera looking down is negative


def turned(normal: torch.Tensor, phi_deg: float) -> torch.Tensor:
    """Normals (3, ...) turned by ``phi_deg`` about the camera's x axis (module docstring)."""
    c, s = math.cos(math.radians(phi_deg)), math.sin(math.radians(phi_deg))
    return torch.stack([normal[0], normal[1] * c - normal[2] * s, normal[1] * s + normal[2] * c])


def mean_angle(pred: torch.Tensor, gt: torch.Tensor) -> float:
    """Mean angle in degrees between unit normals (3, N)."""
    return float(torch.rad2deg(torch.acos((pred * gt).sum(0).clamp(-1, 1))).mean())


def best_turn(pred: torch.Tensor, gt: torch.Tensor, angles) -> tuple[float, float]:
    """(phi in degrees, mean error there) of the angle in ``angles`` that best aligns ``pred`` to ``gt``."""
    return min(((float(a), mean_angle(turned(pred, a), gt)) for a in angles), key=lambda x: x[1])


def camera_pitch(meta: dict) -> float:
    """Degrees the camera looks above the horizon (negative: down); Blender's camera looks down its -z."""
    return math.degrees(math.asin(-meta["camera"]["world_from_camera"][2][2]))


def per_image(pred_dir: Path, shards: Path, split: str, fixed: float | None) -> list[dict]:
    preds = read_predictions(pred_dir, split)
    angles = [fixed] if fixed is not None else range(-MAX_DEG, MAX_DEG + 1)
    rows = []
    for b in make_loader(intrinsics_dataset(shards, split, shuffle=False), 8):
        for i, key in enumerate(b["key"]):
            if key not in preds:
                raise DataError(f"{pred_dir}: no `{split}` prediction for {key}; rerun infer_intrinsics")
            m = b["mask"][i, 0] > 0.5
            if int(m.sum()) == 0:
                continue
            pred = F.normalize(torch.from_numpy(preds[key]["normal"]).permute(2, 0, 1).float(), dim=0)[:, m]
            gt = F.normalize(b["normal"][i].float(), dim=0)[:, m]
            phi, err = best_turn(pred, gt, angles)
            meta = json.loads(b["meta"][i])
            rows.append(
                {
                    "kind": meta["kind"],
                    "pitch": camera_pitch(meta),
                    "error": mean_angle(pred, gt),
                    "turned_error": err,
                    "phi": phi,
                }
            )
    if not rows:
        raise DataError(f"{shards}: the {split} split has no masked images")
    return rows


def interval(xs: list[float]) -> str:
    if len(xs) < 2:
        return f"{xs[0]:+.1f}" if xs else "n/a"
    m, sd = statistics.mean(xs), statistics.stdev(xs)
    half = t_quantile(len(xs) - 1) * sd / math.sqrt(len(xs))
    return f"{m:+.1f} [{m - half:+.1f}, {m + half:+.1f}]"


def table(rows: list[dict], fixed: float | None) -> str:
    groups: dict[str, list[dict]] = {"all": rows}
    for r in rows:
        groups.setdefault(f"kind {r['kind']}", []).append(r)
        lo, hi = next(b for b in PITCH_BINS if b[0] <= r["pitch"] < b[1])
        groups.setdefault(f"pitch [{lo:g}, {hi:g})", []).append(r)
    turn = f"turned by {fixed:+g}°" if fixed is not None else "at each image's best turn"
    lines = [
        f"| images | n | camera pitch (°) | normals mean error (°) | {turn} | best turn φ (°), 95 % t |",
        "|---|---|---|---|---|---|",
    ]
    for name, rs in groups.items():
        mean = lambda k, rs=rs: statistics.mean(r[k] for r in rs)
        lines.append(
            f"| {name} | {len(rs)} | {mean('pitch'):+.1f} | {mean('error'):.2f} | {mean('turned_error'):.2f} "
            f"| {interval([r['phi'] for r in rs]) if fixed is None else 'fixed'} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--pred", type=Path, default=Path("data/intrinsics_pred"))
    ap.add_argument("--shards", type=Path, default=Path("data/shards"))
    ap.add_argument("--split", default="test")
    ap.add_argument("--fixed", type=float, default=None, help="turn every image by this many degrees")
    args = ap.parse_args(argv)
    rows = per_image(args.pred, args.shards, args.split, args.fixed)
    print(f"{args.pred} on {args.shards} ({args.split}), {len(rows)} images")
    print(table(rows, args.fixed))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
