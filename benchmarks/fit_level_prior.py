"""Fit `relight.level_prior` on a split's inputs: the line through (log estimated level, log rendered level).

    python benchmarks/fit_level_prior.py --shards base/data/shards [--split train] [--pred <stage-1 predictions>]
                                         [--json FILE]

For every distinct input image of the split's relight pairs (scene, view, light), the input's light level is
estimated as relative intensity estimates it (the first-order fit, `pf.source_balls(..., level=True)`, from
the image and its ground-truth maps, or stage-1 maps with --pred) and set beside the level of the light
that rendered it (ball_a). Inputs whose light is not found are left out, as relative intensity leaves them
unscaled. Printed: the fit (pilight.relight.level_prior.fit_level_prior) and the params lines to paste.
Fit on the split stage 2 trains on, never on a split it is scored on.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pilight.data.shard_reader import eval_dataset, make_loader  # noqa: E402
from pilight.physics.envmap import light_level  # noqa: E402
from pilight.relight import physics_first as pf  # noqa: E402
from pilight.relight.conditions import optional_predictions, oracle_conditions  # noqa: E402
from pilight.relight.level_prior import fit_level_prior  # noqa: E402


def input_levels(shards: Path, split: str, pred: Path | None) -> tuple[np.ndarray, np.ndarray, int]:
    """(estimated, rendered) levels of the split's distinct inputs whose light was found, and how many were not."""
    preds = optional_predictions(shards, pred, split, "fit_level_prior") if pred else None
    seen: set[tuple] = set()
    est, rendered, lost = [], [], 0
    for batch in make_loader(eval_dataset(shards, split, "relight"), 8):
        intr = oracle_conditions(batch, preds)
        ball, found = pf.source_balls(batch["image_a"], intr, batch["mask"], batch["ball_b"].shape[-1], level=True)
        l_est, l_true = light_level(ball).flatten(), light_level(batch["ball_a"]).flatten()
        for i, meta in enumerate(batch["meta_a"]):
            m = json.loads(meta)
            key = (m["scene"], m["view"], m["light"])
            if key in seen:
                continue
            seen.add(key)
            if not bool(found[i]):
                lost += 1
                continue
            est.append(float(l_est[i]))
            rendered.append(float(l_true[i]))
    return np.array(est), np.array(rendered), lost


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--shards", type=Path, default=Path("data/shards"))
    ap.add_argument("--split", default="train")
    ap.add_argument("--pred", type=Path, default=None, help="stage-1 predictions as the maps (default: truth)")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    est, rendered, lost = input_levels(args.shards, args.split, args.pred)
    try:
        fit = fit_level_prior(est, rendered)
    except ValueError as exc:
        raise SystemExit(f"{args.shards} ({args.split}): {exc}") from None
    fit |= {"shards": str(args.shards), "split": args.split, "maps": "stage-1" if args.pred else "ground truth"}
    fit["not_found"] = lost
    print(
        f"{fit['inputs']} inputs ({lost} without a found light), {fit['maps']} maps: rms log error of the level "
        f"{fit['rms_log_error_before']:.3f} -> {fit['rms_log_error_after']:.3f}\n"
        f"relight:\n  level_prior: {{alpha: {fit['alpha']:.4f}, beta: {fit['beta']:.4f}}}"
    )
    if args.json:
        args.json.write_text(json.dumps(fit, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
