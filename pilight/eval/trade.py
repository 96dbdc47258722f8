"""The speed/accuracy trade of sampling: seconds per image against accuracy, Pareto front marked.

One factor at a time around the pipeline's own sampling params (``infer_intrinsics`` for stage 1,
``relight_infer`` for stage 2), so every point differs from the default in one thing:

- ``steps``:    DDIM with each count in ``evaluate.trade.steps``, for each spacing in ``spacings``
                (CFG and ensemble as in the infer params);
- ``mode``:     the trailing single-step estimate (one UNet call; exact under zero terminal SNR);
- ``cfg``:      each scale, at the infer params' mode and steps;
- ``ensemble``: each size, at the infer params' mode and steps.

A setting reached by two factors is measured once.  Every point samples the same first
``evaluate.trade.images`` test images (stage 2: test pairs with light a != light b) from the same
seed.  Seconds are wall-clock for the batched sampling calls only (no data loading), after one
warm-up call.  A point is on the Pareto front when no other point is at least as fast and at
least as accurate, and strictly better in one of the two.

The trade stage (stages/trade.py) takes the images and pairs with ``sweep_samples``, sweeps both stages
with ``sweep_both`` (``sweep_intrinsics`` / ``sweep_relight``) and writes everything with ``write_trade``.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from pilight import atomic
from pilight.params import SamplingParams, TradeParams

# {metric: (column title, higher is better)} of each stage's points
INTRINSICS_METRICS = {
    "albedo_psnr": ("albedo PSNR (dB) ↑", True),
    "normal_mean_deg": ("normal mean error (°) ↓", False),
    "roughness_mae": ("roughness MAE ↓", False),
    "metallic_mae": ("metallic MAE ↓", False),
}
RELIGHT_METRICS = {"relit_psnr": ("relit PSNR (dB) ↑", True), "relit_ssim": ("relit SSIM ↑", True)}


def sweep_settings(
    base: SamplingParams, tp: TradeParams, cfg_scales: tuple[float, ...]
) -> list[tuple[str, SamplingParams]]:
    """(factor, settings) in sweep order, without duplicates (first factor wins the label)."""
    out: list[tuple[str, SamplingParams]] = []
    seen: set[tuple] = set()

    def add(factor: str, **kw) -> None:
        sp = base.model_copy(update=kw)
        if sp.mode == "single_step":  # one UNet call at t = T - 1: steps and spacing mean nothing
            sp = sp.model_copy(update={"steps": 1, "timestep_spacing": "trailing"})
        key = (sp.mode, sp.steps, sp.timestep_spacing, sp.cfg_scale, sp.ensemble)
        if key not in seen:
            seen.add(key)
            out.append((factor, sp))

    for spacing in tp.spacings:
        for n in tp.steps:
            add("steps", mode="ddim", steps=n, timestep_spacing=spacing, ensemble=1)
    add("mode", mode="single_step", ensemble=1)
    for c in cfg_scales:
        add("cfg", cfg_scale=c, ensemble=1)
    for e in tp.ensemble:
        add("ensemble", ensemble=e)
    return out


def describe(sp: SamplingParams) -> str:
    how = "1-step" if sp.mode == "single_step" else f"DDIM {sp.steps} {sp.timestep_spacing}"
    return f"{how}, cfg {sp.cfg_scale:g}, ens {sp.ensemble}"


def pareto(points: list[dict], cost: str, accuracy: str, higher_is_better: bool) -> list[bool]:
    """True for points no other point dominates (cost lower is better); None accuracy is never on it."""
    sign = 1.0 if higher_is_better else -1.0
    vals = [(p[cost], sign * p[accuracy]) if p.get(accuracy) is not None else None for p in points]
    front = []
    for i, v in enumerate(vals):
        if v is None:
            front.append(False)
            continue
        dominated = any(
            w is not None and j != i and w[0] <= v[0] and w[1] >= v[1] and (w[0] < v[0] or w[1] > v[1])
            for j, w in enumerate(vals)
        )
        front.append(not dominated)
    return front


def run_sweep(
    settings: list[tuple[str, SamplingParams]],
    predict: Callable[[SamplingParams, torch.Generator], object],
    score: Callable[[object], dict[str, float | None]],
    count: int,
    seed: int,
    progress: Callable[[str | None], None] | None = None,
) -> list[dict]:
    """Time ``predict`` (one pass over the sweep's images) for each setting and score its output.
    ``progress`` hears each point's label before it runs and None once it is scored."""
    predict(
        settings[0][1].model_copy(update={"mode": "single_step", "ensemble": 1, "cfg_scale": 1.0}),
        torch.Generator().manual_seed(seed),
    )  # warm-up: first-call allocations are not any point's cost
    rows = []
    for factor, sp in settings:
        if progress is not None:
            progress(describe(sp))
        t0 = time.perf_counter()
        out = predict(sp, torch.Generator().manual_seed(seed))
        seconds = (time.perf_counter() - t0) / count
        rows.append(
            {
                "factor": factor,
                "label": describe(sp),
                "mode": sp.mode,
                "steps": sp.steps,
                "spacing": sp.timestep_spacing,
                "cfg": sp.cfg_scale,
                "ensemble": sp.ensemble,
                "seconds_per_image": seconds,
                **score(out),
            }
        )
        if progress is not None:
            progress(None)
    return rows


def mark_fronts(rows: list[dict], accuracies: dict[str, bool]) -> None:
    """Add ``pareto_<metric>`` to every row for each {metric: higher_is_better}."""
    for metric, higher in accuracies.items():
        for row, on in zip(rows, pareto(rows, "seconds_per_image", metric, higher)):
            row[f"pareto_{metric}"] = on


def markdown_table(rows: list[dict], metrics: dict[str, str], title: str) -> str:
    """``metrics``: {key: column title}; a * marks a point on that metric's Pareto front."""
    fmt = lambda v: "n/a" if v is None else f"{v:.3f}"
    head = "| factor | setting | s / image | " + " | ".join(metrics.values()) + " |"
    lines = [title, "", head, "|" + "---|" * (3 + len(metrics))]
    for r in rows:
        cells = [fmt(r.get(k)) + (" *" if r.get(f"pareto_{k}") else "") for k in metrics]
        lines.append(f"| {r['factor']} | {r['label']} | {r['seconds_per_image']:.3f} | " + " | ".join(cells) + " |")
    lines += [
        "",
        "`*`: on the Pareto front of that metric against seconds per image (no point is both at least as "
        "fast and at least as accurate).",
    ]
    return "\n".join(lines) + "\n"


def plot_png(rows: list[dict], metrics: dict[str, tuple[str, bool]], path, title: str) -> None:
    """One panel per metric: all points by factor, the Pareto front as a line (matplotlib, Agg)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(metrics), figsize=(5.2 * len(metrics), 4), squeeze=False)
    for ax, (key, (name, _higher)) in zip(axes[0], metrics.items()):
        if all(r.get(key) is None for r in rows):  # undefined at every point (e.g. an empty mask): said, not drawn
            ax.text(0.5, 0.5, "n/a: undefined at every point", ha="center", va="center", transform=ax.transAxes)
            ax.set_xlabel("seconds per image (log)")
            ax.set_ylabel(name)
            continue
        for factor in dict.fromkeys(r["factor"] for r in rows):
            pts = [r for r in rows if r["factor"] == factor and r.get(key) is not None]
            ax.scatter([r["seconds_per_image"] for r in pts], [r[key] for r in pts], label=factor, s=22)
        front = sorted((r for r in rows if r.get(f"pareto_{key}")), key=lambda r: r["seconds_per_image"])
        ax.plot([r["seconds_per_image"] for r in front], [r[key] for r in front], "k--", lw=1, label="Pareto front")
        for r in front:
            ax.annotate(
                r["label"], (r["seconds_per_image"], r[key]), fontsize=6, xytext=(3, 3), textcoords="offset points"
            )
        ax.set_xscale("log")
        ax.set_xlabel("seconds per image (log)")
        ax.set_ylabel(name)
        ax.grid(alpha=0.3)
    drawn = [ax for ax in axes[0] if ax.get_legend_handles_labels()[0]]
    if drawn:
        drawn[0].legend(fontsize=7)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    atomic.save_figure(fig, path, dpi=110, metadata={"Software": None})  # no version string: same data, same bytes
    plt.close(fig)


# --- the trade stage's samples and sweeps ------------------------------------------------------
def first_n(loader, n: int, keep=lambda batch, i: True) -> dict:
    """The first n samples of a loader (optionally filtered), stacked into one batch dict."""
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
        yield {k: v[s : s + size] for k, v in batch.items()}


def is_cross_light(batch: dict, i: int) -> bool:
    """Pair i of a pairs batch is lit differently in its input and its target."""
    return json.loads(batch["meta_a"][i])["light"] != json.loads(batch["meta_b"][i])["light"]


def sweep_intrinsics(task, imgs: dict, ip, tp: TradeParams, seed: int, progress=None) -> list[dict]:
    """Stage 1's points around ``ip`` (infer_intrinsics) on the images ``imgs``; ``task.predict(image,
    domains, sampling, generator)`` as pilight.train.intrinsics.IntrinsicsTask's."""
    from pilight.eval.metrics import masked_mae, masked_mean_angular_error, masked_psnr

    def predict(sp, gen):
        outs = [task.predict(b["image"], ip.domains, sp, gen) for b in chunks(imgs, ip.batch_size)]
        return {d: torch.cat([o[d] for o in outs]) for d in ip.domains}

    def score(pred):
        m = imgs["mask"]
        s = {
            "albedo_psnr": masked_psnr(pred["albedo"], imgs["albedo"], m) if "albedo" in pred else None,
            # None, not NaN, over an empty mask (#36)
            "normal_mean_deg": masked_mean_angular_error(pred["normal"], imgs["normal"], m)
            if "normal" in pred
            else None,
        }
        s.update(
            {f"{k}_mae": masked_mae(pred[k], imgs[k], m) if k in pred else None for k in ("roughness", "metallic")}
        )
        return s

    rows = run_sweep(sweep_settings(ip, tp, tp.intrinsics_cfg), predict, score, len(imgs["key"]), seed, progress)
    mark_fronts(rows, {k: hi for k, (_, hi) in INTRINSICS_METRICS.items()})
    return rows


