"""Which training run a checkpoint folder belongs to (``run.json``): the run's identity is its seed,
the stage's params that shape the weights, and a hash of its data. Under ``dvc repro`` the folder is
``persist: true``, so it survives a params change; :func:`claim_run` drops checkpoints of any other run,
otherwise ``dvc exp run -S relight.lambda_ps=0`` would resume the previous experiment's finished
weights and train nothing. ``steps`` is not part of the identity: raising it continues a finished run."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from pathlib import Path
from typing import Any

from pilight import atomic
from pilight.train.checkpoint import TMP_PREFIX, CheckpointError, list_checkpoints, step_of

RUN_FILE = "run.json"  # beside the step_* folders: which run they belong to


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
