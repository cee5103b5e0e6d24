"""Where a batched ``MAIPPEnv`` step spends its time, and what the belief gather costs.

1. Steady-state profile: E envs under a random masked policy with auto-reset (as in
   ``env_throughput.py``), warmed up until episodes of every age are in the batch, then
   ``cProfile`` over ``--steps`` steps; prints milliseconds per step (cumulative) of the
   phases named below, and how many beliefs take measurements per step, with their mean
   and largest counts (what the used-row product of ``GPBelief.add`` saves).
2. The cross-covariance product B^T V of ``GPBelief.add`` in isolation (S of E beliefs, up
   to h rows of Q = 1101 columns, P new points): a fresh gather of the h-row prefixes (a
   new tensor each call), a gather into a reused buffer (what ``add`` did until
   2026-11-22), the blocked product that reads only used rows (what ``add`` does), and a
   gather-free weighted row sum (``embedding_bag``; not used: it changes the summation
   order, hence result bits).
3. The partial-reset merge, side by side: steps per second of ``step_and_maybe_reset`` with
   MAIPPEnv's merge (a plain update) and with TorchRL's (a masked ``where`` per key over
   all E), interleaved chunks of the same random steps (the two give the same data),
   median of the per-pair ratios.

Usage:
    OMP_NUM_THREADS=1 python benchmarks/env_profile.py --envs 1024
"""

from __future__ import annotations

import argparse
import contextlib
import cProfile
import statistics
import time

import torch
import torch.nn.functional as F
from bench_timing import profiled_seconds, seconds_per_call
from tensordict import TensorDictBase
from torchrl.envs import EnvBase

from maipp_bench.envs import MAIPPConfig, MAIPPEnv
from maipp_bench.envs.belief import GPBelief, _gathered_product

PHASES = {  # label -> (file suffix, function name) as cProfile names them
    "whole step (rand_action excluded)": ("torchrl/envs/common.py", "step_and_maybe_reset"),
    "  env step (MAIPPEnv._step)": ("maipp_env.py", "_step"),
    "    belief update (GPBelief.add)": ("belief.py", "add"),
    "    observation (_observe, step and reset)": ("maipp_env.py", "_observe"),
    "  partial resets (EnvBase.reset)": ("torchrl/envs/common.py", "reset"),
    "    new episodes (_new_episodes)": ("maipp_env.py", "_new_episodes"),
    "      roadmaps (build_roadmap: k-NN topk)": ("roadmap.py", "build_roadmap"),
    "    merge into the step's data (_reset_proc_data)": ("maipp_env.py", "_reset_proc_data"),
}


def steady_env(n_envs: int, warmup: int, cls: type[MAIPPEnv] = MAIPPEnv,
               dtype: str = "float64", device: str = "cpu") -> tuple[MAIPPEnv, TensorDictBase]:
    """E envs at B = 3 (seed 0) after ``warmup`` seeded random masked steps with
    auto-reset, so that episodes of every age are in the batch; the env and its data."""
    env = cls(MAIPPConfig(budget=3.0, dtype=dtype), batch_size=[n_envs], device=device)
    env.set_seed(0)
    td = env.reset()
    torch.manual_seed(0)
    for _ in range(warmup):
        _, td = env.step_and_maybe_reset(env.rand_action(td))
    if env.device.type == "cuda":
        torch.cuda.synchronize()
    return env, td


def phase_ms(prof: cProfile.Profile, steps: int) -> dict[str, float]:
    """Cumulative milliseconds per step of each of ``PHASES`` in a finished profile."""
    return {label: 1000 * seconds / steps
            for label, (seconds, _) in profiled_seconds(prof, PHASES).items()}


def profile_steps(n_envs: int, warmup: int, steps: int) -> dict[str, float]:
    """Milliseconds per step of each phase (cumulative time), steady state."""
    env, td = steady_env(n_envs, warmup)
    prof = cProfile.Profile()
    with _record_belief_updates() as updates:
        prof.enable()
        for _ in range(steps):
            _, td = env.step_and_maybe_reset(env.rand_action(td))
        prof.disable()
    out = phase_ms(prof, steps)
    counts = torch.cat([c for c, _ in updates]) if updates else torch.zeros(1)
    out["beliefs updated per step (count)"] = len(counts) / steps
    out["  their mean measurement count (count)"] = float(counts.float().mean())
    out["  the count a padded product gives them, mean (count)"] = sum(
        len(n) * h for n, h in updates) / max(len(counts), 1) if updates else 0.0
    return out


@contextlib.contextmanager
def _record_belief_updates():
    """While open, each ``GPBelief.add`` call appends (counts of the beliefs that take
    points, the largest of them): a product padded per call streams the largest for
    every belief, the used-row product only each one's own."""
    calls, add = [], GPBelief.add

    def recording(self, prior, query, x, y, mask):
        taking = mask.reshape(-1, mask.shape[-1]).any(-1)
        n = self.count.reshape(-1)[taking]
        if n.numel():
            calls.append((n, int(n.max())))
        return add(self, prior, query, x, y, mask)

    GPBelief.add = recording
    try:
        yield calls
    finally:
        GPBelief.add = add


