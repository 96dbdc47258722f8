"""Training checkpoints in safetensors only (nothing is ever pickled or unpickled).

A checkpoint is a folder ``<checkpoint_dir>/step_<NNNNNNN>/`` holding

* ``model.safetensors``     -- state dict of ``Task.trainable()`` (unwrapped; tied weights deduplicated);
* ``optimizer.safetensors`` -- every AdamW state tensor as ``state.<param_index>.<name>``; the
  non-tensor parts (``param_groups``, non-tensor state entries) as JSON in the metadata;
* ``state.safetensors``     -- RNG states as uint8 tensors (``rank<r>.generator``, ``rank<r>.torch_cpu``,
  ``rank<r>.cuda``); metadata ``progress`` (step, epoch, batches consumed in that epoch, ...) and
  ``scheduler`` (LR scheduler state dict), both JSON;
* ``ema.safetensors``       -- only for runs with an EMA of the weights: its shadow tensors as
  ``shadow.<index>`` (the order of the trainable parameters), its counters as JSON metadata.

Folders are written under a hidden temporary name and renamed into place, so a crash mid-write
never leaves a folder that :func:`latest_checkpoint` would pick.

The folder belongs to one *run* (pilight.train.run_identity: ``run.json``).  A ``step_*`` folder is only
considered if all three files exist and their safetensors headers parse (a truncated file fails
that check), so hand-damaged folders are skipped too.

``checksums.json`` holds the sha256 of every file of the folder, written last inside the temporary
folder.  A header parses whatever happens to the tensor bytes after it, so only the checksum
catches flipped bytes in the weights (resumed silently before: exit 0, final loss 5324 against
0.36).  It is required (issue 36): a folder without it, or whose manifest leaves out one of its
files, is damaged like one whose bytes differ (deleting the manifest once let damaged weights resume
and reach models/ with a fresh checksum).  :func:`find_resume` verifies the newest checkpoint before resuming; a damaged one is named,
and falling back to an older one (or to step 0) is said in so many words.  Weights holding NaN or
Inf are never written (:class:`NonFiniteError`): a diverged run must not replace the last good
checkpoint.

Sharded runs (FSDP) write the same files (pilight.train.sharded_state gathers them onto the main
process, and on resume every process keeps its own shard; :func:`load_checkpoint` sees a sharded
model).  So a checkpoint does not record how the run was sharded, and an FSDP run resumes from a
DDP run's checkpoint and back (the RNG streams need the same process count).
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

from pilight import atomic
from pilight.atomic import sha256_file
from pilight.train.sharded_state import is_sharded, load_sharded, shard_like

MODEL_FILE = "model.safetensors"
OPTIMIZER_FILE = "optimizer.safetensors"
STATE_FILE = "state.safetensors"
FILES = (MODEL_FILE, OPTIMIZER_FILE, STATE_FILE)
EMA_FILE = "ema.safetensors"
TMP_PREFIX = ".tmp-"
CHECKSUM_FILE = "checksums.json"
_NAME = re.compile(r"^step_(\d{7,})$")


class CheckpointError(ValueError):
    """The checkpoint folder cannot be used as it is (a damaged run.json, a checkpoint that does not
    restore); the message names the file and what to do."""


class NonFiniteError(FloatingPointError):
    """Weights or loss hold NaN/Inf: nothing is checkpointed or saved."""


def non_finite_tensors(tensors: dict[str, torch.Tensor]) -> list[str]:
    """Names of the floating-point tensors that hold NaN or Inf (one device sync for all of them)."""
    names = [k for k, t in tensors.items() if t.is_floating_point()]
    if not names:
        return []
    device = tensors[names[0]].device
    ok = torch.stack([torch.isfinite(tensors[k]).all().to(device) for k in names]).cpu().tolist()
    return [k for k, good in zip(names, ok) if not good]


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


def damage(path: Path) -> str | None:
    """What is wrong with the checkpoint folder ``path`` (None: every file is there, parses and
    matches its checksum in ``checksums.json``, which must exist and cover every file)."""
    path = Path(path)
    for name in FILES:
        f = path / name
        if not f.is_file():
            return f"{name} missing"
        try:
            with safe_open(str(f), framework="pt") as fh:
                fh.metadata()
        except Exception as exc:  # noqa: BLE001 - safetensors raises its own error types
            return f"{name}: unreadable safetensors header ({exc})"
    sums = path / CHECKSUM_FILE
    if not sums.is_file():
        return f"{CHECKSUM_FILE} missing: nothing vouches for the weights"
    try:
        recorded = json.loads(sums.read_text(encoding="utf-8"))["sha256"]
        if not isinstance(recorded, dict):
            raise ValueError("'sha256' is not an object")
    except (OSError, ValueError, KeyError, TypeError) as exc:
        return f"{CHECKSUM_FILE}: unreadable ({exc})"
    present = FILES + ((EMA_FILE,) if (path / EMA_FILE).is_file() else ())
    uncovered = [name for name in present if name not in recorded]
    if uncovered:
        return f"{CHECKSUM_FILE} does not cover {', '.join(uncovered)}"
    for name, digest in sorted(recorded.items()):
        f = path / name
        if not f.is_file():
            return f"{name} missing (listed in {CHECKSUM_FILE})"
        if sha256_file(f) != digest:
            return f"{name}: sha256 differs from {CHECKSUM_FILE} (the bytes were damaged after writing)"
    return None


def find_resume(checkpoint_dir: Path, max_step: int | None = None) -> tuple[Path | None, list[str]]:
    """The newest verified checkpoint up to ``max_step``, and one warning line per damaged one
    passed over, naming the damaged folder and the one used instead (or step 0)."""
    d = Path(checkpoint_dir)
    if not d.is_dir():
        return None, []
    found = sorted(
        ((int(m.group(1)), p) for p in d.iterdir() if (m := _NAME.match(p.name)) and p.is_dir()), reverse=True
    )
    damaged: list[Path] = []
    notes: list[str] = []
    for step, p in found:
        if max_step is not None and step > max_step:
            continue
        problem = damage(p)
        if problem is None:
            if damaged:
                notes.append(
                    f"resuming from the previous checkpoint {p} instead of the damaged newest one {damaged[0]}"
                )
            return p, notes
        damaged.append(p)
        notes.append(f"{p}: damaged checkpoint, not resumed: {problem}")
    if damaged:
        notes.append(f"no usable checkpoint in {d} (newest {damaged[0]} is damaged): training starts from step 0")
    return None, notes


def latest_checkpoint(checkpoint_dir: Path, max_step: int | None = None) -> Path | None:
    """The newest verified checkpoint (see :func:`find_resume`, which also says what was skipped)."""
    return find_resume(checkpoint_dir, max_step)[0]


def step_of(path: Path) -> int:
    return int(_NAME.match(Path(path).name).group(1))


def remove_stale_tmp(checkpoint_dir: Path) -> None:
    """Delete leftovers of writes interrupted by a crash (only ever our own hidden folders)."""
    d = Path(checkpoint_dir)
    if d.is_dir():
        for p in d.iterdir():
            if p.name.startswith(TMP_PREFIX):
                shutil.rmtree(p, ignore_errors=True) if p.is_dir() else p.unlink(missing_ok=True)


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
    model: torch.nn.Module | dict[str, torch.Tensor],
    optimizer: torch.optim.Optimizer | dict[str, Any],
    scheduler: Any,
    rng: dict[str, torch.Tensor],
    progress: dict[str, Any],
    keep: int,
    ema: Any = None,
) -> Path:
    """Write ``step_<step>`` atomically, then prune to the newest ``keep`` checkpoints.

    ``model``, ``optimizer`` and ``ema`` are the objects, or (a sharded run) their full state dicts
    from :func:`gather_sharded`."""
    d = Path(checkpoint_dir)
    bad = non_finite_tensors(model if isinstance(model, dict) else model.state_dict())
    if ema is not None:
        bad += [f"ema {k}" for k in non_finite_tensors({str(i): t for i, t in enumerate(_shadow(ema))})]
    if bad:
        raise NonFiniteError(
            f"step {step}: weights hold NaN/Inf ({', '.join(bad[:3])}{', ...' if len(bad) > 3 else ''}); "
            f"not checkpointed, so {d} keeps its last good checkpoint (lower the lr?)"
        )
    final = checkpoint_path(d, step)
    tmp = d / f"{TMP_PREFIX}{final.name}-{os.getpid()}"
    try:
        d.mkdir(parents=True, exist_ok=True)
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir()
        if isinstance(model, dict):  # gathered full tensors: separate copies, nothing tied to deduplicate
            save_file({k: v.contiguous() for k, v in model.items()}, str(tmp / MODEL_FILE))
        else:
            save_model(model, str(tmp / MODEL_FILE))
        opt_tensors, opt_meta = _flatten_optimizer(optimizer if isinstance(optimizer, dict) else optimizer.state_dict())
        save_file(opt_tensors, str(tmp / OPTIMIZER_FILE), metadata=opt_meta)
        meta = {"progress": json.dumps({**progress, "step": step}), "scheduler": json.dumps(scheduler.state_dict())}
        save_file({k: v.to("cpu").contiguous() for k, v in rng.items()}, str(tmp / STATE_FILE), metadata=meta)
        names = FILES + ((EMA_FILE,) if ema is not None else ())
        if ema is not None:
            _save_ema(ema, tmp / EMA_FILE)
        sums = {"sha256": {name: sha256_file(tmp / name) for name in names}}
        (tmp / CHECKSUM_FILE).write_text(json.dumps(sums, indent=1, sort_keys=True) + "\n", encoding="utf-8")
        for name in names + (CHECKSUM_FILE,):
            os.chmod(tmp / name, atomic.file_mode())  # safetensors creates its files 0600 whatever the umask
            _fsync(tmp / name)
        _fsync(tmp)
    except OSError as exc:  # a full disk or a read-only folder: name the checkpoint, not a temporary
        shutil.rmtree(tmp, ignore_errors=True)
        raise atomic.path_error(exc, final, lambda name: name.startswith(str(tmp))) from exc
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise

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
    ema: Any = None,
) -> tuple[dict[str, Any], dict[str, torch.Tensor]]:
    """Restore model/optimizer/scheduler (and the EMA, if given) in place; return (progress dict, RNG tensors).

    A sharded ``model`` (FSDP; ``optimizer`` then the torch optimizer itself): every process must call
    this, and each keeps its shard of the full tensors."""
    path = Path(path)
    try:
        if is_sharded(model):
            with safe_open(str(path / OPTIMIZER_FILE), framework="pt") as fh:
                opt_meta = fh.metadata()
            saved = _unflatten_optimizer(load_file(str(path / OPTIMIZER_FILE)), opt_meta)
            load_sharded(model, optimizer, load_file(str(path / MODEL_FILE)), saved)  # strict too
        else:
            # strict: a checkpoint from a different architecture must fail loudly, not half-load.
            load_model(model, str(path / MODEL_FILE), strict=True)
            with safe_open(str(path / OPTIMIZER_FILE), framework="pt") as fh:
                opt_meta = fh.metadata()
            optimizer.load_state_dict(_unflatten_optimizer(load_file(str(path / OPTIMIZER_FILE)), opt_meta))
        with safe_open(str(path / STATE_FILE), framework="pt") as fh:
            meta = fh.metadata()
        scheduler.load_state_dict(json.loads(meta["scheduler"]))
        if ema is not None:
            _load_ema(ema, path / EMA_FILE)
        return json.loads(meta["progress"]), load_file(str(path / STATE_FILE))
    except (OSError, CheckpointError):
        raise
    except Exception as exc:  # noqa: BLE001 - strict-load RuntimeError, SafetensorError, bad JSON metadata, ...
        raise CheckpointError(
            f"{path}: cannot resume from this checkpoint ({type(exc).__name__}: {exc}); "
            f"delete it to fall back to an older one, or {path.parent} to train from step 0"
        ) from exc


def _shadow(ema: Any) -> list[torch.Tensor]:
    return ema["shadow_params"] if isinstance(ema, dict) else ema.shadow_params


def _save_ema(ema: Any, path: Path) -> None:
    """A diffusers EMAModel's state (or that state, gathered): tensors by index, scalar counters as JSON (no pickle)."""
    state = dict(ema if isinstance(ema, dict) else ema.state_dict())
    shadow = state.pop("shadow_params")
    save_file(
        {f"shadow.{i:05d}": t.detach().to("cpu").contiguous() for i, t in enumerate(shadow)},
        str(path),
        metadata={"ema": json.dumps(state)},
    )


def _load_ema(ema: Any, path: Path) -> None:
    if not path.is_file():
        raise FileNotFoundError(
            f"{path.parent}: this run keeps an EMA of its weights but the checkpoint has no {EMA_FILE}"
        )
    with safe_open(str(path), framework="pt") as fh:
        state = json.loads(fh.metadata()["ema"])
    tensors = load_file(str(path))
    if len(tensors) != len(ema.shadow_params):
        raise CheckpointError(f"{path}: {len(tensors)} EMA tensors for {len(ema.shadow_params)} trainable parameters")
    ema.load_state_dict(
        {
            **state,
            "shadow_params": [shard_like(tensors[f"shadow.{i:05d}"], ref) for i, ref in enumerate(ema.shadow_params)],
        }
    )