def sweep_relight(task, pairs: dict, intr: dict, ip, tp: TradeParams, seed: int, progress=None) -> list[dict]:
    """Stage 2's points around ``ip`` (relight_infer) on ``pairs`` conditioned on ``intr``; ``task.predict(batch,
    sampling, generator, intrinsics)`` as pilight.train.relight.RelightTask's. Scored tone-mapped, like evaluate."""
    from pilight.data.colour import tonemap01
    from pilight.eval.metrics import psnr_per_image, ssim_per_image

    n = len(pairs["key"])

    def predict(sp, gen):
        outs = []
        for s in range(0, n, ip.batch_size):
            sl = slice(s, s + ip.batch_size)
            batch, cond = {k: v[sl] for k, v in pairs.items()}, {k: v[sl] for k, v in intr.items()}
            # absolute: the sweep grades sampling settings against the rendered targets, as it always has
            outs.append(task.predict(batch, sp, gen, cond, intensity="absolute"))
        return torch.cat([o["relit"] for o in outs])

    def score(relit):
        p, g = tonemap01(relit), tonemap01(pairs["image_b"])
        return {"relit_psnr": float(psnr_per_image(p, g).mean()), "relit_ssim": float(ssim_per_image(p, g).mean())}

    rows = run_sweep(sweep_settings(ip, tp, tp.relight_cfg), predict, score, n, seed, progress)
    mark_fronts(rows, {k: hi for k, (_, hi) in RELIGHT_METRICS.items()})
    return rows