def gather_costs(s: int, e: int, h: int, q: int, p: int, repeats: int) -> dict[str, float]:
    """Milliseconds per call of four ways to form B^T V for S of E beliefs whose counts
    are uniform in [1, h] (at E = 1024 the steady state's mean is nearer h / 3)."""
    cap = h + 4
    gen = torch.Generator().manual_seed(0)
    v = torch.randn(e, cap, q, dtype=torch.float64, generator=gen)
    idx = torch.randperm(e, generator=gen)[:s].sort().values
    count = torch.randint(1, h + 1, (s,), generator=gen)
    count[0] = h
    v[idx] *= (torch.arange(cap) < count.unsqueeze(-1)).unsqueeze(-1)  # unused rows: zero
    bmt = torch.randn(s, p, h, dtype=torch.float64, generator=gen)
    bmt *= (torch.arange(h) < count.unsqueeze(-1)).unsqueeze(1)
    buf = torch.empty(s, h, q, dtype=torch.float64)
    rows = (idx.view(s, 1, 1) * cap + torch.arange(h).view(1, 1, h)).expand(s, p, h).reshape(-1)
    offsets = torch.arange(s * p) * h
    flat = v.view(e * cap, q)
    ways = {
        "fresh gather + bmm": lambda: bmt @ v[:, :h][idx],
        "gather into a reused buffer + bmm (until 11-22)":
            lambda: bmt @ torch.index_select(v[:, :h], 0, idx, out=buf),
        "used rows, blocks of 8 (GPBelief.add, same bits)":
            lambda: _gathered_product(bmt, v, idx, count),
        "embedding_bag, no gather (changes bits)":
            lambda: F.embedding_bag(rows, flat, offsets, mode="sum",
                                    per_sample_weights=bmt.reshape(-1)),
    }
    return {name: 1000 * seconds_per_call(fn, repeats) for name, fn in ways.items()}


class TorchRLMergeEnv(MAIPPEnv):
    """MAIPPEnv merging partial resets with TorchRL's own code (as before 2026-11-22)."""

    _reset_proc_data = EnvBase._reset_proc_data


def merge_ab(n_envs: int, warmup: int, steps: int, repeats: int) -> dict[str, float]:
    """Milliseconds per step with each merge (medians) and the median per-pair speed-up."""
    runs = {}
    for name, cls in (("MAIPPEnv merge", MAIPPEnv), ("TorchRL merge", TorchRLMergeEnv)):
        runs[name] = [*steady_env(n_envs, warmup, cls), []]
    for r in range(repeats):
        for run in runs.values():
            env, td, times = run
            torch.manual_seed(1 + r)  # same actions: both envs go through the same states
            t0 = time.perf_counter()
            for _ in range(steps):
                _, td = env.step_and_maybe_reset(env.rand_action(td))
            times.append(1000 * (time.perf_counter() - t0) / steps)
            run[1] = td
    (_, _, ours), (_, _, theirs) = runs.values()
    out = {name: statistics.median(run[2]) for name, run in runs.items()}
    out["speed-up (median of pairs)"] = statistics.median(t / o for o, t in zip(ours, theirs))
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--envs", type=int, default=1024)
    p.add_argument("--warmup", type=int, default=150)
    p.add_argument("--steps", type=int, default=40)
    p.add_argument("--gather", type=int, nargs=3, default=[250, 49, 3], metavar=("S", "H", "P"),
                   help="selected beliefs, rows of V and new points for the gather timing")
    p.add_argument("--merge-repeats", type=int, default=15,
                   help="interleaved chunks per merge in the A/B (0: skip it)")
    args = p.parse_args()
    if not 1 <= args.gather[0] <= args.envs:
        p.error(f"--gather S must be in [1, --envs] = [1, {args.envs}], got {args.gather[0]}")
    torch.set_num_threads(1)
    print(f"profile: E={args.envs}, {args.steps} steps after {args.warmup} (cProfile "
          f"overhead included), ms per step")
    for label, v in profile_steps(args.envs, args.warmup, args.steps).items():
        print(f"  {label.removesuffix(' (count)'):48s} {v:8.1f}")
    s, h, pts = args.gather
    print(f"gather: S={s} of E={args.envs} beliefs, h={h}, Q=1101, P={pts}, ms per call")
    for label, ms in gather_costs(s, args.envs, h, 1101, pts, 10).items():
        print(f"  {label:48s} {ms:8.1f}")
    if not args.merge_repeats:
        return
    print(f"merge A/B: E={args.envs}, {args.merge_repeats} interleaved chunks of 10 steps "
          f"each, ms per step (no profiler)")
    for label, v in merge_ab(args.envs, args.warmup, 10, args.merge_repeats).items():
        print(f"  {label:48s} {v:8.2f}")


if __name__ == "__main__":
    main()
