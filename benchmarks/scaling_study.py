"""Stage 1's scaling study: held-out figures against training scenes and against samples seen (docs:
stage 1, "Scaling"), the evidence the base model's budget is chosen from.

    # scenes: the first N training scenes of a render folder, the same steps for each N
    python benchmarks/scaling_study.py scenes --renders base/data/renders --scenes 24 96 384 1200 \\
        --params base/params.yaml -S intrinsics.train.steps=1500 --json /tmp/scenes.json
    # samples: every checkpoint of a training run, scored on the test split
    python benchmarks/scaling_study.py samples --params base/params.yaml --shards base/data/shards \\
        --checkpoints base/checkpoints/intrinsics --json /tmp/samples.json
    # the docs' figure: both axes, one panel per map
    python benchmarks/scaling_study.py plot --samples /tmp/samples.json --scenes /tmp/scenes.json \\
        -o docs/images/stage1_scaling.png

`scenes` builds, per N, a render folder of symlinks to the first N training scenes and every val/test
scene, shards it with the shard stage's own code (so the test split is the same for every N), then
trains and scores as benchmarks/stage1_study.py does. `samples` loads each checkpoint of a run into
the params' model and scores it; samples seen = step x batch size. Each row prints the machine.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.stage1_study import apply_overrides, run_seed, score  # noqa: E402
from pilight.params import IntrinsicsParams, load_section, read_params  # noqa: E402


def finished_manifest(renders: Path) -> dict:
    """The manifest of a render folder, or, while it is still rendering, of its finished scenes (a scene's
    scene.json is written after all its views, pilight.render.views)."""
    if (renders / "manifest.json").is_file():
        return json.loads((renders / "manifest.json").read_text())
    from pilight.render.dataset import manifest_entry

    done = sorted(p.parent for p in renders.glob("*/scene.json"))
    specs = [json.loads((d / "scene.json").read_text())["spec"] for d in done]
    return {
        "resolution": json.loads((done[0] / "scene.json").read_text())["resolution"],
        "scenes": [manifest_entry(s) for s in specs],
    }


def subset_renders(renders: Path, n_train: int, out: Path) -> Path:
    """out/: symlinks to the first ``n_train`` training scenes and every other split's, and their manifest."""
    manifest = finished_manifest(renders)
    train = sorted((s for s in manifest["scenes"] if s["split"] == "train"), key=lambda s: s["id"])
    if n_train > len(train):
        raise SystemExit(f"{renders}: {len(train)} training scenes, {n_train} asked for")
    keep = train[:n_train] + [s for s in manifest["scenes"] if s["split"] != "train"]
    out.mkdir(parents=True, exist_ok=True)
    for s in keep:
        link = out / s["id"]
        if not link.exists():
            link.symlink_to((renders / s["id"]).resolve(), target_is_directory=True)
    (out / "manifest.json").write_text(json.dumps(manifest | {"scenes": keep}, indent=1, sort_keys=True))
    return out


def scenes(args) -> None:
    from pilight.data.shard_params import ShardParams
    from pilight.data.shard_writer import write_shards

    raw = apply_overrides(read_params(args.params)["intrinsics"], args.overrides)
    base = load_section("base", args.params)
    shard_p = ShardParams.model_validate(read_params(args.params)["shard"])
    from pilight import machine

    result = {"axis": "training scenes", "overrides": args.overrides, "machine": machine.one_line(), "rows": []}
    with tempfile.TemporaryDirectory(dir=args.work) as work:
        for n in args.scenes:
            renders = subset_renders(args.renders, n, Path(work) / f"renders_{n}")
            shards = Path(work) / f"shards_{n}"
            write_shards(renders, shards, shard_p, seed=base.seed)
            for seed in args.seeds:
                row = {"train_scenes": n, **run_seed(raw, shards, seed, args.train_images)}
                result["rows"].append(row)
                print(json.dumps(row), flush=True)
                if args.json:
                    args.json.write_text(json.dumps(result, indent=1))


