"""The shipped base model's card (weights/pilight-base/MODEL_CARD.md), written by the export stage from
the params that made it, its training logs and its evaluation on both test splits: every figure on
the card comes from a file, none is typed in."""

from __future__ import annotations

from typing import Any


def _flat(d: Any, prefix: str = "") -> dict[str, float]:
    if isinstance(d, dict):
        out: dict[str, float] = {}
        for k, v in d.items():
            out |= _flat(v, f"{prefix}.{k}" if prefix else str(k))
        return out
    return {prefix: float(d)} if isinstance(d, int | float) and not isinstance(d, bool) else {}


def _figures(metrics: dict[str, dict], keys: list[str]) -> list[str]:
    """One row per headline key (pilight.eval.metrics_files), one column per test split."""
    flat = {name: _flat(m) for name, m in metrics.items()}
    names = list(flat)
    rows = ["| figure | " + " | ".join(names) + " |", "|---" * (len(names) + 1) + "|"]
    for k in keys:
        cells = [f"{flat[n][k]:.3f}" if k in flat[n] else "–" for n in names]
        rows.append(f"| {k} | " + " | ".join(cells) + " |")
    return rows


def _training(stage: str, p, log: dict, label: str | None = None, also: str = "", seed: int | None = None) -> str:
    """A stage's Training line; ``label`` replaces the bold stage name, ``also`` ends the run's description,
    ``seed`` is the run's (its train.seed, else base.train_seed, else base.seed): two runs of one recipe differ
    by it alone."""
    m = log.get("machine", {})
    where = m.get("device") if m.get("device") not in (None, "cpu") else f"{m.get('cpu')}, {m.get('cores')} cores"
    seconds = log.get("seconds")
    took = f"{seconds / 3600:.2f} h" if isinstance(seconds, int | float) else "?"
    extra = f", objective {p.objective}, layout {p.layout}" if stage == "intrinsics" else ""
    prior = getattr(p, "level_prior", None)
    if prior is not None:  # the weights relight at the prior's level: params without it would not (MUST_MATCH)
        extra += f", light-level prior alpha {prior.alpha}, beta {prior.beta} (relight.level_prior)"
    precision = log.get("mixed_precision", m.get("mixed_precision", "?"))
    precision = {"no": "fp32"}.get(precision, precision)  # accelerate calls full precision "no"
    return (
        f"- {label or f'**{stage}**:'} {log.get('steps', p.train.steps)} steps of {p.train.batch_size}, "
        f"lr {p.train.lr} ({p.train.lr_schedule}), {precision} precision{extra}{also}"
        f"{f', seed {seed}' if seed is not None else ''}; "
        f"{took} on {where}"
    )


def _tuning(stage: str, tune, prior, log: dict) -> str:
    """The line of a tune that went on from the stage's prior (base/tune_profile.yaml): its own run, and the
    loss weights it changed, since those are what the tune is for. ``prior`` is the recipe's prior (the
    export's --params): a tune of a release that was itself tuned still lists the weights against that."""
    weights = getattr(tune, "task_loss", None)
    changed = (
        [f"{k} {v:g}" for k, v in weights.model_dump().items() if v != getattr(prior.task_loss, k)] if weights else []
    )
    also = f", loss weights {', '.join(changed)}" if changed else ""
    return _training(stage, tune, log, label=f"**{stage}, tuned** from it:", also=also)


def _scene_mix(sc, light) -> str:
    """The kinds of scene it saw: what a photo must resemble for its stage 1 to read it (a portrait read
    as a floor before a wall when no close-ups were drawn; docs/base-model.md)."""
    objects = 1.0 - sc.room_fraction - sc.closeup_fraction
    return (
        f"- Scenes: {sc.room_fraction:.0%} rooms, {sc.closeup_fraction:.0%} close-ups (one subject at eye level, "
        f"a wall or nothing behind it), {objects:.0%} objects on a ground plane; Blender's sky in "
        f"{light.sky_probability:.0%} of scenes; materials: {sc.material_model}."
    )


def model_card(
    base,
    render,
    intrinsics,
    relight,
    *,
    metrics: dict[str, dict],
    training: dict[str, dict],
    weights_bytes: int,
    kept: dict[str, str] | None = None,
    tuned: dict[str, tuple[Any, dict]] | None = None,
) -> str:
    """The card's markdown. ``kept``: {stage: its Training line from the previous card}, for a stage this
    export did not retrain (its weights are the previous base's, so is its training record). ``tuned``:
    {stage: (the tune's params section, its run's log)}, for a stage whose weights went on from its prior."""
    kept, tuned = kept or {}, tuned or {}
    sc, light, hdri = render.scene, render.light, render.hdri
    held = [h for h in hdri.names if h in hdri.test_holdout]
    keys = list(dict.fromkeys(k for m in metrics.values() for k in _flat(m)))  # the headline files' order
    headline = metrics
    lines = [
        "# pilight-base",
        "",
        "Both stages of pilight (stage 1: photo -> albedo, normal, roughness, metallic; stage 2: photo, intrinsics",
        "and a light ball -> relit image, diffuse D and specular S), trained from scratch on procedural Blender",
        "scenes by the stages of `base/dvc.yaml` (`cd base && dvc repro` runs them all; the Training lines say",
        "which ran for these weights). No third-party weights went into it.",
        "",
        f"Weights: {weights_bytes / 2**20:.1f} MB in float16 safetensors (they load as float32).",
        "",
        "## Use",
        "- `pilight relight photo.jpg --light left` uses it when there is no pipeline `models/` folder.",
        "- `unet.init: base` in a stage's params starts training from it (the embedded default does).",
        "",
        "## Data",
        f"- {render.scenes.train} training scenes, {render.scenes.val} validation, {render.scenes.test} test; "
        f"{render.views_per_scene} views x {render.lights_per_view} lights each, {render.resolution}^2 px, "
        f"base.seed {base.seed} (the embedded default's scenes come from another seed).",
        _scene_mix(sc, light),
        f"- Shapes: {', '.join(sc.shapes)}; textures: {', '.join(sc.textures)}.",
        f"- HDRIs: {', '.join(hdri.names)}; held out for its test split: {', '.join(held) or 'none'}. "
        f"Point light alone or with an HDRI (p = {light.hdri_probability}).",
        "- Never seen: the embedded default's held-out HDRIs and its test scenes; the held-out split's "
        "shapes and textures (base/heldout.yaml).",
        "",
        "## Training",
        *(
            line
            for stage, p in (("intrinsics", intrinsics), ("relight", relight))
            for line in (
                kept[stage]
                if stage in kept
                else _training(stage, p, training.get(stage, {}), seed=base.stage_training_seed(p.train)),
                *([_tuning(stage, tuned[stage][0], p, tuned[stage][1])] if stage in tuned else []),
            )
        ),
        "",
        "## Figures (held-out test splits)",
        "",
        *_figures(headline, keys),
        "",
        "## Limits",
        "- Trained on procedural scenes at 128^2: real photos are out of its domain (see the docs' photo results).",
        "- A single photo cannot tell albedo level from light power: relight with relative intensity (k = 1 keeps",
        "  the exposure) and read albedo in the scale-invariant figures.",
        "",
    ]
    return "\n".join(lines)
