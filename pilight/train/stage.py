"""What both training stage scripts (stages/train_intrinsics.py, stages/train_relight.py) do around
:func:`pilight.train.loop.train`: check the shards, build the task, train with a run identity,
save the model.  Each script keeps only its params section and how its task is built; the exit
codes come from pilight.stage_cli."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from pilight.stage_cli import fails_on


def run_training_stage(
    name: str,
    section: str,
    base: Any,
    p: Any,
    make_task: Callable[[], Any],
    *,
    shards: Path,
    data: list[Path],
    out: Path,
    checkpoints: Path,
    live: Path,
) -> int:
    """Exit code 0; bad data or model input (before training starts) and damage found while it runs
    (a shard, a checkpoint, a diverged loss, a full disk) end the stage with exit 1 and a message
    naming the file (pilight.stage_cli.fails_on).

    ``data``: the inputs whose bytes belong to the run's identity (pilight.train.run_identity).
    A task with ``describe()`` (what each substituted part is) has it printed and written to
    ``out/task.json`` for reports."""
    import torch

    from pilight import atomic
    from pilight.base_model import BaseModelError, init_from_base
    from pilight.data.schema import DataError
    from pilight.data.shard_reader import read_index
    from pilight.models.folder import save_model
    from pilight.models.stack import ModelError, check_image_size
    from pilight.train.checkpoint import CheckpointError
    from pilight.train.loop import resolve_mixed_precision, train
    from pilight.train.run_identity import run_identity

    # Before the task is built: its model is initialised from the global RNG. Seeding after it
    # (as this function once did) gave every run different initial weights.
    torch.manual_seed(base.seed)
    with fails_on(DataError, ModelError, BaseModelError, OSError, ValueError, FloatingPointError):
        index = read_index(shards)
        if not index["splits"].get("train", {}).get("shards"):
            raise DataError(f"{shards}: the train split has no shards")
        task = make_task()
        check_image_size(tuple(index["sizes"]["image"][:2]), task.stack.codec.factor, f"{shards}/index.json")
        if p.unet.init == "base":  # the shipped prior (pilight.base_model); checkpoints, when any, win below
            print(f"{name}: starting from the base model {init_from_base(task.stack, p, section)}")
    # Damage found once training runs (a shard, a checkpoint, a diverged loss, a full disk) is a
    # message naming the file and exit 1, like damage found before it starts.
    with fails_on(DataError, ModelError, CheckpointError, FloatingPointError, OSError):
        described = task.describe() if hasattr(task, "describe") else None
        if described is not None:
            print(f"{name}: {described}")
        identity = run_identity(base.seed, section, p.model_dump(mode="json"), data)
        # auto resolves per machine: a checkpoint trained in bf16 is not resumed in fp32, nor the reverse
        identity["mixed_precision"] = resolve_mixed_precision(p.train.mixed_precision)[0]
        stats = train(task, p.train, checkpoints, live, seed=base.seed, identity=identity)
        from accelerate import PartialState

        if not PartialState().is_main_process:  # every rank ends with the same weights; one writes them
            return 0
        save_model(task.stack, out, p.model_dump(mode="json"))
        # On what the seconds in dvclive's metrics were measured (the model card and every timing table
        # name it). Beside the metrics, not in `out`: the model's bytes must not change with the machine.
        from pilight import machine

        facts = machine.describe() | {"mixed_precision": identity["mixed_precision"]}
        atomic.write_json(Path(live) / "machine.json", facts, sort_keys=True)
        if described is not None:
            atomic.write_json(out / "task.json", described, sort_keys=True)
    if p.train.steps == 0:
        start = "random weights (unet.init: scratch)" if p.unet.init == "scratch" else f"the {p.unet.init} weights"
        print(
            f"{name}: {section}.train.steps is 0, so {start} are the model, untrained (loss {stats['final_loss']:.4f}); "
            f"set {section}.train.steps to fine-tune -> {out}"
        )
    else:
        print(
            f"{name}: {stats['steps']} steps in {stats['seconds']:.0f} s "
            f"({stats['samples_per_second']:.2f} samples/s), final loss {stats['final_loss']:.4f} -> {out}"
        )
    return 0