def sweep_samples(shards: Path, pred_dir: Path, split: str, n: int) -> tuple[dict, dict, dict | None]:
    """What both sweeps run on: the first ``n`` test images and the first ``n`` cross-light pairs of
    ``split``, each stacked into one batch (DataError when either is empty), and the stage-1
    predictions in ``pred_dir`` that condition the pairs (None: ground truth conditions them)."""
    from pilight.data.schema import DataError
    from pilight.data.shard_reader import eval_dataset, make_loader
    from pilight.relight.conditions import optional_predictions

    imgs = first_n(make_loader(eval_dataset(shards, "test", "intrinsics"), 8), n)
    pairs = first_n(make_loader(eval_dataset(shards, split, "relight"), 8), n, is_cross_light)
    if not imgs or not pairs:
        raise DataError(f"{shards}: no test images or no cross-light {split} pairs to sweep")
    return imgs, pairs, optional_predictions(shards, pred_dir, split, "trade")


def sweep_both(
    t1, imgs: dict, ip1, t2, pairs: dict, ip2, preds: dict | None, tp: TradeParams, seed: int
) -> tuple[list[dict], list[dict]]:
    """Stage 1's and stage 2's points (``sweep_intrinsics`` with ``t1``, ``sweep_relight`` with ``t2``)
    under one progress bar that names the setting being sampled; stage 2 conditioned on ``preds``
    (stage-1 predictions) when given, else on ground truth."""
    from tqdm import tqdm

    from pilight.relight.conditions import choose_intrinsics

    intr = choose_intrinsics(pairs, torch.full((len(pairs["key"]),), preds is not None), preds)
    points = len(sweep_settings(ip1, tp, tp.intrinsics_cfg)) + len(sweep_settings(ip2, tp, tp.relight_cfg))
    with tqdm(total=points, desc="trade", unit="point") as bar:
        # the label names the point being sampled; None: it is done, so the bar and its ETA move on
        tick = lambda label: bar.set_postfix_str(label) if label is not None else bar.update(1)
        rows1 = sweep_intrinsics(t1, imgs, ip1, tp, seed, tick)
        rows2 = sweep_relight(t2, pairs, intr, ip2, tp, seed, tick)
    return rows1, rows2


