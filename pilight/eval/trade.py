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
"""

from __future__ import annotations

import time
from typing import Callable

import torch

from pilight import atomic
from pilight.params import SamplingParams, TradeParams


def sweep_settings(base: SamplingParams, tp: TradeParams, cfg_scales: tuple[float, ...]) -> list[tuple[str, SamplingParams]]:
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
        dominated = any(w is not None and j != i and w[0] <= v[0] and w[1] >= v[1] and (w[0] < v[0] or w[1] > v[1])
                        for j, w in enumerate(vals))
        front.append(not dominated)
    return front


def run_sweep(settings: list[tuple[str, SamplingParams]], predict: Callable[[SamplingParams, torch.Generator], object],
              score: Callable[[object], dict[str, float | None]], count: int, seed: int,
              progress: Callable[[str], None] | None = None) -> list[dict]:
    """Time ``predict`` (one pass over the sweep's images) for each setting and score its output."""
    predict(settings[0][1].model_copy(update={"mode": "single_step", "ensemble": 1, "cfg_scale": 1.0}),
            torch.Generator().manual_seed(seed))  # warm-up: first-call allocations are not any point's cost
    rows = []
    for factor, sp in settings:
        if progress is not None:
            progress(describe(sp))
        t0 = time.perf_counter()
        out = predict(sp, torch.Generator().manual_seed(seed))
        seconds = (time.perf_counter() - t0) / count
        rows.append({"factor": factor, "label": describe(sp), "mode": sp.mode,
                     "steps": sp.steps, "spacing": sp.timestep_spacing,
                     "cfg": sp.cfg_scale, "ensemble": sp.ensemble, "seconds_per_image": seconds, **score(out)})
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
    lines += ["", "`*`: on the Pareto front of that metric against seconds per image (no point is both at least as "
              "fast and at least as accurate)."]
    return "\n".join(lines) + "\n"


def plot_png(rows: list[dict], metrics: dict[str, tuple[str, bool]], path, title: str) -> None:
    """One panel per metric: all points by factor, the Pareto front as a line (matplotlib, Agg)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(metrics), figsize=(5.2 * len(metrics), 4), squeeze=False)
    for ax, (key, (name, _higher)) in zip(axes[0], metrics.items()):
        for factor in dict.fromkeys(r["factor"] for r in rows):
            pts = [r for r in rows if r["factor"] == factor and r.get(key) is not None]
            ax.scatter([r["seconds_per_image"] for r in pts], [r[key] for r in pts], label=factor, s=22)
        front = sorted((r for r in rows if r.get(f"pareto_{key}")), key=lambda r: r["seconds_per_image"])
        ax.plot([r["seconds_per_image"] for r in front], [r[key] for r in front], "k--", lw=1, label="Pareto front")
        for r in front:
            ax.annotate(r["label"], (r["seconds_per_image"], r[key]), fontsize=6, xytext=(3, 3), textcoords="offset points")
        ax.set_xscale("log")
        ax.set_xlabel("seconds per image (log)")
        ax.set_ylabel(name)
        ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=7)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    atomic.save_figure(fig, path, dpi=110, metadata={"Software": None})  # no version string: same data, same bytes
    plt.close(fig)
