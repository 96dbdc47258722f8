"""The machine a timing was measured on, named the way our reports name it: the CPU model (or GPU) and
whether it has native bf16 kernels. Machines of one "2-core" class differ by 3-13x, so a number without
this line cannot be compared with another."""

from __future__ import annotations

import platform
from pathlib import Path

import torch


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown CPU"


def bf16_is_native(*, onednn_runs_bf16: bool, x86: bool, avx512_bf16: bool, amx_bf16: bool) -> bool:
    """Whether bf16 autocast runs on bf16 hardware. torch's own check (``onednn_runs_bf16``) is yes on
    any x86 CPU with AVX-512, because oneDNN runs bf16 there by emulation (its `jit_bf16:avx512_core`
    kernels): on a Xeon with AVX-512 and VNNI but no AVX512-BF16 (2026-12-07) a stage-1 step took 2.7x
    its fp32 time, a stage-2 step 2.5x. So on x86 the instructions must be there too; elsewhere (ARM's
    bf16 extension) torch's check already asks the hardware. ``ONEDNN_MAX_CPU_ISA`` can still withdraw
    oneDNN's consent, which is how the AVX2-only path is tested on a faster machine."""
    if not onednn_runs_bf16:
        return False
    return avx512_bf16 or amx_bf16 if x86 else True


def _cpuinfo_says(probe: str) -> bool:
    """torch.cpu's cpuinfo probes (private, hence getattr: a torch without one answers no)."""
    return bool(getattr(torch.cpu, probe, lambda: False)())


def cpu_has_native_bf16() -> bool:
    """Whether oneDNN has native bf16 kernels on this CPU (AVX512-BF16 or AMX on x86). Without them CPU
    autocast still computes in bf16, but by emulation, and a step is slower than in fp32."""
    return bf16_is_native(
        onednn_runs_bf16=bool(torch.backends.mkldnn.is_available() and torch.ops.mkldnn._is_mkldnn_bf16_supported()),
        x86=platform.machine().lower() in ("x86_64", "amd64", "i686", "x86"),
        avx512_bf16=_cpuinfo_says("_is_avx512_bf16_supported"),
        amx_bf16=_cpuinfo_says("_is_amx_tile_supported"),
    )


def describe() -> dict[str, object]:
    """{"device", "cpu", "cores", "threads", "native_bf16"}: what a timing ran on."""
    gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else None
    return {
        "device": gpu or "cpu",
        "cpu": cpu_model(),
        "cores": torch.multiprocessing.cpu_count() if hasattr(torch, "multiprocessing") else None,
        "threads": torch.get_num_threads(),
        "native_bf16": bool(gpu) or cpu_has_native_bf16(),
    }


def one_line() -> str:
    d = describe()
    bf16 = "native bf16" if d["native_bf16"] else "no native bf16"
    where = d["device"] if d["device"] != "cpu" else f"{d['cpu']}, {d['cores']} cores"
    return f"{where}, {d['threads']} torch threads, {bf16}"