RELIT_LIGHTS_ROWS = 4  # test views in reports/relit_lights.png


def lights_grid(task, shards: Path, split: str, ip, seed: int, preds: dict | None, lights: int):
    """reports/relit_lights.png (pilight.eval.relit_lights): the first cross-light pair of each of the first
    RELIT_LIGHTS_ROWS views of ``split``, relit under ``lights`` analytic lights, conditioned on ``preds``
    (stage-1 predictions) when given, else on ground truth."""
    from pilight.data.shard_reader import eval_dataset, make_loader
    from pilight.eval.relit_lights import relit_lights_grid
    from pilight.relight.conditions import choose_intrinsics

    views: set[tuple] = set()

    def new_view(b, i):  # one row per test view: the first cross-light pair of each
        m = json.loads(b["meta_a"][i])
        if not is_cross_light(b, i) or (m["scene"], m["view"]) in views:
            return False
        views.add((m["scene"], m["view"]))
        return True

    shown = first_n(make_loader(eval_dataset(shards, split, "relight"), 8), RELIT_LIGHTS_ROWS, new_view)
    shown_intr = choose_intrinsics(shown, torch.full((len(shown["key"]),), preds is not None), preds)
    return relit_lights_grid(
        lambda batch, c: task.predict(batch, ip, torch.Generator().manual_seed(seed), c, intensity="absolute"),
        [
            ({k: v[i : i + 1] for k, v in shown.items()}, {k: v[i : i + 1] for k, v in shown_intr.items()})
            for i in range(len(shown["key"]))
        ],
        lights,
    )


def write_trade(
    rows1: list[dict],
    rows2: list[dict],
    n1: int,
    n2: int,
    conditions: str,
    lights: np.ndarray,
    metrics: Path,
    plots: Path,
    reports: Path,
) -> str:
    """metrics (every point), plots/trade_<stage>[_pareto_<metric>].json, reports/trade_<stage>.png,
    reports/trade.md and reports/relit_lights.png (``lights``: ``lights_grid``); returns the markdown."""
    for d in (metrics.parent, plots, reports):
        d.mkdir(parents=True, exist_ok=True)
    result = {
        "intrinsics": {"images": n1, "points": rows1},
        "relight": {"pairs": n2, "conditions": conditions, "points": rows2},
    }
    atomic.write_json(metrics, result)
    for name, rows, columns in (("intrinsics", rows1, INTRINSICS_METRICS), ("relight", rows2, RELIGHT_METRICS)):
        atomic.write_json(plots / f"trade_{name}.json", rows)
        for key in columns:
            front = sorted((r for r in rows if r.get(f"pareto_{key}")), key=lambda r: r["seconds_per_image"])
            atomic.write_json(plots / f"trade_{name}_pareto_{key}.json", front)
        plot_png(
            rows,
            columns,
            reports / f"trade_{name}.png",
            f"{'Stage 1' if name == 'intrinsics' else 'Stage 2'}: seconds per image vs accuracy "
            f"({n1 if name == 'intrinsics' else n2} test {'images' if name == 'intrinsics' else 'pairs'})",
        )
    md = (
        markdown_table(
            rows1,
            {k: v for k, (v, _) in INTRINSICS_METRICS.items()},
            f"Stage 1 speed/accuracy trade ({n1} test images, around `infer_intrinsics`)",
        )
        + "\n"
        + markdown_table(
            rows2,
            {k: v for k, (v, _) in RELIGHT_METRICS.items()},
            f"Stage 2 speed/accuracy trade ({n2} cross-light test pairs, conditions: "
            f"{conditions}, around `relight_infer`)",
        )
    )
    atomic.write_text(reports / "trade.md", md)
    atomic.write_png(reports / "relit_lights.png", lights)
    return md
