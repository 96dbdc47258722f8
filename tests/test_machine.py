"""pilight.machine: which CPUs count as having native bf16 (what `mixed_precision: auto` decides on)."""

from __future__ import annotations

import pytest

from pilight import machine


@pytest.mark.parametrize(
    "onednn, x86, avx512_bf16, amx, native",
    [
        (True, True, False, False, False),  # AVX-512 without AVX512-BF16: oneDNN emulates, 2.5-2.7x slower
        (True, True, True, False, True),  # AVX512-BF16 (the AMD EPYC of 2026-12-06)
        (True, True, False, True, True),  # AMX (the Xeon of 2026-12-05)
        (False, True, True, True, False),  # ONEDNN_MAX_CPU_ISA=AVX2 withdraws oneDNN's bf16
        (False, True, False, False, False),  # AVX2 only
        (True, False, False, False, True),  # ARM with its bf16 extension: torch's check asks the hardware
    ],
)
def test_native_bf16_needs_the_instructions_not_only_onednn(onednn, x86, avx512_bf16, amx, native):
    assert machine.bf16_is_native(onednn_runs_bf16=onednn, x86=x86, avx512_bf16=avx512_bf16, amx_bf16=amx) is native


def test_an_x86_cpu_without_bf16_instructions_is_not_native(monkeypatch):
    """Whatever oneDNN says here: with the cpuinfo probes answering no, an x86 CPU has no native bf16."""
    monkeypatch.setattr(machine.platform, "machine", lambda: "x86_64")
    monkeypatch.setattr(machine, "_cpuinfo_says", lambda probe: False)
    assert machine.cpu_has_native_bf16() is False
    assert "no native bf16" in machine.one_line()
