"""Where a ``MAIPPEnv`` step spends its time on CUDA.

E envs under a random masked policy with auto-reset, warmed up to the steady state, then

1. wall milliseconds per step of the phases of ``env_profile.PHASES`` (``cProfile``; on
   CUDA a phase that waits for the device, e.g. at a ``nonzero`` or ``.item()``, is
   charged the wait);
2. ``torch.profiler`` over the same number of steps: kernel launches, host-device copies
   and synchronize calls per step, device busy time per step (the kernels' time), and the
   operators with the most host time and the most device time.

Usage:
    python benchmarks/cuda_profile.py --envs 1024 4096 --out profile.txt
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import time
from pathlib import Path

import torch
from bench_timing import cuda_counts
from env_profile import phase_ms, steady_env
from torch.profiler import ProfilerActivity, profile


def report(n_envs: int, warmup: int, steps: int, dtype: str, device: str) -> str:
    env, td = steady_env(n_envs, warmup, dtype=dtype, device=device)
    lines = [f"E={n_envs} {dtype} on {torch.cuda.get_device_name()}, {steps} steps after "
             f"{warmup}"]
    t0 = time.perf_counter()
    for _ in range(steps):
        _, td = env.step_and_maybe_reset(env.rand_action(td))
    torch.cuda.synchronize()
    lines.append(f"  no profiler: {1000 * (time.perf_counter() - t0) / steps:.1f} ms per step")

    prof = cProfile.Profile()
    prof.enable()
    for _ in range(steps):
        _, td = env.step_and_maybe_reset(env.rand_action(td))
    torch.cuda.synchronize()
    prof.disable()
    lines.append("  cProfile, cumulative wall ms per step:")
    lines += [f"    {label:52s} {ms:8.1f}" for label, ms in phase_ms(prof, steps).items()]
    stats = pstats.Stats(prof).stats
    top = sorted(((v[2], f"{Path(f).name}:{ln} {n}") for (f, ln, n), v in stats.items()),
                 reverse=True)[:25]
    lines.append("  cProfile, top self time (ms per step):")
    lines += [f"    {1000 * t / steps:8.2f}  {name}" for t, name in top]

    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as tp:
        for _ in range(steps):
            _, td = env.step_and_maybe_reset(env.rand_action(td))
        torch.cuda.synchronize()
    events = tp.key_averages()
    n = cuda_counts(events)
    lines.append(f"  torch.profiler: {n['launches'] / steps:.0f} kernel launches, "
                 f"{n['copies'] / steps:.0f} cudaMemcpyAsync, {n['syncs'] / steps:.0f} "
                 f"synchronize calls, {n['device_ms'] / steps:.1f} ms of device time per step")
    for key in ("self_cpu_time_total", "self_device_time_total"):
        lines.append(events.table(sort_by=key, row_limit=25, max_name_column_width=50))
    return "\n".join(lines)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--envs", type=int, nargs="+", default=[1024])
    p.add_argument("--warmup", type=int, default=150)
    p.add_argument("--steps", type=int, default=20)
    p.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    p.add_argument("--out", type=Path)
    args = p.parse_args()
    if not torch.cuda.is_available():
        p.error("needs CUDA")
    text = "\n\n".join(report(e, args.warmup, args.steps, args.dtype, "cuda")
                       for e in args.envs)
    print(text)
    if args.out:
        args.out.write_text(text)


if __name__ == "__main__":
    main()
