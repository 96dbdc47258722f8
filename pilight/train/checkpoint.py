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

The folder belongs to one *run*: ``run.json`` holds its identity (the training params that shape
the weights, and a hash of the training data).  Under ``dvc repro`` the folder is ``persist: true``,
so it survives a params change; :func:`claim_run` drops checkpoints of any other run, otherwise
``dvc exp run -S relight.lambda_ps=0`` would resume the previous experiment's finished weights and
train nothing.  ``steps`` is not part of the identity: raising it continues a finished run.  A ``step_*`` folder is only
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

Sharded runs (FSDP) write the same files: :func:`gather_sharded` gathers full CPU copies of the
weights, the AdamW state and the EMA onto the main process, which writes them as above; the
optimizer state keeps the parameter-index keys of ``Optimizer.state_dict()``.  On resume every
process reads the full tensors and keeps its own shard (:func:`load_checkpoint` sees a sharded
model).  So a checkpoint does not record how the run was sharded, and an FSDP run resumes from a
DDP run's checkpoint and back (the RNG streams need the same process count).
"""

from __future__ import annotations

import hashlib
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

MODEL_FILE = "model.safetensors"
OPTIMIZER_FILE = "optimizer.safetensors"
STATE_FILE = "state.safetensors"
FILES = (MODEL_FILE, OPTIMIZER_FILE, STATE_FILE)
EMA_FILE = "ema.safetensors"
TMP_PREFIX = ".tmp-"
RUN_FILE = "run.json"
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


def hash_files(paths: list[Path]) -> str:
    """blake2b over the files' names and bytes, in sorted order (folders are walked)."""
    h = hashlib.blake2b(digest_size=16)
    files = sorted(f for p in map(Path, paths) for f in ([p] if p.is_file() else p.rglob("*")) if f.is_file())
    for f in files:
        h.update(f.name.encode() + b"\0")
        with open(f, "rb") as fh:
            for chunk in iter(lambda: fh.read(1 << 20), b""):
                h.update(chunk)
    return h.hexdigest()


# Train keys that never change the weights of step k (steps: raising it continues the run).
_NOT_IDENTITY = (
    "steps",
    "checkpoint_every",
    "keep_checkpoints",
    "log_every",
    "image_every",
    "num_workers",
    "grad_share_every",
)


def run_identity(seed: int, section: str, params: dict[str, Any], data: list[Path]) -> dict[str, Any]:
    """The identity of a training run: seed, the stage's params (less ``_NOT_IDENTITY`` under
    ``train``) and a hash of its data files, for :func:`claim_run`."""
    params = json.loads(json.dumps(params))
    for key in _NOT_IDENTITY:
        params.get("train", {}).pop(key, None)
    return {"seed": seed, section: params, "data": hash_files(data)}


def claim_run(checkpoint_dir: Path, identity: dict[str, Any], max_step: int) -> list[str]:
    """Make ``checkpoint_dir`` hold only checkpoints of the run ``identity`` (JSON-able) up to ``max_step``.

    Checkpoints written under another identity (or with none recorded) are deleted, as are
    checkpoints past ``max_step`` (``steps`` was lowered: the run must end with ``max_step``'s
    weights).  Returns one line per reason something was dropped, for the log."""
    d = Path(checkpoint_dir)
    d.mkdir(parents=True, exist_ok=True)
    run_file, found = d / RUN_FILE, list_checkpoints(d)
    wanted = json.loads(json.dumps(identity, sort_keys=True))
    old = _read_run_file(run_file) if run_file.is_file() else None
    dropped: list[str] = []
    if found and old != wanted:
        changed = sorted(k for k in set(wanted) | set(old or {}) if (old or {}).get(k) != wanted.get(k))
        dropped.append(f"{d}: {len(found)} checkpoint(s) of another run dropped (changed: {', '.join(changed)})")
        for p in found:
            shutil.rmtree(p)
    elif late := [p for p in found if step_of(p) > max_step]:
        dropped.append(f"{d}: checkpoint(s) past step {max_step} dropped: {', '.join(p.name for p in late)}")
        for p in late:
            shutil.rmtree(p)
    tmp = d / f"{TMP_PREFIX}{RUN_FILE}-{os.getpid()}"
    try:
        tmp.write_text(json.dumps(wanted, indent=1, sort_keys=True) + "\n", encoding="utf-8")
        os.replace(tmp, run_file)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise atomic.path_error(exc, run_file, lambda name: name == str(tmp)) from exc
    return dropped


