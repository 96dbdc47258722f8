"""Profiles: overlays on params.yaml that hold only the keys where a setup differs from the embedded
default (profiles/paper.yaml: the paper's), composed into a complete params file.

    pilight profile profiles/paper.yaml -o params.yaml [--base params.yaml] [--no-check-paths]

An overlay's mappings are merged key by key into the base; any other value (a number, a string, a
list, null) replaces the base's, and so does a mapping whose `kind` differs from the base's (another
choice with other options, such as stage 2's `relight.form`). A key the base does not have is an error naming it (a typo would
otherwise be dropped or refused later, far from its cause). The result is validated section by
section through pilight.params before it is written (write, then rename).
"""

from __future__ import annotations

from pathlib import Path

import yaml

from pilight import atomic
from pilight.params import ParamsError, read_params, validate_sections


def compose(base: dict, overlay: dict, where: str = "") -> dict:
    """base with overlay's values; mappings merged key by key, every other value replaced."""
    out = dict(base)
    for key, value in overlay.items():
        name = f"{where}{key}"
        if key not in base:
            raise ParamsError(f"{name}: not a key of the base params (a typo?); known here: {sorted(base)}")
        if isinstance(value, dict) and isinstance(base[key], dict):
            other_choice = "kind" in value and value["kind"] != base[key].get("kind")
            out[key] = dict(value) if other_choice else compose(base[key], value, f"{name}.")
        elif isinstance(value, dict) != isinstance(base[key], dict):
            raise ParamsError(f"{name}: the base has {type(base[key]).__name__}, the overlay {type(value).__name__}")
        else:
            out[key] = value
    return out


def compose_files(base: Path, overlay: Path) -> dict:
    base_raw, overlay_raw = read_params(base), read_params(overlay)  # an overlay reads as a params file
    try:
        return compose(base_raw, overlay_raw)
    except ParamsError as exc:
        raise ParamsError(f"{overlay}: {exc}") from None


def write_profile(base: Path, overlay: Path, out: Path, *, check_paths: bool = True) -> dict:
    """Compose, validate every section (weight folders checked unless check_paths is False), write out."""
    raw = compose_files(base, overlay)
    text = (
        f"# Composed by `pilight profile {overlay}` from {base} (see pilight/profiles.py); edit the\n"
        f"# overlay and compose again rather than this file.\n" + yaml.safe_dump(raw, sort_keys=False)
    )
    try:
        validate_sections(raw, f"{overlay} over {base}", check_paths=check_paths)
    except ParamsError as exc:
        hint = " (weights on another machine? --no-check-paths validates the rest)" if check_paths else ""
        raise ParamsError(f"{exc}{hint}") from None
    atomic.write_text(out, text)
    return raw
