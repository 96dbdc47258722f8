"""Training checkpoints in safetensors only (nothing is ever pickled or unpickled).

A checkpoint is a folder ``<checkpoint_dir>/step_<NNNNNNN>/`` holding

* ``model.safetensors``     -- state dict of ``Task.trainable()`` (unwrapped; tied weights deduplicated);
* ``optimizer.safetensors`` -- every AdamW state tensor as ``state.<param_index>.<name>``; the
  non-tensor parts (``param_groups``, non-tensor state entries) as JSON in the metadata;
* ``state.safetensors``     -- RNG states as uint8 tensors (``rank<r>.generator``, ``rank<r>.torch_cpu``,
  ``rank<r>.cuda``); metadata ``progress`` (step, epoch, batches consumed in that epoch, ...) and
  ``scheduler`` (LR scheduler state dict), both JSON.

Folders are written under a hidden temporary name and renamed into place, so a crash mid-write
never leaves a folder that :func:`latest_checkpoint` would pick.  A ``step_*`` folder is only
considered if all three files exist and their safetensors headers parse (a truncated file fails
that check), so hand-damaged folders are skipped too.
"""

from __future__ import annotations

import json
import os
import re
import shutil
from pathlib import Path
from typing import Any

import torch
from safetensors import safe_open
from safetensors.torch import load_file, load_model, save_file, save_model

MODEL_FILE = "model.safetensors"
OPTIMIZER_FILE = "optimizer.safetensors"
STATE_FILE = "state.safetensors"
FILES = (MODEL_FILE, OPTIMIZER_FILE, STATE_FILE)
TMP_PREFIX = ".tmp-"
_NAME = re.compile(r"^step_(\d{7,})$")


def checkpoint_path(checkpoint_dir: Path, step: int) -> Path:
    return Path(checkpoint_dir) / f"step_{step:07d}"


def is_complete(path: Path) -> bool:
    """True if every file exists and its safetensors header parses (catches truncation)."""
    for name in FILES:
        f = Path(path) / name
        if not f.is_file():
            return False
        try:
            with safe_open(str(f), framework="pt") as fh:
                fh.metadata()
        except Exception:  # noqa: BLE001 - any parse failure means "not a usable checkpoint"
            return False
    return True


def list_checkpoints(checkpoint_dir: Path) -> list[Path]:
    """Complete checkpoint folders, oldest step first."""
    d = Path(checkpoint_dir)
    if not d.is_dir():
        return []
    found = [(int(m.group(1)), p) for p in d.iterdir() if (m := _NAME.match(p.name)) and p.is_dir()]
    return [p for _, p in sorted(found) if is_complete(p)]


def latest_checkpoint(checkpoint_dir: Path) -> Path | None:
    ckpts = list_checkpoints(checkpoint_dir)
    return ckpts[-1] if ckpts else None


def remove_stale_tmp(checkpoint_dir: Path) -> None:
    """Delete leftovers of writes interrupted by a crash (only ever our own hidden folders)."""
    d = Path(checkpoint_dir)
    if d.is_dir():
        for p in d.iterdir():
            if p.name.startswith(TMP_PREFIX) and p.is_dir():
                shutil.rmtree(p, ignore_errors=True)


def _fsync(path: Path) -> None:
    # Durability: the rename must not reach disk before the file contents do.
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _flatten_optimizer(sd: dict[str, Any]) -> tuple[dict[str, torch.Tensor], dict[str, str]]:
    tensors: dict[str, torch.Tensor] = {}
    scalars: dict[str, dict[str, Any]] = {}
    for idx, entry in sd["state"].items():
        for name, val in entry.items():
            if torch.is_tensor(val):
                tensors[f"state.{idx}.{name}"] = val.detach().to("cpu").contiguous()
            else:
                scalars.setdefault(str(idx), {})[name] = val
    meta = {"param_groups": json.dumps(sd["param_groups"]), "scalars": json.dumps(scalars)}
    return tensors, meta


def _unflatten_optimizer(tensors: dict[str, torch.Tensor], meta: dict[str, str]) -> dict[str, Any]:
    state: dict[int, dict[str, Any]] = {}
    for key, val in tensors.items():
        _, idx, name = key.split(".", 2)
        state.setdefault(int(idx), {})[name] = val
    for idx, entry in json.loads(meta["scalars"]).items():
        state.setdefault(int(idx), {}).update(entry)
    return {"state": state, "param_groups": json.loads(meta["param_groups"])}


def save_checkpoint(
    checkpoint_dir: Path,
    step: int,
    *,
    model: torch.nn.Module,
    optimizer: torch.optim.Optimizer,
    scheduler: Any,
    rng: dict[str, torch.Tensor],
    progress: dict[str, Any],
    keep: int,
) -> Path:
    """Write ``step_<step>`` atomically, then prune to the newest ``keep`` checkpoints."""
    d = Path(checkpoint_dir)
    d.mkdir(parents=True, exist_ok=True)
    final = checkpoint_path(d, step)
    tmp = d / f"{TMP_PREFIX}{final.name}-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()

    save_model(model, str(tmp / MODEL_FILE))
    opt_tensors, opt_meta = _flatten_optimizer(optimizer.state_dict())
    save_file(opt_tensors, str(tmp / OPTIMIZER_FILE), metadata=opt_meta)
    meta = {"progress": json.dumps({**progress, "step": step}), "scheduler": json.dumps(scheduler.state_dict())}
    save_file({k: v.to("cpu").contiguous() for k, v in rng.items()}, str(tmp / STATE_FILE), metadata=meta)
    for name in FILES:
        _fsync(tmp / name)
    _fsync(tmp)

    if final.exists():  # same step saved again (e.g. a damaged folder): move aside, never rename onto it
        trash = d / f"{TMP_PREFIX}old-{final.name}-{os.getpid()}"
        os.replace(final, trash)
        shutil.rmtree(trash, ignore_errors=True)
    os.replace(tmp, final)
    _fsync(d)

    for old in list_checkpoints(d)[:-keep]:
        shutil.rmtree(old, ignore_errors=True)
    return final


def load_checkpoint(
    path: Path,
    *,
    model: torch.nn.Module,
    optimizer: torch.optim.Optimizer,
    scheduler: Any,
) -> tuple[dict[str, Any], dict[str, torch.Tensor]]:
    """Restore model/optimizer/scheduler in place; return (progress dict, RNG tensors)."""
    path = Path(path)
    # strict: a checkpoint from a different architecture must fail loudly, not half-load.
    load_model(model, str(path / MODEL_FILE), strict=True)
    with safe_open(str(path / OPTIMIZER_FILE), framework="pt") as fh:
        opt_meta = fh.metadata()
    optimizer.load_state_dict(_unflatten_optimizer(load_file(str(path / OPTIMIZER_FILE)), opt_meta))
    with safe_open(str(path / STATE_FILE), framework="pt") as fh:
        meta = fh.metadata()
    scheduler.load_state_dict(json.loads(meta["scheduler"]))
    return json.loads(meta["progress"]), load_file(str(path / STATE_FILE))