def _read_run_file(run_file: Path) -> dict[str, Any]:
    # Not guessed at: deleting the checkpoints of a run that might be this one could throw away
    # hours of training, and keeping them could resume another run's weights.
    try:
        old = json.loads(run_file.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise CheckpointError(
            f"{run_file}: unreadable ({exc}); it records which run the checkpoints next to it "
            f"belong to. Restore it, or delete {run_file.parent} to train from step 0"
        ) from None
    if not isinstance(old, dict):
        raise CheckpointError(
            f"{run_file}: want a JSON object, got {type(old).__name__}; restore it, or delete "
            f"{run_file.parent} to train from step 0"
        )
    return old


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


def is_sharded(model: torch.nn.Module) -> bool:
    """True for a module sharded by FSDP (torch's ``fully_shard``, or the FSDP1 wrapper)."""
    from torch.distributed.fsdp import FSDPModule, FullyShardedDataParallel

    return any(isinstance(m, (FSDPModule, FullyShardedDataParallel)) for m in model.modules())


def _full(t: torch.Tensor) -> torch.Tensor:
    """The whole tensor of a DTensor shard (a collective: every process calls it), else ``t``."""
    from torch.distributed.tensor import DTensor

    return t.full_tensor() if isinstance(t, DTensor) else t


def _shard_like(full: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """``full`` placed like ``ref``: this process's shard of it when ``ref`` is a DTensor."""
    from torch.distributed.tensor import DTensor, distribute_tensor

    if isinstance(ref, DTensor):  # every process holds the full tensor: src_data_rank=None slices it locally
        return distribute_tensor(full.to(ref.device), ref.device_mesh, ref.placements, src_data_rank=None)
    return full.to(ref.device)


def _by_index(osd: dict[str, Any]) -> dict[str, Any]:
    """torch.distributed.checkpoint keys optimizer state by parameter name, ``Optimizer.state_dict()`` by
    the parameter's position over the param groups; the files keep the position."""
    index = {name: i for i, name in enumerate(n for g in osd["param_groups"] for n in g["params"])}
    return {
        "state": {index[n]: entry for n, entry in osd["state"].items()},
        "param_groups": [{**g, "params": [index[n] for n in g["params"]]} for g in osd["param_groups"]],
    }


def _by_name(sd: dict[str, Any], names: list[str]) -> dict[str, Any]:
    n_saved = sum(len(g["params"]) for g in sd["param_groups"])
    if n_saved != len(names):
        raise CheckpointError(
            f"the checkpoint holds optimizer state for {n_saved} parameters, the model trains {len(names)}"
        )
    return {
        "state": {names[int(i)]: entry for i, entry in sd["state"].items()},
        "param_groups": [{**g, "params": [names[i] for i in g["params"]]} for g in sd["param_groups"]],
    }


def gather_sharded(
    model: torch.nn.Module, optimizer: torch.optim.Optimizer, ema: Any = None
) -> tuple[dict[str, torch.Tensor], dict[str, Any], dict[str, Any] | None]:
    """(weights, optimizer state, EMA state) of a sharded run as full CPU tensors, for :func:`save_checkpoint`.

    A collective: every process calls it.  The main process receives the tensors, the others empty
    dicts (``cpu_offload``: no process but the writer ever holds a full copy).  ``optimizer`` is the
    torch optimizer itself, not accelerate's wrapper."""
    from torch.distributed.checkpoint.state_dict import StateDictOptions, get_state_dict

    weights, optim = get_state_dict(model, optimizer, options=StateDictOptions(full_state_dict=True, cpu_offload=True))
    ema_state = None
    if ema is not None:
        shadow = []
        for t in ema.shadow_params:
            whole = _full(t)  # a collective: every process gathers, the main one keeps
            if weights:
                shadow.append(whole.cpu())
        ema_state = {**ema.state_dict(), "shadow_params": shadow} if weights else None
    return weights, (_by_index(optim) if optim else {}), ema_state


def _load_sharded(path: Path, model: torch.nn.Module, optimizer: torch.optim.Optimizer) -> None:
    """Every process reads the full tensors and keeps its shard of them (no process waits on another)."""
    from torch.distributed.checkpoint.state_dict import StateDictOptions, get_optimizer_state_dict, set_state_dict

    with safe_open(str(path / OPTIMIZER_FILE), framework="pt") as fh:
        opt_meta = fh.metadata()
    saved = _unflatten_optimizer(load_file(str(path / OPTIMIZER_FILE)), opt_meta)
    # The parameter names in the optimizer's order, from this process's own (sharded) state: no gather.
    local = get_optimizer_state_dict(model, optimizer, options=StateDictOptions())
    names = [n for g in local["param_groups"] for n in g["params"]]
    set_state_dict(
        model,
        optimizer,
        model_state_dict=load_file(str(path / MODEL_FILE)),
        optim_state_dict=_by_name(saved, names),
        options=StateDictOptions(full_state_dict=True),
    )


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
            _load_sharded(path, model, optimizer)  # strict too
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
            "shadow_params": [_shard_like(tensors[f"shadow.{i:05d}"], ref) for i, ref in enumerate(ema.shadow_params)],
        }
    )
