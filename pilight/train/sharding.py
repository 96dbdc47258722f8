"""Sharded training (FSDP) for pilight.train.loop: ZeRO-2's split of gradients and AdamW state.

Under ``accelerate launch --config_file profiles/accelerate_fsdp.yaml`` a sharded COPY of the task's
module trains (what ``task.loss`` gets); the module itself is emptied meanwhile and receives the whole
weights for previews (main process) and at the end (every process), so ``task.images`` and the stage's
save see plain tensors. On GPUs accelerate shards; on CPU processes (gloo), where accelerate keeps
MULTI_CPU and would wrap DDP, this module applies torch's ``fully_shard`` with the same config's
settings. A request that cannot be met is an error, never a silent DDP run.
"""

from __future__ import annotations

import copy
from collections.abc import Callable

import torch
from accelerate import Accelerator
from accelerate.utils import DistributedType, parse_flag_from_env


def sharding_requested(acc: Accelerator) -> bool:
    """True when the launcher asked for FSDP (``accelerate launch --config_file profiles/accelerate_fsdp.yaml``
    exports ACCELERATE_USE_FSDP); an error when what was asked for is not what would run.

    accelerate enables FSDP only on accelerator devices: CPU processes keep MULTI_CPU (the loop shards
    them itself), and a single unlaunched process has nothing to shard across.  DeepSpeed is refused:
    under ZeRO the optimizer's ``state_dict()`` is DeepSpeed's partitioned format (no ``state`` /
    ``param_groups``), which the safetensors checkpoints cannot hold, so a run would die at its first
    checkpoint; and on CPU processes accelerate does not enable DeepSpeed at all (plain DDP would run)."""
    if parse_flag_from_env("ACCELERATE_USE_DEEPSPEED") or acc.distributed_type == DistributedType.DEEPSPEED:
        raise RuntimeError(
            "DeepSpeed was requested, but the loop's safetensors checkpoints cannot hold ZeRO's "
            "partitioned optimizer state. The same ZeRO-2 split (gradients and AdamW state sharded) "
            "runs as FSDP: accelerate launch --config_file profiles/accelerate_fsdp.yaml"
        )
    if acc.distributed_type == DistributedType.FSDP:  # GPUs: accelerate shards
        return True
    if not parse_flag_from_env("ACCELERATE_USE_FSDP"):
        return False
    if acc.distributed_type != DistributedType.MULTI_CPU:
        raise RuntimeError(
            f"FSDP was requested (ACCELERATE_USE_FSDP) but accelerate set up "
            f"{acc.distributed_type.value}, not several processes to shard across: start the stage "
            "with accelerate launch --config_file profiles/accelerate_fsdp.yaml"
        )
    return True


def fully_shard_on_cpu(module: torch.nn.Module, acc: Accelerator) -> None:
    """FSDP2 (torch's ``fully_shard``) on a CPU device mesh, as the launcher's FSDP settings say.

    accelerate does not shard CPU processes: its state stays MULTI_CPU and ``prepare`` would wrap the
    module in DDP.  Forcing its FSDP branch (overwriting ``AcceleratorState.distributed_type``) would
    lean on private state that accelerate re-derives in several places; ``fully_shard`` on a CPU mesh
    is torch's public API for exactly this, and accelerate's own plugin and wrap policy read the same
    FSDP_* variables from the same config file as on GPUs."""
    from accelerate.utils import FullyShardedDataParallelPlugin
    from accelerate.utils.fsdp_utils import fsdp2_prepare_auto_wrap_policy, get_module_children_bottom_up
    from torch.distributed.device_mesh import init_device_mesh
    from torch.distributed.fsdp import fully_shard

    plugin = FullyShardedDataParallelPlugin()  # from the FSDP_* variables accelerate launch exports
    if plugin.fsdp_version != 2:
        raise RuntimeError(
            f"FSDP on CPU processes is FSDP2 (torch's fully_shard); the config asks for fsdp_version "
            f"{plugin.fsdp_version}: set fsdp_version: 2 (profiles/accelerate_fsdp.yaml does)"
        )
    kwargs = {
        "mesh": init_device_mesh("cpu", (acc.num_processes,)),
        "reshard_after_forward": plugin.reshard_after_forward,
    }
    plugin.set_auto_wrap_policy(module)
    wrap = fsdp2_prepare_auto_wrap_policy(plugin, module)
    # Blocks first (bottom-up): each block's gradients are reduce-scattered, and their full copies
    # freed, as soon as its backward is done; the root takes whatever no block holds.
    for sub in get_module_children_bottom_up(module)[:-1] if wrap is not None else []:
        if wrap(sub):
            fully_shard(sub, **kwargs)
    fully_shard(module, **kwargs)


def prepare_sharded(acc: Accelerator, module: torch.nn.Module, make_optimizer: Callable):
    """(sharded model, optimizer, scheduler) for FSDP, trained in a copy of ``module``.

    The copy is what shards: FSDP turns a module's parameters into shards for good, and the task's
    own module must stay usable by one process alone (``task.images`` on the main process; the
    stage's save). While the copy trains, the module's parameter storage is released; it receives
    the whole weights for previews (main process) and at the end (every process)."""
    import torch.distributed as dist

    with torch.no_grad():  # DDP's constructor broadcasts rank 0's weights; FSDP keeps each rank's own slice
        for t in [*module.parameters(), *module.buffers()]:
            dist.broadcast(t.data, src=0)
    shards = copy.deepcopy(module)
    if acc.distributed_type == DistributedType.FSDP:  # GPUs: accelerate shards (FSDP2 or FSDP1, as configured)
        prepared = acc.prepare(shards, *make_optimizer(shards))
        release(module)
        return prepared
    fully_shard_on_cpu(shards, acc)
    # Not acc.prepare(shards): on CPU processes that would add a DDP wrapper around the shards.
    # No no_sync either (accelerate finds none on the module): every micro-batch's gradients are
    # reduce-scattered at once, as under ZeRO-2, instead of held whole until the last one.
    optimizer, scheduler = acc.prepare(*make_optimizer(shards))
    release(module)
    return shards, optimizer, scheduler


def release(module: torch.nn.Module) -> None:
    """Free the whole module's parameter storage while its sharded copy trains; dtype and device stay
    (tasks read ``next(module.parameters()).device``)."""
    for p in module.parameters():
        p.data = torch.empty(0, dtype=p.dtype, device=p.device)


def whole_weights(model: torch.nn.Module, module: torch.nn.Module, *, everywhere: bool) -> None:
    """The sharded ``model``'s full weights into ``module``: a collective, every process calls it;
    ``everywhere=False``: only the main process receives them (``cpu_offload``), for its previews."""
    from torch.distributed.checkpoint.state_dict import StateDictOptions, get_model_state_dict

    full = get_model_state_dict(model, options=StateDictOptions(full_state_dict=True, cpu_offload=not everywhere))
    if not full:
        return
    own = module.state_dict(keep_vars=True)  # the parameter and buffer objects themselves
    if own.keys() != full.keys():
        raise RuntimeError(f"the sharded copy's state has {sorted(set(full) ^ set(own))[:3]} where the module has not")
    device = next(module.parameters()).device
    for name, t in full.items():  # .data: the released parameters have no storage to copy into
        own[name].data = t.to(device)


def local(t: torch.Tensor) -> torch.Tensor:
    from torch.distributed.tensor import DTensor

    return t.to_local() if isinstance(t, DTensor) else t
