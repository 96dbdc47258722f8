"""pilight-base: the prior we train ourselves and ship in git (weights/pilight-base, made by base/dvc.yaml).

It is a `save_pretrained` folder (intrinsics/ and relight/, each model.safetensors in half precision
+ config.json + checksums.json, and pipeline.json) with its model card beside it. Three uses:

- ``unet.init: base`` in a stage's params: training starts from the shipped weights of that stage
  (``init_from_base``), as the paper starts from GeoWizard. The params must build the same network
  and give its outputs the same meaning: every key of ``MUST_MATCH`` is compared, and a difference
  is an error naming the key, both values and the file.
- ``pilight relight`` / ``decompose`` with no pipeline models/ use it (``default_models``).
- the model card says what it is, what it saw and how well it does.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

BASE_DIR = Path(__file__).resolve().parents[1] / "weights" / "pilight-base"
CARD = "MODEL_CARD.md"

# The keys that decide a stage's network and what its outputs mean. Everything else (learning rate,
# steps, loss weights, augmentations) may differ between the base and a fine-tune.
_NETWORK = ("codec", "unet.block_out_channels", "unet.layers_per_block", "unet.attention_head_dim")
_NETWORK += ("unet.cross_attention_dim", "conditioning.kind", "cross_batch_attention", "schedule")
MUST_MATCH: dict[str, tuple[str, ...]] = {
    "intrinsics": _NETWORK + ("layout", "albedo_space"),
    "relight": _NETWORK
    + (
        "decomposition",
        "form.kind",
        "form.target",
        "form.resolution",
        "form.albedo_source",
        "form.specular_anchor",
        "d_calc_condition",
        "ds_ball",
        "level_prior",  # the gains were learnt on anchors at the prior's level (pilight.relight.level_prior)
    ),
}
# What a saved config without a key (saved before the key existed) means by it.
ABSENT_MEANS: dict[str, Any] = {"level_prior": None}


# (key, the base's value, the params' value) -> the parameters the params' model adds, which start at values
# that make it compute what the base computes: ball tokens extend the learned embedding with a projection
# that starts at zero (pilight.diffusion.light_tokens).
EXTENSIONS: dict[tuple[str, str, str], tuple[str, ...]] = {
    ("conditioning.kind", "learned", "ball_tokens"): ("conditioning.proj.",),
}


class BaseModelError(ValueError):
    """The shipped base is missing, damaged, or does not fit the params."""


def _get(d: dict, dotted: str) -> Any:
    for part in dotted.split("."):
        if not isinstance(d, dict) or part not in d:
            return ABSENT_MEANS.get(dotted, "<absent>")
        d = d[part]
    return d


def _flat(x: Any) -> Any:
    return json.loads(json.dumps(x))  # tuples -> lists, as in a saved config


def base_folder(stage: str, path: str | None = None) -> Path:
    """The folder of one stage of the base: ``path`` (unet.path) when given, else the shipped one."""
    return Path(path) / stage if path else BASE_DIR / stage


def saved_params(cfg: Path, error: type[Exception], fix: str = "") -> dict:
    """The params a model folder's config.json was saved with; ``error`` naming the file when unreadable."""
    try:
        return json.loads(cfg.read_text(encoding="utf-8"))["params"]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise error(f"{cfg}: unreadable ({type(exc).__name__}: {exc}){fix}") from None


def mismatches(stage: str, wanted: dict, saved: dict, whose: str = "the base") -> list[str]:
    """``key: <whose> has X, params ask for Y`` for every MUST_MATCH key that differs."""
    from pilight.params import migrate_saved_relight

    wanted, saved = _flat(wanted), _flat(saved)
    if stage == "relight":  # a base saved before stage 2's form was one choice
        saved = migrate_saved_relight(saved)
    return [
        f"{stage}.{k}: {whose} has {_get(saved, k)!r}, the params ask for {_get(wanted, k)!r}"
        for k in MUST_MATCH[stage]
        if _get(saved, k) != _get(wanted, k)
        and not any(ext == (k, _get(saved, k), _get(wanted, k)) for ext in EXTENSIONS)
    ]


def check_saved_params(model_dir: Path, stage: str, p) -> None:
    """A stage that builds its model from the params must build the one that was trained: the keys that
    ``init: base`` also checks (pilight.base_model.MUST_MATCH; for stage 2 the light's level prior among
    them, as a model run without the prior it was trained with relights at another level, silently). A
    ModelError names the folder's config.json and each key."""
    from pilight.models.folder import CONFIG_FILE
    from pilight.models.stack import ModelError

    cfg = Path(model_dir) / CONFIG_FILE
    saved = saved_params(cfg, ModelError, "; rerun the training stage")
    wrong = mismatches(stage, p.model_dump(mode="json"), saved, whose=str(model_dir))
    if wrong:
        raise ModelError(
            f"{cfg}: the params build another model than the one trained:\n  "
            + "\n  ".join(wrong)
            + f"\nset these {stage} keys as the model has them, or retrain it"
        )


def extended_parts(wanted: dict, saved: dict) -> tuple[str, ...]:
    """The parameter prefixes the params' model adds to the base's (EXTENSIONS), to start from their initial values."""
    return tuple(
        prefix
        for (k, was, now), prefixes in EXTENSIONS.items()
        if _get(_flat(saved), k) == was and _get(_flat(wanted), k) == now
        for prefix in prefixes
    )


def init_from_base(stack, p, stage: str) -> Path:
    """Load the base's weights of ``stage`` into ``stack`` (built from params ``p``); returns the folder.
    BaseModelError when the folder is missing or the params build another network."""
    from pilight.models.folder import load_model
    from pilight.models.stack import ModelError

    folder = base_folder(stage, p.unet.path)
    cfg = folder / "config.json"
    if not cfg.is_file():
        raise BaseModelError(
            f"{stage}.unet.init is 'base' but {cfg} does not exist: the shipped base lives in "
            f"{BASE_DIR} (git), or set {stage}.unet.path to a folder holding {stage}/config.json"
        )
    saved = saved_params(cfg, BaseModelError)
    wrong = mismatches(stage, p.model_dump(mode="json"), saved)
    if wrong:
        raise BaseModelError(
            f"{stage}.unet.init is 'base' but the params build another model than {folder}:\n  "
            + "\n  ".join(wrong)
            + "\nset these keys as the base has them, or use unet.init: scratch"
        )
    new = extended_parts(p.model_dump(mode="json"), saved)
    if new:
        print(f"{stage}: the base's weights, with {', '.join(new)} new (they start at zero: the base's function)")
    try:
        load_model(stack, folder, new_parts=new)
    except ModelError as exc:
        raise BaseModelError(f"{stage}.unet.init is 'base': {exc}") from None
    return folder


def default_models(models: Path) -> tuple[Path, str | None]:
    """``models`` when it holds a pipeline's models; else the shipped base with a line saying so
    (a fresh clone relights a photo without training anything)."""
    if Path(models).is_dir() or not (BASE_DIR / "intrinsics" / "config.json").is_file():
        return Path(models), None
    return BASE_DIR, f"no {models}/ here: using the shipped base model {BASE_DIR} (see its {CARD})"
