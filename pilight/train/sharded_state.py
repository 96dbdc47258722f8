"""Sharded (FSDP) training state to and from the checkpoint files: the main process gathers full CPU
copies of the weights, the AdamW state and the EMA (``gather_sharded``) and pilight.train.checkpoint
writes them as for any run; on resume every process reads the full tensors and keeps its own shard
(``load_sharded``, ``shard_like``). The optimizer state keeps the parameter-index keys of
``Optimizer.state_dict()``, so a checkpoint does not record how the run was sharded."""

from __future__ import annotations

from typing import Any

import torch


def is_sharded(model: torch.nn.Module) -> bool:
    """True for a module sharded by FSDP (torch's ``fully_shard``, or the FSDP1 wrapper)."""
    from torch.distributed.fsdp import FSDPModule, FullyShardedDataParallel

    return any(isinstance(m, (FSDPModule, FullyShardedDataParallel)) for m in model.modules())


def _full(t: torch.Tensor) -> torch.Tensor:
    """The whole tensor of a DTensor shard (a collective: every process calls it), else ``t``."""
    from torch.distributed.tensor import DTensor

    return t.full_tensor() if isinstance(t, DTensor) else t


def shard_like(full: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
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
        raise ValueError(
            f"the checkpoint holds optimizer state for {n_saved} parameters, the model trains {len(names)}"
        )
    return {
        "state": {names[int(i)]: entry for i, entry in sd["state"].items()},
        "param_groups": [{**g, "params": [names[i] for i in g["params"]]} for g in sd["param_groups"]],
    }


def gather_sharded(
    model: torch.nn.Module, optimizer: torch.optim.Optimizer, ema: Any = None
) -> tuple[dict[str, torch.Tensor], dict[str, Any], dict[str, Any] | None]:
    """(weights, optimizer state, EMA state) of a sharded run as full CPU tensors, for pilight.train.checkpoint.save_checkpoint.

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


def load_sharded(
    model: torch.nn.Module, optimizer: torch.optim.Optimizer, weights: dict[str, torch.Tensor], saved: dict[str, Any]
) -> None:
    """Every process holds the full tensors read from a checkpoint (``weights``; ``saved``: the optimizer
    state as ``Optimizer.state_dict()`` keys it) and keeps its shard of them (no process waits on another)."""
    from torch.distributed.checkpoint.state_dict import StateDictOptions, get_optimizer_state_dict, set_state_dict

    # The parameter names in the optimizer's order, from this process's own (sharded) state: no gather.
    local = get_optimizer_state_dict(model, optimizer, options=StateDictOptions())
    names = [n for g in local["param_groups"] for n in g["params"]]
    set_state_dict(
        model,
        optimizer,
        model_state_dict=weights,
        optim_state_dict=_by_name(saved, names),
        options=StateDictOptions(full_state_dict=True),
    )
