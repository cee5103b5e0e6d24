"""Timing helpers shared by the benchmark scripts (run as ``python benchmarks/<script>.py``)."""

from __future__ import annotations

import cProfile
import pstats
import time
from collections.abc import Callable
from typing import Any

import torch


def seconds_per_call(fn: Callable[[], object], repeats: int) -> float:
    """Mean wall time of ``fn()`` over ``repeats`` calls, after one untimed warm-up call."""
    fn()
    start = time.perf_counter()
    for _ in range(repeats):
        fn()
    return (time.perf_counter() - start) / repeats


def profiled_seconds(prof: cProfile.Profile,
                     phases: dict[str, tuple[str, str]]) -> dict[str, tuple[float, int]]:
    """Cumulative seconds and calls of each phase of a finished profile: label ->
    (file suffix, function name) as cProfile names them; every match is summed."""
    stats = pstats.Stats(prof).stats
    out = {}
    for label, (suffix, func) in phases.items():
        hits = [v for (file, _, name), v in stats.items()
                if name == func and file.endswith(suffix)]
        out[label] = (sum(v[3] for v in hits), sum(v[1] for v in hits))
    return out


def cuda_counts(events: Any) -> dict[str, float]:
    """What a ``torch.profiler`` run (``key_averages()``) asked of the GPU: kernel
    launches, ``cudaMemcpyAsync`` calls, synchronize calls, and the kernels' device time in ms
    (kernels only: an operator's row repeats the device time of the kernels it launched)."""
    return {
        "launches": sum(e.count for e in events
                        if e.key in ("cudaLaunchKernel", "cudaLaunchKernelExC")),
        "copies": sum(e.count for e in events if e.key == "cudaMemcpyAsync"),
        "syncs": sum(e.count for e in events if "Synchronize" in e.key),
        "device_ms": sum(e.self_device_time_total for e in events
                         if e.device_type == torch.autograd.DeviceType.CUDA) / 1000,
    }