def samples(args) -> None:
    from pilight.train.checkpoint import list_checkpoints, load_checkpoint, step_of
    from pilight.train.intrinsics import IntrinsicsTask
    from pilight.train.loop import _lr_schedule

    raw = apply_overrides(read_params(args.params)["intrinsics"], args.overrides)
    p = IntrinsicsParams.model_validate(raw)
    from pilight import machine

    result = {"axis": "samples seen", "machine": machine.one_line(), "rows": []}
    for ckpt in list_checkpoints(args.checkpoints):
        task = IntrinsicsTask(p, args.shards, seed=0)
        model = task.stack.model
        opt = torch.optim.AdamW([q for q in model.parameters() if q.requires_grad], lr=p.train.lr)
        sched = _lr_schedule(opt, p.train.lr_schedule, p.train.warmup_steps, p.train.steps)
        load_checkpoint(ckpt, model=model, optimizer=opt, scheduler=sched)
        model.eval()
        step = step_of(ckpt)
        row = {
            "step": step,
            "samples": step * p.train.batch_size * p.train.grad_accum,
            **score(task, args.shards, "test"),
        }
        result["rows"].append(row)
        print(json.dumps(row), flush=True)
        if args.json:
            args.json.write_text(json.dumps(result, indent=1))


PANELS = (  # (row keys, label, baseline key in the rows or None)
    (("normal_mean", "normal_median"), "normals: mean, median (deg)", None),
    (("albedo_si_psnr",), "albedo si-PSNR (dB)", "input_albedo_si_psnr"),
    (("roughness_mae",), "roughness MAE", None),
    (("metallic_mae",), "metallic MAE", None),
)


def plot(args) -> None:
    """Both axes as one figure: a row per axis, a panel per map, the machine in the title."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from pilight import atomic

    axes_data = [
        (json.loads(f.read_text()), x, label)
        for f, x, label in (
            (args.samples, "samples", "samples seen (one run, its checkpoints)"),
            (args.scenes, "train_scenes", "training scenes (1,000 steps of 8 each)"),
        )
        if f is not None
    ]
    if not axes_data:
        raise SystemExit("plot: give --samples and/or --scenes (the JSON files of the other two commands)")
    fig, grid = plt.subplots(
        len(axes_data), len(PANELS), figsize=(4 * len(PANELS), 3.2 * len(axes_data)), squeeze=False
    )
    for row, (data, x, xlabel) in zip(grid, axes_data):
        rows = sorted(data["rows"], key=lambda r: r[x])
        xs = [r[x] for r in rows]
        for ax, (keys, label, base) in zip(row, PANELS):
            for k in keys:
                ax.plot(xs, [r[k] for r in rows], "o-", label=k.split("_")[-1] if len(keys) > 1 else None)
            if base and base in rows[0]:
                ax.axhline(rows[0][base], color="gray", ls="--", label="input image")
            ax.set_xscale("log")
            ax.minorticks_off()
            ax.set_xticks(xs, [f"{v // 1000}k" if v >= 4000 else str(v) for v in xs])
            ax.set_xlabel(xlabel)
            ax.set_title(label, fontsize=10)
            if len(keys) > 1 or base:
                ax.legend(fontsize=8)
    fig.suptitle(f"Stage 1 on the base's test split; {axes_data[0][0].get('machine', '')}", fontsize=10)
    fig.tight_layout()
    atomic.write_with(args.out, lambda tmp: fig.savefig(tmp, format="png", dpi=110))
    print(f"plot: {args.out}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="axis", required=True)
    for name in ("scenes", "samples"):
        s = sub.add_parser(name)
        s.add_argument("--params", type=Path, default=Path("base/params.yaml"))
        s.add_argument("-S", dest="overrides", action="append", default=[], metavar="intrinsics.KEY=VALUE")
        s.add_argument("--json", type=Path, default=None)
    s = sub.choices["scenes"]
    s.add_argument("--renders", type=Path, required=True)
    s.add_argument("--scenes", type=int, nargs="+", required=True)
    s.add_argument("--seeds", type=int, nargs="+", default=[42])
    s.add_argument("--train-images", type=int, default=0)
    s.add_argument("--work", type=Path, default=None, help="where the subsets' shards go (default: the temp dir)")
    s = sub.choices["samples"]
    s.add_argument("--shards", type=Path, required=True)
    s.add_argument("--checkpoints", type=Path, required=True)
    s = sub.add_parser("plot")
    s.add_argument("--samples", type=Path, default=None, help="the samples command's --json")
    s.add_argument("--scenes", type=Path, default=None, help="the scenes command's --json")
    s.add_argument("-o", "--out", type=Path, required=True)
    args = ap.parse_args(argv)
    {"scenes": scenes, "samples": samples, "plot": plot}[args.axis](args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
