"""A trained model's files: `<dir>/model.safetensors` (trainable weights only; frozen pretrained parts
such as a CLIP encoder or a VAE are reloaded from their own local paths), `<dir>/config.json` (the
params that built it, and the names of every substituted part) and `<dir>/checksums.json`, the
manifest: the sha256 of both, since both decide what the model computes.

Integrity by content (issue 36): ``load_model`` requires the manifest and every file it must cover. A
missing manifest is an error, not a pass (deleting it used to load damaged weights without a word);
the one exception is a folder made by hand, loaded with ``trust_unverified=True`` (the CLI's
``--trust-unverified``), which is announced as an ``UnverifiedModelWarning``.
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import torch
from safetensors.torch import load_file, save_file

from pilight import atomic
from pilight.atomic import sha256_file
from pilight.models.stack import DiffusionStack, ModelError


class UnverifiedModelWarning(UserWarning):
    """A model folder without a manifest was loaded because the caller said to trust it (trust_unverified)."""


def trainable_state(model: torch.nn.Module) -> dict[str, torch.Tensor]:
    keep = {n for n, prm in model.named_parameters() if prm.requires_grad}
    return {
        k: v.detach().cpu().contiguous()
        for k, v in model.state_dict().items()
        if k in keep or not k.startswith("conditioning.")
    }


MODEL_FILE = "model.safetensors"
CONFIG_FILE = "config.json"
CHECKSUM_FILE = "checksums.json"
COVERED = (MODEL_FILE, CONFIG_FILE)  # what decides what a saved model computes: the manifest must list both
TRUST_HINT = (
    "a folder written by save_model / save_pretrained always has one; a folder made by hand loads with "
    "--trust-unverified (pilight CLI) or trust_unverified=True (load_model, PILightPipeline.from_pretrained)"
)


def write_manifest(folder: Path, names: tuple[str, ...] | list[str]) -> None:
    """``folder/checksums.json``: the sha256 of each of ``names`` (paths relative to ``folder``)."""
    folder = Path(folder)
    atomic.write_json(
        folder / CHECKSUM_FILE, {"sha256": {n: sha256_file(folder / n) for n in sorted(names)}}, sort_keys=True
    )


def verify_manifest(
    folder: Path, required: tuple[str, ...] | list[str], *, trust_unverified: bool = False, fix: str = ""
) -> bool:
    """Check ``folder/checksums.json`` against the bytes: it must exist, list every name of ``required``,
    and every file it lists must exist and match. ModelError naming the file otherwise (``fix``: what to
    do, e.g. "rerun the training stage"). Returns False when there is no manifest and
    ``trust_unverified`` allowed the folder anyway (after an UnverifiedModelWarning naming it)."""
    folder = Path(folder)
    sums = folder / CHECKSUM_FILE
    fix = f"; {fix}" if fix else ""
    if not sums.is_file():
        if trust_unverified:
            warnings.warn(
                f"{folder}: no {CHECKSUM_FILE}: loading {', '.join(required)} UNVERIFIED, as asked "
                "(trust_unverified): nothing checks that they are the bytes that were saved",
                UnverifiedModelWarning,
                stacklevel=3,
            )
            return False
        raise ModelError(f"{sums}: missing, so nothing vouches for {', '.join(required)}; {TRUST_HINT}")
    try:
        recorded = json.loads(sums.read_text(encoding="utf-8"))["sha256"]
        if not isinstance(recorded, dict) or not all(
            isinstance(k, str) and isinstance(v, str) for k, v in recorded.items()
        ):
            raise TypeError("'sha256' is not an object of file name: hex digest")
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ModelError(f"{sums}: unreadable ({type(exc).__name__}: {exc}){fix}") from None
    uncovered = [n for n in required if n not in recorded]
    if uncovered:
        raise ModelError(f"{sums}: does not cover {', '.join(uncovered)} (it must list {', '.join(required)}){fix}")
    for name, digest in sorted(recorded.items()):
        if Path(name).is_absolute() or ".." in Path(name).parts:
            raise ModelError(f"{sums}: lists {name!r}, which is not a file of {folder}{fix}")
        f = folder / name
        if not f.is_file():
            raise ModelError(f"{f}: missing (listed in {sums}){fix}")
        if sha256_file(f) != digest:
            raise ModelError(
                f"{f}: sha256 differs from {sums}: the file was damaged, changed or only partly written after "
                f"saving{fix}"
            )
    return True


def save_model(stack: DiffusionStack, out_dir: Path, params: dict, dtype: torch.dtype | None = None) -> None:
    """Weights, config.json, then checksums.json (the sha256 of both, which load_model requires).
    ``dtype``: store floating tensors in it (float16 for the shipped base: half the bytes; load_model
    copies them into the float32 model).

    The manifest is written last, so a crash between the files leaves new files with the old manifest,
    which load_model reports as a mismatch rather than loading weights of unknown provenance."""
    out_dir = Path(out_dir)
    state = trainable_state(stack.model)
    bad = [k for k, t in state.items() if t.is_floating_point() and not bool(torch.isfinite(t).all())]
    if bad:
        raise ModelError(
            f"{out_dir / MODEL_FILE}: not saved, the trained weights hold NaN/Inf "
            f"({', '.join(bad[:3])}{', ...' if len(bad) > 3 else ''})"
        )
    if dtype is not None:
        state = {k: t.to(dtype) if t.is_floating_point() else t for k, t in state.items()}
    out_dir.mkdir(parents=True, exist_ok=True)
    atomic.write_with(out_dir / MODEL_FILE, lambda tmp: save_file(state, tmp))
    atomic.write_text(
        out_dir / CONFIG_FILE, json.dumps({"params": params, "parts": stack.describe()}, indent=1, sort_keys=True)
    )
    write_manifest(out_dir, COVERED)


def verify_model_folder(model_dir: Path, *, trust_unverified: bool = False) -> bool:
    """The manifest of a saved model (``verify_manifest`` over ``COVERED``); False when unverified, as allowed."""
    path = Path(model_dir) / MODEL_FILE
    if not path.is_file():
        raise ModelError(f"{path}: trained model not found; run the training stage first")
    return verify_manifest(model_dir, COVERED, trust_unverified=trust_unverified, fix="rerun the training stage")


def load_model(
    stack: DiffusionStack,
    model_dir: Path,
    *,
    trust_unverified: bool = False,
    verified: bool = False,
    new_parts: tuple[str, ...] = (),
) -> None:
    """Load trained weights into ``stack``; every way the folder can be wrong is a ModelError naming the
    file. The manifest is required (``verify_model_folder``) unless ``trust_unverified``; ``verified``:
    the caller has just checked it (``pilight.pipeline.load_stage`` does before it reads config.json).
    ``new_parts``: name prefixes of parameters the folder may lack because the stack extends its model
    (they keep their initial values; pilight.base_model.init_from_base)."""
    path = Path(model_dir) / MODEL_FILE
    if not verified:
        verify_model_folder(model_dir, trust_unverified=trust_unverified)
    try:
        state = load_file(str(path))
    except Exception as exc:  # noqa: BLE001 - safetensors raises its own error types on truncation
        raise ModelError(
            f"{path}: unreadable safetensors file ({exc}); truncated or not a model, rerun the training stage"
        ) from None
    bad = [k for k, t in state.items() if t.is_floating_point() and not bool(torch.isfinite(t).all())]
    if bad:
        raise ModelError(f"{path}: weights hold NaN/Inf ({', '.join(bad[:3])}); rerun the training stage")
    try:
        missing, unexpected = stack.model.load_state_dict(state, strict=False)
    except RuntimeError as exc:  # shapes differ: the params build another architecture than the one saved
        first = str(exc).strip().splitlines()[1:2] or [str(exc)]
        raise ModelError(f"{path}: does not match the params' model ({first[0].strip()})") from None
    missing = [k for k in missing if k in trainable_state(stack.model) and not (new_parts and k.startswith(new_parts))]
    if missing or unexpected:
        raise ModelError(
            f"{path}: does not match the params' model (missing {missing[:3]}, unexpected {unexpected[:3]})"
        )
