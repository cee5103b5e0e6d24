"""Cost of the belief copy that trajectory intent TI(a, j) plans on.

Each deciding agent's a rollouts start from a float32 copy of its belief with room for the
rollouts' fantasy measurements. This script times, side by side in one run on the same
mid-episode beliefs, the two ways to make that copy:

* ``index + grown``: index the env's beliefs once per rollout (``B * a`` full-capacity
  float64 copies), then convert and pad (what the TI policy did before);
* ``gathered``: ``GPBelief.gathered`` copies each agent's belief once, only its used
  measurement slots, in float32, then repeats it for the rollouts (what it does now; the
  same result bits, see tests/test_belief.py).

The beliefs come from E protocol-sized envs of a suite's env config, stepped ``--steps``
times with random masked actions; one agent per env decides.

Usage:
    OMP_NUM_THREADS=1 python benchmarks/ti_belief_copy.py [--agents 10 --budget 3]
"""

from __future__ import annotations

import argparse
import platform

import torch
from bench_timing import seconds_per_call

from maipp_bench.algos.rollouts import samples_per_edge
from maipp_bench.envs import MAIPPConfig, MAIPPEnv


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--agents", type=int, default=10)
    p.add_argument("--budget", type=float, default=3.0)
    p.add_argument("--risk", action="store_true", help="risk on (agents10 has it off)")
    p.add_argument("--envs", type=int, default=30, help="deciding agents B (one per env)")
    p.add_argument("--steps", type=int, default=60, help="random steps before the copy")
    p.add_argument("--rollouts", type=int, default=8)
    p.add_argument("--depth", type=int, default=5, help="j: rollout steps")
    p.add_argument("--repeats", type=int, default=10)
    args = p.parse_args()
    torch.set_num_threads(1)
    torch.manual_seed(0)  # rand_action draws from torch's global generator
    cfg = MAIPPConfig(n_agents=args.agents, budget=args.budget, risk_enabled=args.risk)
    env = MAIPPEnv(cfg, batch_size=[args.envs])
    env.set_seed(0)
    td = env.reset()
    for _ in range(args.steps):
        td = env.step(env.rand_action(td))["next"]
    st = env.episode
    e_idx = torch.arange(args.envs)
    g_idx = env.agent_belief_index[torch.zeros(args.envs, dtype=torch.int64)]
    a = args.rollouts
    extra = args.depth * samples_per_edge(st.roadmap, cfg.sample_spacing)  # as TI sizes it

    def old() -> object:
        rep = lambda x: x.repeat_interleave(a, 0)  # noqa: E731
        return st.belief[rep(e_idx), rep(g_idx)].grown(extra, torch.float32)

    def new() -> object:
        return st.belief.gathered((e_idx, g_idx), extra, torch.float32, repeats=a)

    ways = {"index + grown (before)": old, "gathered (now)": new}
    times = {name: [] for name in ways}
    for _ in range(3):  # interleaved rounds: both ways see the same machine state
        for name, fn in ways.items():
            times[name].append(seconds_per_call(fn, args.repeats))
    count = st.belief.count[e_idx, g_idx]
    print(f"{platform.machine()}, torch {torch.__version__}, 1 thread; m = {args.agents}, "
          f"B = {args.budget}, risk {'on' if args.risk else 'off'}: {args.envs} deciding "
          f"agents x {a} rollouts of depth {args.depth}, capacity {st.belief.capacity}, used slots "
          f"{int(count.min())}-{int(count.max())}, +{extra}")
    base = min(times["index + grown (before)"])
    for name, ts in times.items():
        print(f"  {name:24s} {1000 * min(ts):8.2f} ms per copy   {base / min(ts):5.2f}x")


if __name__ == "__main__":
    main()
