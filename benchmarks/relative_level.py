"""The relative tier's level: how much of the model's loss there is the level, and can a level rule fix it?

    python benchmarks/relative_level.py                      # data/shards, data/relit (the default's run)
    python benchmarks/relative_level.py --shards base/data/shards --relit base/data/relit

In the relative tier (docs: evaluate, "Relighting in three tiers") the model is told r = level(ball_b) /
level(ball_a) and sets the target light's level from its own estimate of the input's light
(pilight.physics.source_light); the exposure-matched copy I_a x r needs no estimate. This rescales each
relit image of the relative splits (``<split>``: stage-1 conditions, ``<split>_gt``: ground-truth ones)
to a level between its own and the copy's, in log space:

    I_w = I_relit x g^w,    g = r Y(I_a) / Y(I_relit)     (Y: mean Rec. 709 luminance on the mask)

w = 0 is the model as the evaluate stage grades it, w = 1 the copy's level with the model's structure
(what the photo API's ``exposure: photo`` does at k = 1, pilight.relight.intensity.exposure_gain). Each
row: PSNR, SSIM, change_r2 on the mask and the level sd (linear HDR), on the cross-light pairs, scored
by the tiers' own MethodScores, beside the exposure-matched copy. Nothing is written.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pilight.data.predictions import read_predictions  # noqa: E402
from pilight.data.schema import DataError  # noqa: E402
from pilight.data.shard_reader import eval_dataset, make_loader  # noqa: E402
from pilight.eval.relight_tiers import MethodScores, Pairs, exposure_matched_copy, intensity_ratio  # noqa: E402
from pilight.relight.intensity import mean_luminance  # noqa: E402

WEIGHTS = (0.0, 0.25, 0.5, 0.75, 1.0)
SUFFIXES = {"": "model, stage-1 conditions", "_gt": "model, ground-truth conditions"}


def toward_level(relit: torch.Tensor, image_a: torch.Tensor, mask: torch.Tensor, r: torch.Tensor, w: float):
    """``relit`` (B, 3, H, W) moved a share ``w`` of the way (in log level) to the exposure-matched level
    r x Y(image_a), Y being the mean luminance on ``mask``; r is (B,)."""
    g = r * mean_luminance(image_a.float(), mask) / mean_luminance(relit.float(), mask).clamp_min(1e-12)
    return relit * (g**w).view(-1, 1, 1, 1).to(relit.dtype)


def study(shards: Path, relit: Path, split: str, weights=WEIGHTS) -> dict[str, dict]:
    """{row name: figures} over the cross-light pairs of ``split`` (module docstring)."""
    written = set(json.loads((relit / "index.json").read_text())["splits"])
    preds = {sfx: read_predictions(relit, split + sfx) for sfx in SUFFIXES if split + sfx in written}
    if "" not in preds:
        raise DataError(f"{relit}: no `{split}` split (the relight stage's relative-mode model); rerun it")
    scores: dict[str, MethodScores] = {}
    for b in make_loader(eval_dataset(shards, split, "relight"), 8):
        cross = [json.loads(a)["light"] != json.loads(c)["light"] for a, c in zip(b["meta_a"], b["meta_b"])]
        sel = torch.tensor(cross)
        if not sel.any():
            continue
        keys = [k for k, c in zip(b["key"], cross) if c]
        image_a, ball_a, ball_b, mask = (b[k][sel] for k in ("image_a", "ball_a", "ball_b", "mask"))
        pairs = Pairs.of(image_a, b["image_b"][sel], mask, torch.ones(len(keys), dtype=torch.bool))
        r = intensity_ratio(ball_a, ball_b).flatten()
        rows = {"exposure-matched copy (input x r)": exposure_matched_copy(image_a, ball_a, ball_b)}
        for sfx, p in preds.items():
            missing = [k for k in keys if k not in p]
            if missing:
                raise DataError(f"{relit}: no `{split}{sfx}` prediction for {missing[:3]}; rerun the relight stage")
            img = torch.stack([torch.from_numpy(p[k]["relit"]).permute(2, 0, 1) for k in keys]).float()
            for w in weights:
                rows[f"{SUFFIXES[sfx]}, w = {w:g}"] = toward_level(img, image_a, mask, r, w)
        for name, img in rows.items():
            scores.setdefault(name, MethodScores()).update(img.float(), pairs)
    if not scores:
        raise DataError(f"{shards}: the {split} split has no cross-light pairs")
    return {name: s.compute() for name, s in scores.items()}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--shards", type=Path, default=Path("data/shards"))
    ap.add_argument("--relit", type=Path, default=Path("data/relit"))
    ap.add_argument("--split", default="test")
    args = ap.parse_args(argv)
    figures = study(args.shards, args.relit, args.split)
    print(f"relative tier, {args.split} split, {next(iter(figures.values()))['pairs']} cross-light pairs")
    print("| level | PSNR (dB) | SSIM | change_r2 mask | level sd |")
    print("|---|---|---|---|---|")
    for name, f in figures.items():
        print(f"| {name} | {f['psnr']:.2f} | {f['ssim']:.3f} | {f['change_r2_mask']:.3f} | {f['level_sd']:.3f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
