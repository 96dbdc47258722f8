"""Ceilings of candidate relit-output forms, computed from ground-truth maps (no model).

    python benchmarks/oracle_relight.py [--shards data/shards] [--pred data/intrinsics_pred] [--split test]
    python benchmarks/oracle_relight.py --per-map      # + one stage-1 map at a time, ground truth for the rest
    python benchmarks/oracle_relight.py --tiers        # the default form's anchor and ceiling in the three tiers

For every cross-light pair of the split, each candidate forms I_hat_b on the mask from physics and
(some) ground truth, and copies the input off the mask. Printed per candidate: change_r2 on the full
image and on the mask (pilight.eval.light_following), and relight PSNR / SSIM (the evaluation's
tone-mapped space), beside "copy the input". With --pred, the same candidates with the conditions
(albedo, normal, roughness, metallic) taken from stage-1 predictions: what stage-1 errors cost each
form. --per-map adds one setting per map, "pred <map>": that map from stage 1 and the others from the
ground truth, so the gap between the two settings is split by the map that opens it. It also adds
"pred, albedo at GT level" and "pred albedo at GT level": the stage-1 albedo rescaled per image and
channel to the ground truth's mean on the mask (what the albedo's level costs, apart from its pattern).

--tiers grades the default form (physics-first, effective albedo with the SH-estimated source light,
cell-smoothed lookups, GGX specular) as the evaluation's tiers do (pilight.eval.relight_tiers): its
anchor (zero gains) and its ceiling (perfect cell gains) with the target ball as rendered (absolute)
and relative to the input's estimated light (relative, told r = level(ball_b)/level(ball_a)), each
scored raw and after its least-squares scale on the mask (scale-invariant), beside copying the input,
the exposure-matched copy (input x r) and the copy x s*. What the relative tier gains over the
absolute one is the level; what remains to the ceiling is structure.

Candidates (A, N, m: the conditions; D, S: the target light's ground truth; "cell" = what a
perfect network at one value per 4x4 codec cell would output):
  A D_calc, + S_calc, + F S_calc  Lambertian lookup of the target ball; + the specular lookup of
                                  (gray - Lambertian ball); + the crude metal Fresnel (physics.calculated)
  A D_calc + S, A D + F S_calc    the true specular / the true diffuse shading
  A D_calc + S_ggx, A D + S_ggx   the microfacet specular of the target ball's dominant light with the
                                  conditions' roughness and Fresnel (pilight.physics.specular_model)
  A cell(D) + cell(S), A D + cell(S)   display-space gains on D_calc and F S_calc, cell resolution
  I_a cell(G)                     the display-space gain on the input at cell resolution (relit_target gain)
  PF <albedo>[, smoothed]: ...    the physics-first form (pilight.relight.physics_first): I = A_x D + S,
                                  D and S as gains g_D, g_S on D_calc and S_calc. anchor = zero gains
                                  (physics alone); cell g_D, cell g_S = perfect gains at cell resolution.
                                  A_x: effective (the input's own ball), effective with the ball estimated
                                  from the input by an SH fit (pilight.physics.source_light: what a photo
                                  gets), or the conditioning albedo. smoothed: lookups cell-smoothed.
                                  GGX S: S_calc (and S_calc_a) from pilight.physics.specular_model.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

from pilight.data import schema
from pilight.data.colour import tonemap01
from pilight.data.shard_reader import eval_dataset, make_loader
from pilight.diffusion.codec import cell_mean, cell_smooth
from pilight.eval.light_following import ChangeR2, cross_light
from pilight.eval.metrics import psnr_per_image, ssim_per_image
from pilight.eval.scale_invariant import scaled_to
from pilight.params import DOMAINS
from pilight.physics.calculated import diffuse_calculated, specular_calculated
from pilight.physics.source_light import estimate_source_ball
from pilight.physics.specular_model import specular_from_ball
from pilight.relight.conditions import optional_predictions, oracle_conditions
from pilight.relight.encoding import gain_decode, gain_encode
from pilight.relight.physics_first import anchors, compose_relit, diffuse_target, gain_of

CELL = 4


def cell_gain(truth: torch.Tensor, anchor: torch.Tensor) -> torch.Tensor:
    """truth as a cell-resolution display-space gain on anchor, decoded (linear HDR)."""
    tm = lambda x: schema.to_model("image", x.float())
    g = cell_smooth(cell_mean(gain_encode(tm(truth), tm(anchor)), CELL), CELL)
    return schema.from_model("image", gain_decode(g, tm(anchor)))


def candidates(b: dict, c: dict) -> dict[str, torch.Tensor]:
    """Linear-HDR relit image on the mask for each candidate; c: the conditions."""
    A, N, m, mask = c["albedo"], c["normal"], c["metallic"], b["mask"]
    lamb = b.get("ball_lambertian_b", b["ball_b"])
    d_calc = diffuse_calculated(b["ball_b"], N, mask, m)
    s_raw = specular_calculated(b["ball_b"], lamb, N, mask, A, torch.zeros_like(m))
    s_f = specular_calculated(b["ball_b"], lamb, N, mask, A, m)
    D, S, I_a = b["diffuse_b"].float(), b["specular_b"].float(), b["image_a"].float()
    s_ggx = specular_from_ball(lamb, N, c["roughness"], A, m) * mask
    out = {
        "A D_calc": A * d_calc,
        "A D_calc + S_calc": A * d_calc + s_raw,
        "A D_calc + F S_calc": A * d_calc + s_f,
        "A D_calc + S_ggx": A * d_calc + s_ggx,
        "A D_calc + S": A * d_calc + S,
        "A D + F S_calc": A * D + s_f,
        "A D + S_ggx": A * D + s_ggx,
        "A cell(D) + cell(S)": A * cell_gain(D, d_calc) + cell_gain(S, s_f),
        "A D + cell(S)": A * D + cell_gain(S, s_f),
        "I_a cell(G)": cell_gain(b["image_b"].float(), I_a),
    }
    zero = torch.zeros_like(I_a)
    cs = lambda g: cell_smooth(cell_mean(g, CELL), CELL)
    sources = {
        "effective": (b["ball_a"], b.get("ball_lambertian_a")),
        "effective, SH source": (estimate_source_ball(I_a, A, N, mask, b["ball_a"].shape[-1], m), None),
        "conditioning": (None, None),
    }
    settings = [(name, smooth, "lookup") for name in sources for smooth in (1, CELL)]
    settings += [(name, CELL, "ggx") for name in sources]
    for name, smooth, spec in settings:
        ball_a, lamb_a = sources[name]
        anc = anchors(
            I_a,
            c,
            mask,
            b["ball_b"],
            b.get("ball_lambertian_b"),
            ball_a=ball_a,
            lambertian_a=lamb_a,
            albedo_source="conditioning" if name == "conditioning" else "effective",
            smooth_cell=smooth,
            specular=spec,
        )
        tag = f"PF {name}{', smoothed' if smooth > 1 else ''}{', GGX S' if spec == 'ggx' else ''}"
        g_d = gain_of(diffuse_target(b["image_b"], S, anc.albedo), anc.d_calc, anc.eps)
        g_s = gain_of(S, anc.s_calc, anc.eps)
        out[f"{tag}: anchor"] = compose_relit(anc, zero, zero)["relit"]
        out[f"{tag}: cell g_D, cell g_S"] = compose_relit(anc, cs(g_d), cs(g_s))["relit"]
        if smooth > 1 and name.startswith("effective"):
            out[f"{tag}: cell g_D, g_S = 0"] = compose_relit(anc, cs(g_d), zero)["relit"]
            out[f"{tag}: g_D = 0, cell g_S"] = compose_relit(anc, zero, cs(g_s))["relit"]
    return out


def tier_forms(b: dict, c: dict, sources: tuple | None = None) -> dict[str, dict[str, torch.Tensor]]:
    """{tier: {name: linear relit}} for --tiers (module docstring); the scale-invariant tier's images are
    the absolute ones, scaled when scored. ``sources``: ((shading ball, found), (level ball, found)) of
    light a, default the pipeline's estimates (pf.source_balls; benchmarks/source_light_level.py varies them)."""
    from pilight.eval.relight_tiers import exposure_matched_copy
    from pilight.relight import physics_first as pf
    from pilight.relight.intensity import relative_pair, to_source_level

    I_a, S, mask = b["image_a"].float(), b["specular_b"].float(), b["mask"]
    if sources is None:
        size = b["ball_b"].shape[-1]
        sources = (pf.source_balls(I_a, c, mask, size), pf.source_balls(I_a, c, mask, size, level=True))
    source, level_source = sources
    cs = lambda g: cell_smooth(cell_mean(g, CELL), CELL)
    zero = torch.zeros_like(I_a)
    out = {"absolute": {"copy the input": I_a}, "relative": {"copy the input": I_a}}
    out["relative"]["exposure-matched copy (input x r)"] = exposure_matched_copy(I_a, b["ball_a"], b["ball_b"])
    for tier in ("absolute", "relative"):
        balls = {k: b[k] for k in ("ball_b", "ball_lambertian_b") if k in b}
        if tier == "relative":
            balls = to_source_level({k: relative_pair(b)[k] for k in balls}, *level_source)
        anc = pf.anchors(
            I_a,
            c,
            mask,
            balls["ball_b"],
            balls.get("ball_lambertian_b"),
            ball_a=source[0],
            found=source[1],
            smooth_cell=CELL,
            specular="ggx",
        )
        g_d = pf.gain_of(pf.diffuse_target(b["image_b"], S, anc.albedo), anc.d_calc, anc.eps)
        g_s = pf.gain_of(S, anc.s_calc, anc.eps)
        out[tier]["anchor (zero gains)"] = pf.compose_relit(anc, zero, zero)["relit"]
        out[tier]["ceiling (perfect cell gains)"] = pf.compose_relit(anc, cs(g_d), cs(g_s))["relit"]
    out["scale_invariant"] = {k: v for k, v in out["absolute"].items()}
    return out


