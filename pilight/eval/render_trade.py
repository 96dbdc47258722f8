"""The render side of the speed/accuracy trade, scored and reported: samples per pixel against noise
and seconds (the renders: pilight.render.spp_sweep).

Noise error = PSNR of the tone-mapped image (pilight.data.colour.tonemap01, as the models see it)
against the reference render of the same scene; the reference has its own noise, so PSNR saturates
as spp approaches it. Writes metrics/render_trade.json, plots/render_trade.json (dvc plots) and
reports/render_trade.md / .png.
"""

from __future__ import annotations

from pathlib import Path

import torch

from pilight import atomic
from pilight.data.colour import tonemap01
from pilight.eval.metrics import psnr_from_mse


def score_renders(renders: list[dict]) -> list[dict]:
    """One row per non-reference render (pilight.render.spp_sweep.render_spp_sweep), PSNR and RMSE against
    the reference before it."""
    rows, ref = [], None
    for r in renders:
        img = tonemap01(torch.from_numpy(r["image"][..., :3]).permute(2, 0, 1)).numpy()
        if r["what"] == "reference":
            ref = img
            continue
        mse = float(((img - ref) ** 2).mean())
        rows.append(
            {
                "scene": r["spec"]["kind"],
                "objects": len(r["spec"]["objects"]),
                "what": r["what"],
                "spp": r["spp"],
                "adaptive_threshold": r["adaptive_threshold"],
                "seconds": r["seconds"],
                "psnr_vs_reference": psnr_from_mse(mse),
                "rmse": mse**0.5,
            }
        )
    return rows


def write_render_trade(
    rows: list[dict], resolution: int, reference_spp: int, metrics: Path, plots: Path, reports: Path
) -> str:
    """The metrics, the dvc plot's points, the markdown table and the plot; returns the markdown."""
    for d in (metrics.parent, plots, reports):
        d.mkdir(parents=True, exist_ok=True)
    atomic.write_json(metrics, {"resolution": resolution, "reference_spp": reference_spp, "points": rows})
    atomic.write_json(plots / "render_trade.json", [r for r in rows if r["what"] == "spp"])
    lines = [
        f"Render side: samples per pixel against noise and seconds ({resolution}², view 0 / light 0 of the first "
        f"object and room scene; reference {reference_spp} spp with another seed; PSNR on tone-mapped images)",
        "",
        "| scene | spp | adaptive threshold | seconds | PSNR vs reference (dB) | RMSE |",
        "|---|---|---|---|---|---|",
    ]
    lines += [
        f"| {r['scene']} ({r['objects']} obj.) | {r['spp']}{' (pipeline)' if r['what'] == 'pipeline' else ''} | "
        f"{r['adaptive_threshold']:g} | {r['seconds']:.2f} | {r['psnr_vs_reference']:.2f} | {r['rmse']:.4f} |"
        for r in rows
    ]
    md = "\n".join(lines) + "\n"
    atomic.write_text(reports / "render_trade.md", md)
    plot_png(rows, reports / "render_trade.png", resolution)
    return md


def plot_png(rows: list[dict], path: Path, res: int) -> None:
    """PSNR and seconds against spp, per scene; the pipeline's own setting as a star (matplotlib, Agg)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
    for kind in dict.fromkeys(r["scene"] for r in rows):
        pts = [r for r in rows if r["scene"] == kind and r["what"] == "spp"]
        own = [r for r in rows if r["scene"] == kind and r["what"] == "pipeline"]
        for ax, key in zip(axes, ("psnr_vs_reference", "seconds")):
            (line,) = ax.plot([r["spp"] for r in pts], [r[key] for r in pts], "o-", label=f"{kind}, adaptive off")
            ax.plot(
                [r["spp"] for r in own],
                [r[key] for r in own],
                "*",
                ms=12,
                color=line.get_color(),
                label=f"{kind}, pipeline setting (adaptive)",
            )
    for ax, name in zip(axes, ("PSNR vs reference (dB)", "seconds per render")):
        ax.set_xscale("log", base=2)
        ax.set_xlabel("samples per pixel")
        ax.set_ylabel(name)
        ax.grid(alpha=0.3)
    axes[1].set_yscale("log")
    axes[0].legend(fontsize=7)
    fig.suptitle(f"Render side of the trade ({res}², beauty pass)", fontsize=10)
    fig.tight_layout()
    atomic.save_figure(fig, path, dpi=110, metadata={"Software": None})  # no version string: same data, same bytes
    plt.close(fig)
