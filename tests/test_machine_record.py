"""benchmarks.common.machine: the CPU and BLAS code path recorded with each benchmark run."""

from __future__ import annotations

import pytest
import torch

from benchmarks.common import machine


def test_machine_names_torchs_cpu_capability_and_a_forced_mkl_path(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("MKL_ENABLE_INSTRUCTIONS", raising=False)
    plain = machine()
    assert plain.endswith(f"(torch {torch.backends.cpu.get_cpu_capability()})")
    assert not plain.startswith("(")  # a CPU is named, or "unknown CPU"
    monkeypatch.setenv("MKL_ENABLE_INSTRUCTIONS", "AVX2")
    assert machine() == plain[: -len(")")] + ", MKL_ENABLE_INSTRUCTIONS=AVX2)"
