"""Environment throughput: batched ``MAIPPEnv`` vs a reference-style per-env Python loop.

Both implementations step a random masked policy (uniform over each deciding agent's
feasible neighbour slots) with automatic reset of finished episodes, and both count

    agent-steps = env steps x n_agents

(an env step takes one action per agent, whether or not that agent decides).

* ``MAIPPEnv`` with ``E`` envs: ``env.rand_action`` + ``env.step_and_maybe_reset`` (what
  ``env.rollout(T, break_when_any_done=False)`` does per step, without stacking the
  trajectory), timed over ``--steps`` steps: ``E * steps * m`` agent-steps.
* ``ReferenceMAIPPEnv`` (``reference_env.py``): one env, numpy/scipy float64, both GPs
  refit from scratch at every decision event. A reference code runs E envs one after the
  other, so its rate is E-independent: ``m / (seconds per env step)``, timed on one env
  over ``--ref-steps`` steps (several whole episodes, resets included).

The two are measured interleaved in one process: each repeat times a reference chunk and
then a MAIPPEnv chunk for each E, so slow drifts of the machine's load hit both alike; the
table reports medians over repeats and the median of the per-pair ratios.

An episode lasts about 72 env steps at B = 3. Windows much shorter than that (e.g.
``--steps 20``) see only the start of the first episodes, before any auto-reset, and
overstate MAIPPEnv's steady-state rate at large E (about 2x at E = 64 on the 2-core box).

Usage:
    python benchmarks/env_throughput.py                          # full run, E = 1 64 1024
    python benchmarks/env_throughput.py --envs 1 64 --steps 20 --ref-steps 80 --repeats 2
    python benchmarks/env_throughput.py --device cuda --dtype float32 --out results.json

On a shared or busy machine, multi-threaded BLAS (numpy/scipy, used by the reference) and
OpenMP (torch) can slow down by 10x when their threads get descheduled; for stable
figures there, pin both to one thread:
``OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 python benchmarks/env_throughput.py``.
The JSON output records these variables and the load average around every repeat.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from reference_env import ReferenceMAIPPEnv  # noqa: E402

from maipp_bench.envs.config import MAIPPConfig  # noqa: E402
from maipp_bench.envs.maipp_env import MAIPPEnv  # noqa: E402
from maipp_bench.hardware import cpu_model, native_bf16  # noqa: E402


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--envs", type=int, nargs="+", default=[1, 64, 1024],
                   help="batch sizes E of MAIPPEnv")
    p.add_argument("--steps", type=int, default=150,
                   help="timed MAIPPEnv steps per repeat and per E")
    p.add_argument("--ref-steps", type=int, default=300,
                   help="timed reference env steps per chunk (one chunk per repeat and E)")
    p.add_argument("--repeats", type=int, default=5, help="interleaved timing repeats")
    p.add_argument("--warmup", type=int, default=5, help="untimed steps after the first reset")
    p.add_argument("--budget", type=float, default=3.0, help="per-agent budget B")
    p.add_argument("--agents", type=int, default=3, help="number of agents m")
    p.add_argument("--device", choices=["cpu", "cuda"], default="cpu")
    p.add_argument("--dtype", choices=["float64", "float32"], default="float64",
                   help="MAIPPEnv belief dtype (the reference is always float64)")
    p.add_argument("--threads", type=int, default=None,
                   help="torch.set_num_threads (torch only; numpy/scipy: OPENBLAS_NUM_THREADS)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=None, help="write the results as JSON here")
    args = p.parse_args(argv)
    if min(args.envs) < 1 or args.steps < 1 or args.ref_steps < 1 or args.repeats < 1:
        p.error("--envs, --steps, --ref-steps and --repeats must be >= 1")
    if args.device == "cuda" and not torch.cuda.is_available():
        p.error("--device cuda: CUDA is not available in this torch build")
    return args


def machine_info(device: str) -> dict:
    info = {
        "platform": platform.platform(),
        "processor": platform.processor(),
        "cpu_model": cpu_model(),
        "native_bf16": native_bf16(),
        "machine": platform.machine(),
        "cpu_count": os.cpu_count(),
        "python": platform.python_version(),
        "torch": torch.__version__,
        "torch_num_threads": torch.get_num_threads(),
        "numpy": np.__version__,
        "device": device,
        "thread_env": {k: os.environ.get(k) for k in
                       ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")},
    }
    try:
        import scipy
        import torchrl

        info["scipy"], info["torchrl"] = scipy.__version__, torchrl.__version__
    except ImportError:
        pass
    if device == "cuda":
        info["gpu"] = torch.cuda.get_device_name(0)
    return info


def load_average() -> list[float] | None:
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except OSError:
        return None


# ---------------------------------------------------------------------- MAIPPEnv
class MAIPPRunner:
    """A MAIPPEnv of E envs kept alive across timing chunks (auto-reset included)."""

    def __init__(self, args: argparse.Namespace, n_envs: int) -> None:
        cfg = MAIPPConfig(budget=args.budget, n_agents=args.agents, dtype=args.dtype,
                          seed=args.seed)
        self.device = torch.device(args.device)
        t0 = time.perf_counter()
        self.env = MAIPPEnv(cfg, batch_size=[n_envs], device=self.device)
        self.td = self.env.reset()
        self._sync()
        self.first_reset_s = time.perf_counter() - t0
        self.n_envs, self.n_agents = n_envs, cfg.n_agents
        self.episodes_done = 0
        self.run(args.warmup)
        self.episodes_done = 0  # count timed steps only

    def _sync(self) -> None:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)

    def run(self, steps: int) -> float:
        """Step ``steps`` times; returns the wall time in seconds."""
        env, td, done = self.env, self.td, 0
        self._sync()
        t0 = time.perf_counter()
        for _ in range(steps):
            td = env.rand_action(td)
            out, td = env.step_and_maybe_reset(td)
            done = done + out.get(("next", "done")).sum()  # stays on device: no sync
        self._sync()
        elapsed = time.perf_counter() - t0
        self.td = td
        self.episodes_done += int(done)
        return elapsed


# ---------------------------------------------------------------------- reference
class ReferenceRunner:
    """One ReferenceMAIPPEnv stepped serially (auto-reset with a fresh seed)."""

    def __init__(self, args: argparse.Namespace) -> None:
        self.env = ReferenceMAIPPEnv(n_agents=args.agents, budget=args.budget)
        self.rng = np.random.default_rng(args.seed)
        self.next_seed = args.seed
        self.episodes_done, self.steps_done, self.measurements = 0, 0, []
        self._reset()
        for _ in range(args.warmup):
            self._step()

    def _reset(self) -> None:
        self.env.reset(seed=self.next_seed)
        self.next_seed += 1

    def _step(self) -> None:
        obs, _, done = self.env.step(self.env.random_masked_action(self.rng))
        if done:
            self.episodes_done += 1
            self.measurements.append(obs["metrics"]["measurements"])
            self._reset()

    def run(self, steps: int) -> float:
        t0 = time.perf_counter()
        for _ in range(steps):
            self._step()
        elapsed = time.perf_counter() - t0
        self.steps_done += steps
        return elapsed


# ---------------------------------------------------------------------- main
def main(argv: list[str] | None = None) -> dict:
    args = parse_args(argv)
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    m = args.agents
    wall0 = time.perf_counter()
    load_before = load_average()
    if load_before and load_before[0] > 0.5:
        print(f"note: load average {load_before} before start: other processes share this "
              f"machine ({os.cpu_count()} CPUs), so the figures will be noisy", flush=True)
    print(f"building envs: E = {args.envs} on {args.device} ({args.dtype}) ...", flush=True)
    ref = ReferenceRunner(args)
    runners = {e: MAIPPRunner(args, e) for e in args.envs}

    ref_rates: list[float] = []
    samples = {e: {"maipp": [], "reference": [], "ratio": [], "load": []} for e in args.envs}
    for r in range(args.repeats):
        for e, runner in runners.items():
            ref_s = ref.run(args.ref_steps)
            maipp_s = runner.run(args.steps)
            ref_rate = m * args.ref_steps / ref_s
            rate = e * m * args.steps / maipp_s
            ref_rates.append(ref_rate)
            samples[e]["reference"].append(ref_rate)
            samples[e]["maipp"].append(rate)
            samples[e]["ratio"].append(rate / ref_rate)
            samples[e]["load"].append(load_average())
            print(f"  repeat {r + 1}/{args.repeats} E={e:<5d} MAIPPEnv {rate:12,.0f} "
                  f"agent-steps/s ({maipp_s:6.2f} s)   reference {ref_rate:8,.0f} "
                  f"agent-steps/s ({ref_s:5.2f} s)", flush=True)

    ref_median = statistics.median(ref_rates)
    rows = [{"implementation": "reference (numpy/scipy, per-env loop)", "E": "any",
             "agent_steps_per_s": ref_median, "best_agent_steps_per_s": max(ref_rates),
             "ratio_to_reference": 1.0}]
    for e in args.envs:
        s = samples[e]
        rows.append({"implementation": f"MAIPPEnv ({args.device}, {args.dtype})", "E": e,
                     "agent_steps_per_s": statistics.median(s["maipp"]),
                     "best_agent_steps_per_s": max(s["maipp"]),
                     "ratio_to_reference": statistics.median(s["ratio"])})

    print()
    print("| implementation | E | agent-steps/s (median) | best repeat | ratio to reference |")
    print("|---|---|---:|---:|---:|")
    for row in rows:
        print(f"| {row['implementation']} | {row['E']} | {row['agent_steps_per_s']:,.0f} "
              f"| {row['best_agent_steps_per_s']:,.0f} | {row['ratio_to_reference']:.2f}x |")
    ref_ms = 1e3 * m / ref_median
    print(f"\nreference: {ref_ms:.2f} ms per env step (median); "
          f"{ref.episodes_done} episodes in {ref.steps_done} timed steps"
          + (f", {np.mean(ref.measurements):.1f} measurements per episode"
             if ref.measurements else ""))
    print("ratio = median over repeats of (MAIPPEnv rate / reference rate of the same repeat)")

    result = {
        "benchmark": "env_throughput",
        "definition": "agent-steps/s = env steps x n_agents / wall seconds; random masked "
                      "policy; auto-reset of finished episodes included",
        "args": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
        "machine": machine_info(args.device),
        "load_average_before": load_before,
        "load_average_after": load_average(),
        "total_wall_s": time.perf_counter() - wall0,
        "rows": rows,
        "reference": {
            "agent_steps_per_s_median": ref_median,
            "ms_per_env_step_median": ref_ms,
            "samples_agent_steps_per_s": ref_rates,
            "timed_steps": ref.steps_done,
            "episodes_completed": ref.episodes_done,
            "mean_measurements_per_episode": (float(np.mean(ref.measurements))
                                              if ref.measurements else None),
        },
        "maipp": {
            str(e): {
                "agent_steps_per_s_median": statistics.median(samples[e]["maipp"]),
                "ratio_to_reference_median": statistics.median(samples[e]["ratio"]),
                "samples_agent_steps_per_s": samples[e]["maipp"],
                "paired_reference_agent_steps_per_s": samples[e]["reference"],
                "load_average_after_each_repeat": samples[e]["load"],
                "ms_per_env_step_median": 1e3 * e * m / statistics.median(samples[e]["maipp"]),
                "first_reset_s": runners[e].first_reset_s,
                "episodes_completed": runners[e].episodes_done,
            }
            for e in args.envs
        },
    }
    print(f"total wall time {result['total_wall_s']:.1f} s; load average before "
          f"{load_before}, after {result['load_average_after']}")
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(result, indent=2))
        print(f"wrote {args.out}")
    return result


if __name__ == "__main__":
    main()
