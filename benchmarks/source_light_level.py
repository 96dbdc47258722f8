"""Which fit of the input's light should set a relative light's level, and what limits it? The physics anchor, five ways.

    python benchmarks/source_light_level.py [--shards data/shards] [--pred data/intrinsics_pred] [--split test]
                                            [--batches N] [--json FILE]

Physics-first relighting estimates the input's own light from the input and its intrinsics
(pilight.physics.source_light) for two things: the SHADING at the image's normals (inside the
effective albedo) and the LEVEL (the estimated ball's mean, which scales a relative light;
pilight.relight.intensity). For every cross-light pair of the split, the default form's anchor (zero
gains: effective albedo, cell-smoothed lookups, GGX specular) is formed with the light estimated by:

  nine terms         second-order SH for both (the pipeline until 2026-12-06)
  first order        first-order SH with the level's ridge for both
  split (pipeline)   nine terms for the shading, first order for the level (pf.source_balls)
  rendered ball_a    the shards' own ball of light a for both (what no photo has)
  split, true albedo the split with the ground-truth albedo in the fit and only there (the other
                     maps, and the albedo the anchor uses elsewhere, are the conditions'): what a
                     perfect stage-1 albedo would give the light estimate

each scored in the three tiers of the evaluation (absolute: the target ball as rendered; relative:
told r = level(ball_b) / level(ball_a) and scaled to the estimated level; scale-invariant: the
absolute image at its best scale on the mask), with ground-truth and stage-1 conditions. Printed:
change_r2 on the mask, PSNR and SSIM (tone-mapped), as oracle_relight.py scores them. No model.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.oracle_relight import RelitScores, tier_forms  # noqa: E402
from pilight.data.shard_reader import eval_dataset, make_loader
from pilight.eval.light_following import cross_light
from pilight.eval.scale_invariant import scaled_to
from pilight.relight import physics_first as pf
from pilight.relight.conditions import optional_predictions, oracle_conditions

TIERS = ("absolute", "relative", "scale_invariant")
FITS = ("nine terms", "first order", "split (pipeline)", "rendered ball_a", "split, true albedo")


def estimates(b: dict, c: dict) -> dict[str, tuple[tuple, tuple]]:
    """{name: ((shading ball, found), (level ball, found))}."""
    I_a, mask, size = b["image_a"].float(), b["mask"], b["ball_b"].shape[-1]
    nine = pf.source_balls(I_a, c, mask, size)
    first = pf.source_balls(I_a, c, mask, size, level=True)
    rendered = (b["ball_a"], torch.ones(I_a.shape[0], dtype=torch.bool))
    if torch.equal(c["albedo"], b["albedo"]):  # ground-truth conditions: the same two fits
        nine_true, first_true = nine, first
    else:
        true_albedo = dict(c, albedo=b["albedo"])
        nine_true = pf.source_balls(I_a, true_albedo, mask, size)
        first_true = pf.source_balls(I_a, true_albedo, mask, size, level=True)
    return {
        "nine terms": (nine, nine),
        "first order": (first, first),
        "split (pipeline)": (nine, first),
        "rendered ball_a": (rendered, rendered),
        "split, true albedo": (nine_true, first_true),
    }


def anchor_images(b: dict, c: dict, shading: tuple, level: tuple) -> dict[str, torch.Tensor]:
    """{tier: the anchor's linear relit image, the input off the mask} (oracle_relight.tier_forms)."""
    forms = tier_forms(b, c, (shading, level))
    I_a, mask = b["image_a"].float(), b["mask"]
    out = {t: torch.where(mask > 0.5, forms[t]["anchor (zero gains)"], I_a) for t in ("absolute", "relative")}
    out["scale_invariant"] = torch.where(mask > 0.5, scaled_to(out["absolute"], b["image_b"].float(), mask), I_a)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--shards", type=Path, default=Path("data/shards"))
    ap.add_argument("--pred", type=Path, default=Path("data/intrinsics_pred"))
    ap.add_argument("--split", default="test")
    ap.add_argument("--batches", type=int, default=None, help="only the first N batches of 8 (a train split)")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    preds = optional_predictions(args.shards, args.pred, args.split, "source_light_level")
    settings = {"gt": None} | ({"pred": preds} if preds is not None else {})
    scores = RelitScores()
    pairs = 0
    for i, b in enumerate(make_loader(eval_dataset(args.shards, args.split, "relight"), 8)):
        if args.batches is not None and i >= args.batches:
            break
        b = cross_light(b)
        if b is None:
            continue
        pairs += b["image_a"].shape[0]
        for setting, p in settings.items():
            c = oracle_conditions(b, p)
            for name, (shading, level) in estimates(b, c).items():
                for tier, img in anchor_images(b, c, shading, level).items():
                    scores.add((setting, tier, name), img, b)
    table: dict = {}
    print(f"{args.split}: {pairs} cross-light pairs; the physics anchor (zero gains) with each fit of light a")
    print(f"{'conditions':10s} {'tier':16s} {'fit':20s} {'r2 mask':>8s} {'PSNR':>7s} {'SSIM':>6s}")
    for setting in settings:
        for tier in TIERS:
            for name in FITS:
                row = scores.row((setting, tier, name))
                table.setdefault(setting, {}).setdefault(tier, {})[name] = row
                print(
                    f"{setting:10s} {tier:16s} {name:20s} {row['change_r2_mask']:8.3f} {row['psnr']:7.2f} {row['ssim']:6.3f}"
                )
    if args.json:
        args.json.write_text(json.dumps({"pairs": pairs, "split": args.split, "anchors": table}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
