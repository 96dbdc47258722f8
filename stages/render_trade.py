"""DVC stage `render_trade`: the render side of the speed/accuracy trade, samples per pixel against
noise and seconds.

    python stages/render_trade.py

For the first object scene and the first room scene of the test split (view 0, light 0, the
render params' resolution and bounces), the beauty pass is rendered at each
`evaluate.trade.render_spp` with adaptive sampling OFF (so spp means spp), and once at
`evaluate.trade.render_reference_spp` with another seed as the reference.  Noise error = PSNR of
the tone-mapped image (schema.to_model, as the models see it) against the reference; seconds are
wall-clock per render.  The reference has its own noise, so PSNR saturates as spp approaches it.
The pipeline's own setting (`render.cycles.samples` with its adaptive threshold) is measured too.

Writes metrics/render_trade.json, plots/render_trade.json (dvc plots) and reports/render_trade.md / .png.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pilight import atomic  # noqa: E402
from pilight.params import ParamsError, load_section  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--params", default="params.yaml")
    ap.add_argument("--metrics", type=Path, default=Path("metrics/render_trade.json"))
    ap.add_argument("--plots", type=Path, default=Path("plots"))
    ap.add_argument("--reports", type=Path, default=Path("reports"))
    ap.add_argument("--log", type=Path, default=Path("logs/render_trade.log"), help="where Blender's own output goes")
    ap.add_argument("--verbose", action="store_true", help="Blender's output on the terminal instead of --log")
    args = ap.parse_args(argv)
    try:
        base, p = load_section("base", args.params), load_section("render", args.params)
        tp = load_section("evaluate", args.params).trade
    except ParamsError as exc:
        print(f"render_trade: {exc}", file=sys.stderr)
        return 2
    import tempfile

    import numpy as np
    import torch
    from tqdm import tqdm

    from pilight.data import schema
    from pilight.eval.metrics import psnr_from_mse
    from pilight.render import dataset, passes, scene
    from pilight.render.blender_log import blender_output_to
    from pilight.render.scene import RenderError
    from pilight.render.spec import scene_spec

    def first_of(kind: str) -> dict | None:
        for split in ("test", "val", "train"):
            for i in range(getattr(p.scenes, split)):
                spec = scene_spec(p, base.seed, split, i)
                if spec["kind"] == kind:
                    return spec
        return None

    def tonemap(x: np.ndarray) -> np.ndarray:
        return ((schema.to_model("image", torch.from_numpy(x[..., :3]).permute(2, 0, 1)) + 1) / 2).numpy()

    points = [("spp", n, 0.0, base.seed + 1) for n in tp.render_spp]
    points.append(("pipeline", p.cycles.samples, p.cycles.adaptive_threshold, base.seed + 1))
    rows = []
    specs = [s for s in (first_of("object"), first_of("room")) if s is not None]
    with blender_output_to(None if args.verbose else args.log) as terminal, \
            tempfile.TemporaryDirectory(prefix="render_trade_") as tmp, \
            tqdm(total=len(specs) * (len(points) + 1), desc="render_trade", unit="render", file=terminal) as bar:
        try:
            for spec in specs:
                handles = scene.build(spec, p, dataset.bundled_hdri_dir())
                scn = handles["scene"]
                scene.set_view(handles, spec["views"][0])
                light = spec["lights"][0][0]
                scene.set_lights(light)
                scene.set_world(handles["world"], light)
                passes.configure(scn.view_layers[0], diffuse=False, view_maps=False)

                def render(spp: int, threshold: float, seed: int) -> tuple[np.ndarray, float]:
                    c = scn.cycles
                    c.samples, c.use_adaptive_sampling, c.adaptive_threshold, c.seed = spp, threshold > 0, threshold, seed
                    t0 = time.perf_counter()
                    img = dataset._render(scn, Path(tmp))["Combined"]
                    bar.update(1)
                    return tonemap(img), time.perf_counter() - t0

                ref, _ = render(tp.render_reference_spp, 0.0, base.seed)
                for what, spp, threshold, seed in points:
                    img, sec = render(spp, threshold, seed)
                    mse = float(((img - ref) ** 2).mean())
                    rows.append({"scene": spec["kind"], "objects": len(spec["objects"]), "what": what, "spp": spp,
                                 "adaptive_threshold": threshold, "seconds": sec, "psnr_vs_reference": psnr_from_mse(mse),
                                 "rmse": mse ** 0.5})
        except RenderError as exc:
            print(f"render_trade: {exc}", file=terminal)
            return 1
    for d in (args.metrics.parent, args.plots, args.reports):
        d.mkdir(parents=True, exist_ok=True)
    res = p.resolution
    atomic.write_json(args.metrics, {"resolution": res, "reference_spp": tp.render_reference_spp, "points": rows})
    atomic.write_json(args.plots / "render_trade.json", [r for r in rows if r["what"] == "spp"])
    lines = [f"Render side: samples per pixel against noise and seconds ({res}², view 0 / light 0 of the first object "
             f"and room scene; reference {tp.render_reference_spp} spp with another seed; PSNR on tone-mapped images)", "",
             "| scene | spp | adaptive threshold | seconds | PSNR vs reference (dB) | RMSE |", "|---|---|---|---|---|---|"]
    lines += [f"| {r['scene']} ({r['objects']} obj.) | {r['spp']}{' (pipeline)' if r['what'] == 'pipeline' else ''} | "
              f"{r['adaptive_threshold']:g} | {r['seconds']:.2f} | {r['psnr_vs_reference']:.2f} | {r['rmse']:.4f} |" for r in rows]
    md = "\n".join(lines) + "\n"
    atomic.write_text(args.reports / "render_trade.md", md)
    _plot(rows, args.reports / "render_trade.png", res)
    print(md)
    return 0


def _plot(rows: list[dict], path: Path, res: int) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
    for kind in dict.fromkeys(r["scene"] for r in rows):
        pts = [r for r in rows if r["scene"] == kind and r["what"] == "spp"]
        own = [r for r in rows if r["scene"] == kind and r["what"] == "pipeline"]
        for ax, key in zip(axes, ("psnr_vs_reference", "seconds")):
            line, = ax.plot([r["spp"] for r in pts], [r[key] for r in pts], "o-", label=f"{kind}, adaptive off")
            ax.plot([r["spp"] for r in own], [r[key] for r in own], "*", ms=12, color=line.get_color(),
                    label=f"{kind}, pipeline setting (adaptive)")
    for ax, name in zip(axes, ("PSNR vs reference (dB)", "seconds per render")):
        ax.set_xscale("log", base=2)
        ax.set_xlabel("samples per pixel")
        ax.set_ylabel(name)
        ax.grid(alpha=0.3)
    axes[1].set_yscale("log")
    axes[0].legend(fontsize=7)
    fig.suptitle(f"Render side of the trade ({res}², beauty pass)", fontsize=10)
    fig.tight_layout()
    atomic.save_figure(fig, path, dpi=110, metadata={"Software": None})
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
