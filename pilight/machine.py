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


def cpu_has_native_bf16() -> bool:
    """Whether oneDNN has native bf16 kernels on this CPU (AVX512-BF16 or AMX). Without them CPU
    autocast still computes in bf16, but by emulation, and a step is slower than in fp32."""
    return bool(torch.backends.mkldnn.is_available() and torch.ops.mkldnn._is_mkldnn_bf16_supported())


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
    bf16 = "native bf16" if d["native_bf16"] else "no native bf16 (AVX2-class)"
    where = d["device"] if d["device"] != "cpu" else f"{d['cpu']}, {d['cores']} cores"
    return f"{where}, {d['threads']} torch threads, {bf16}"
