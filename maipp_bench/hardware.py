"""What machine a run or a measurement came from, and whether its CPU has native bfloat16.

Training cards, leaderboards and benchmark figures name the CPU model: the development
boxes changed between AMD EPYC (with ``avx512_bf16``) and Intel Xeon (without it); ``bf16``
training runs at about half float32's speed where bfloat16 is emulated
(docs/performance.md), and MKL's default kernels round differently on another CPU (eval
pins its CPU-independent ones: maipp_bench/kernels.py; docs/protocol.md, "Another CPU").

Boards written before the CPU model was recorded (2026-11-28) were all computed on 2-core
AMD EPYC boxes: :data:`UNRECORDED_CPU`.
"""

from __future__ import annotations

import os
import platform
from pathlib import Path


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
    import torch  # here: the leaderboard imports this module without needing torch

    checks = ("_is_avx512_bf16_supported", "_is_amx_tile_supported")  # torch.cpu's own
    return any(getattr(torch.cpu, name, lambda: False)() for name in checks)


def machine_name() -> str:
    """One line naming the machine: architecture, CPU model, cores and native bf16."""
    model = cpu_model() or "unknown CPU"
    return (f"{platform.machine()}, {model}, {os.cpu_count()} cores, "
            f"native bf16: {'yes' if native_bf16() else 'no'}")


UNRECORDED_CPU = "AMD EPYC"  # the CPU of every board written before cpu_model was recorded


def same_cpu(recorded: str | None) -> bool:
    """Whether this machine's CPU is the one a board or card recorded (``None``: written
    before the model was recorded, so :data:`UNRECORDED_CPU`, matched as a prefix)."""
    here = cpu_model() or ""
    return here.startswith(UNRECORDED_CPU) if recorded is None else here == recorded