class RelitScores:
    """change_r2 (full image and mask), PSNR and SSIM of relit images, tone-mapped as the evaluation does,
    accumulated per key over cross-light batches (also used by benchmarks/source_light_level.py)."""

    def __init__(self):
        self.scores: dict = {}

    def add(self, key, img: torch.Tensor, b: dict) -> None:
        r = self.scores.setdefault(key, {"r2": ChangeR2(), "psnr": [], "ssim": []})
        u, u_gt = tonemap01(img), tonemap01(b["image_b"])
        r["r2"].update(u, u_gt, tonemap01(b["image_a"]), b["mask"])
        r["psnr"].append(psnr_per_image(u, u_gt))
        r["ssim"].append(ssim_per_image(u, u_gt))

    def row(self, key) -> dict[str, float]:
        r = self.scores[key]
        r2 = r["r2"].compute()
        return {
            "change_r2_full": r2["full"],
            "change_r2_mask": r2["mask"],
            "psnr": float(torch.cat(r["psnr"]).mean()),
            "ssim": float(torch.cat(r["ssim"]).mean()),
        }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--shards", type=Path, default=Path("data/shards"))
    ap.add_argument("--pred", type=Path, default=Path("data/intrinsics_pred"))
    ap.add_argument("--split", default="test")
    ap.add_argument("--json", type=Path, default=None, help="also write the table as JSON")
    ap.add_argument("--per-map", action="store_true", help="also one stage-1 map at a time (needs --pred)")
    ap.add_argument("--tiers", action="store_true", help="only the default form, in the three tiers")
    args = ap.parse_args(argv)
    preds = optional_predictions(args.shards, args.pred, args.split, "oracle") if args.pred else None
    if args.per_map and preds is None:
        ap.error(f"--per-map needs stage-1 predictions, and none were found under --pred {args.pred}")
    # name -> (predictions or None for ground truth, oracle_conditions()'s options)
    settings = {"gt": (None, {})} | ({"pred": (preds, {})} if preds is not None else {})
    if args.per_map:
        settings |= {f"pred {d}": (preds, {"only": d}) for d in DOMAINS}
        settings["pred, albedo at GT level"] = (preds, {"at_gt_level": True})
        settings["pred albedo at GT level"] = (preds, {"only": "albedo", "at_gt_level": True})
    scores = RelitScores()
    names: dict[str, list[str]] = {s: [] for s in settings}
    pairs = 0
    for b in make_loader(eval_dataset(args.shards, args.split, "relight"), 8):
        b = cross_light(b)
        if b is None:
            continue
        pairs += b["image_a"].shape[0]
        mask = b["mask"]
        for setting, (p, options) in settings.items():
            c = oracle_conditions(b, p, **options)
            if args.tiers:
                forms = {
                    f"{tier}: {k}": scaled_to(v, b["image_b"].float(), mask) if tier == "scale_invariant" else v
                    for tier, fs in tier_forms(b, c).items()
                    for k, v in fs.items()
                }
            else:
                forms = {"copy the input": b["image_a"].float()} | candidates(b, c)
            for name, img in forms.items():
                scores.add((setting, name), torch.where(mask > 0.5, img, b["image_a"].float()), b)
                if name not in names[setting]:
                    names[setting].append(name)
    table = {}
    for setting, rows in names.items():
        print(f"\n{args.split}: {pairs} cross-light pairs, conditions {setting}")
        print(f"{'candidate':44s} {'r2 full':>8s} {'r2 mask':>8s} {'PSNR':>7s} {'SSIM':>6s}")
        for name in rows:
            row = scores.row((setting, name))
            table.setdefault(setting, {})[name] = row
            print(
                f"{name:44s} {row['change_r2_full']:8.3f} {row['change_r2_mask']:8.3f} {row['psnr']:7.2f} {row['ssim']:6.3f}"
            )
    if args.json:
        args.json.write_text(json.dumps({"pairs": pairs, "split": args.split, "oracles": table}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
