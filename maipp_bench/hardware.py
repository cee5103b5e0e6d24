"""What machine a run or a measurement came from, and whether its CPU has native bfloat16.

Training cards and benchmark figures name the CPU model: the development boxes changed
between AMD EPYC (with ``avx512_bf16``) and Intel Xeon (without it), and ``bf16`` training
runs at about half float32's speed where bfloat16 is emulated (docs/performance.md).
"""

from __future__ import annotations

import os
import platform
from pathlib import Path

import torch


def cpu_model() -> str | None:
    """The CPU model name (``platform.processor()`` is often empty on Linux), or None."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or None


def native_bf16() -> bool:
    """Whether the CPU computes bfloat16 matrix products natively (AVX512-BF16 or AMX);
    without either, autocast to bfloat16 on CPU is emulated and slower than float32."""
    checks = ("_is_avx512_bf16_supported", "_is_amx_tile_supported")  # torch.cpu's own
    return any(getattr(torch.cpu, name, lambda: False)() for name in checks)


def machine_name() -> str:
    """One line naming the machine: architecture, CPU model, cores and native bf16."""
    model = cpu_model() or "unknown CPU"
    return (f"{platform.machine()}, {model}, {os.cpu_count()} cores, "
            f"native bf16: {'yes' if native_bf16() else 'no'}")
