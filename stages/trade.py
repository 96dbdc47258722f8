"""DVC stage `trade`: the speed/accuracy trade of sampling, for both stages, and a relit-under-
several-lights grid.

    python stages/trade.py

Sweeps steps x spacing, single-step, CFG and ensemble size one factor at a time around
`infer_intrinsics` (stage 1) and `relight_infer` (stage 2) on the first `evaluate.trade.images`
test images / pairs (see pilight/eval/trade.py).  Writes

- metrics/trade.json                  every point (dvc metrics), seconds per image and accuracy;
- plots/trade_intrinsics.json, plots/trade_relight.json and their *_pareto*.json fronts (dvc plots);
- reports/trade.md, reports/trade_intrinsics.png, reports/trade_relight.png;
- reports/relit_lights.png: RELIT_LIGHTS_ROWS test views (the first cross-light pair of each), one row each, relit under
  `evaluate.relight_lights` analytic lights swept around them, each column's ball above it
  (pilight/eval/relit_lights.py).

Timings vary between runs, so this stage is not byte-deterministic; the accuracy columns are.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pilight import atomic  # noqa: E402
from pilight.params import ParamsError, load_section  # noqa: E402

INTRINSICS_METRICS = {"albedo_psnr": ("albedo PSNR (dB) ↑", True), "normal_mean_deg": ("normal mean error (°) ↓", False),
                      "roughness_mae": ("roughness MAE ↓", False), "metallic_mae": ("metallic MAE ↓", False)}
RELIGHT_METRICS = {"relit_psnr": ("relit PSNR (dB) ↑", True), "relit_ssim": ("relit SSIM ↑", True)}


def first_n(loader, n: int, keep=lambda batch, i: True) -> dict:
    """The first n samples of a loader (optionally filtered), stacked into one batch dict."""
    import torch

    rows: dict[str, list] = {}
    count = 0
    for batch in loader:
        for i in range(len(batch["key"])):
            if count < n and keep(batch, i):
                for k, v in batch.items():
                    rows.setdefault(k, []).append(v[i])
                count += 1
        if count >= n:
            break
    if count == 0:
        return {}
    return {k: torch.stack(v) if hasattr(v[0], "shape") else list(v) for k, v in rows.items()}


def chunks(batch: dict, size: int):
    n = len(batch["key"])
    for s in range(0, n, size):
        yield {k: v[s:s + size] for k, v in batch.items()}


RELIT_LIGHTS_ROWS = 4


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--params", default="params.yaml")
    ap.add_argument("--shards", type=Path, default=Path("data/shards"))
    ap.add_argument("--pred", type=Path, default=Path("data/intrinsics_pred"))
    ap.add_argument("--intrinsics-model", type=Path, default=Path("models/intrinsics"))
    ap.add_argument("--relight-model", type=Path, default=Path("models/relight"))
    ap.add_argument("--metrics", type=Path, default=Path("metrics/trade.json"))
    ap.add_argument("--plots", type=Path, default=Path("plots"))
    ap.add_argument("--reports", type=Path, default=Path("reports"))
    args = ap.parse_args(argv)
    try:
        base = load_section("base", args.params)
        p1, ip1 = load_section("intrinsics", args.params), load_section("infer_intrinsics", args.params)
        p2, ip2 = load_section("relight", args.params), load_section("relight_infer", args.params)
        ev = load_section("evaluate", args.params)
    except ParamsError as exc:
        print(f"trade: {exc}", file=sys.stderr)
        return 2
    import torch
    from tqdm import tqdm

    from pilight.data.schema import DataError
    from pilight.data.shards import eval_dataset, make_loader
    from pilight.eval import trade
    from pilight.eval.metrics import angular_errors, masked_mae, masked_psnr, psnr_per_image, ssim_per_image
    from pilight.eval.relight import tonemap01
    from pilight.eval.relit_lights import relit_lights_grid
    from pilight.train.build import ModelError, load_model
    from pilight.train.intrinsics import IntrinsicsTask
    from pilight.relight.conditions import choose_intrinsics, optional_predictions
    from pilight.train.relight import RelightTask

    tp, split = ev.trade, ip2.split
    try:
        t1 = IntrinsicsTask(p1, args.shards, seed=base.seed)
        load_model(t1.stack, args.intrinsics_model)
        t2 = RelightTask(p2.model_copy(update={"conditions": "gt"}), args.shards, seed=base.seed)
        load_model(t2.stack, args.relight_model)
        imgs = first_n(make_loader(eval_dataset(args.shards, "test", "intrinsics"), 8), tp.images)
        cross = lambda b, i: json.loads(b["meta_a"][i])["light"] != json.loads(b["meta_b"][i])["light"]
        pairs = first_n(make_loader(eval_dataset(args.shards, split, "relight"), 8), tp.images, cross)
        if not imgs or not pairs:
            raise DataError(f"{args.shards}: no test images or no cross-light {split} pairs to sweep")
        preds = optional_predictions(args.shards, args.pred, split, "trade")
    except (DataError, ModelError, FileNotFoundError, ValueError) as exc:
        print(f"trade: {exc}", file=sys.stderr)
        return 1
    t1.stack.model.eval()
    t2.stack.model.eval()
    n1, n2 = len(imgs["key"]), len(pairs["key"])
    intr = choose_intrinsics(pairs, torch.full((n2,), preds is not None), preds)

    def predict1(sp, gen):
        outs = [t1.predict(b["image"], ip1.domains, sp, gen) for b in chunks(imgs, ip1.batch_size)]
        return {d: torch.cat([o[d] for o in outs]) for d in ip1.domains}

    def score1(pred):
        m = imgs["mask"]
        s = {"albedo_psnr": masked_psnr(pred["albedo"], imgs["albedo"], m) if "albedo" in pred else None,
             "normal_mean_deg": float(angular_errors(pred["normal"], imgs["normal"], m).mean()) if "normal" in pred else None}
        s.update({f"{k}_mae": masked_mae(pred[k], imgs[k], m) if k in pred else None for k in ("roughness", "metallic")})
        return s

    def predict2(sp, gen):
        outs = []
        for s in range(0, n2, ip2.batch_size):
            sl = slice(s, s + ip2.batch_size)
            outs.append(t2.predict({k: v[sl] for k, v in pairs.items()}, sp, gen, {k: v[sl] for k, v in intr.items()}))
        return torch.cat([o["relit"] for o in outs])

    def score2(relit):
        p, g = tonemap01(relit), tonemap01(pairs["image_b"])
        return {"relit_psnr": float(psnr_per_image(p, g).mean()), "relit_ssim": float(ssim_per_image(p, g).mean())}

    s1 = trade.sweep_settings(ip1, tp, tp.intrinsics_cfg)
    s2 = trade.sweep_settings(ip2, tp, tp.relight_cfg)
    with tqdm(total=len(s1) + len(s2), desc="trade", unit="point") as bar:
        tick = lambda label: (bar.set_postfix_str(label), bar.update(0))
        rows1 = trade.run_sweep(s1, predict1, score1, n1, base.seed, tick)
        bar.update(len(s1))
        rows2 = trade.run_sweep(s2, predict2, score2, n2, base.seed, tick)
        bar.update(len(s2))
    trade.mark_fronts(rows1, {k: hi for k, (_, hi) in INTRINSICS_METRICS.items()})
    trade.mark_fronts(rows2, {k: hi for k, (_, hi) in RELIGHT_METRICS.items()})

    views: set[tuple] = set()

    def new_view(b, i):  # one row per test view: the first cross-light pair of each
        m = json.loads(b["meta_a"][i])
        if not cross(b, i) or (m["scene"], m["view"]) in views:
            return False
        views.add((m["scene"], m["view"]))
        return True

    shown = first_n(make_loader(eval_dataset(args.shards, split, "relight"), 8), RELIT_LIGHTS_ROWS, new_view)
    shown_intr = choose_intrinsics(shown, torch.full((len(shown["key"]),), preds is not None), preds)
    grid = relit_lights_grid(lambda batch, c: t2.predict(batch, ip2, torch.Generator().manual_seed(base.seed), c),
                             [({k: v[i:i + 1] for k, v in shown.items()}, {k: v[i:i + 1] for k, v in shown_intr.items()})
                              for i in range(len(shown["key"]))], ev.relight_lights)

    for d in (args.metrics.parent, args.plots, args.reports):
        d.mkdir(parents=True, exist_ok=True)
    conditions = "stage-1 predictions" if preds is not None else "ground-truth intrinsics"
    result = {"intrinsics": {"images": n1, "points": rows1}, "relight": {"pairs": n2, "conditions": conditions, "points": rows2}}
    atomic.write_json(args.metrics, result)
    for name, rows, metrics in (("intrinsics", rows1, INTRINSICS_METRICS), ("relight", rows2, RELIGHT_METRICS)):
        atomic.write_json(args.plots / f"trade_{name}.json", rows)
        for key in metrics:
            front = sorted((r for r in rows if r.get(f"pareto_{key}")), key=lambda r: r["seconds_per_image"])
            atomic.write_json(args.plots / f"trade_{name}_pareto_{key}.json", front)
        trade.plot_png(rows, metrics, args.reports / f"trade_{name}.png",
                       f"{'Stage 1' if name == 'intrinsics' else 'Stage 2'}: seconds per image vs accuracy "
                       f"({n1 if name == 'intrinsics' else n2} test {'images' if name == 'intrinsics' else 'pairs'})")
    md = (trade.markdown_table(rows1, {k: v for k, (v, _) in INTRINSICS_METRICS.items()},
                               f"Stage 1 speed/accuracy trade ({n1} test images, around `infer_intrinsics`)")
          + "\n" + trade.markdown_table(rows2, {k: v for k, (v, _) in RELIGHT_METRICS.items()},
                                        f"Stage 2 speed/accuracy trade ({n2} cross-light test pairs, conditions: "
                                        f"{conditions}, around `relight_infer`)"))
    atomic.write_text(args.reports / "trade.md", md)
    atomic.write_png(args.reports / "relit_lights.png", grid)
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
