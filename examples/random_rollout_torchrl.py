"""Batched random rollout through TorchRL, with the ``ActionMask`` transform.

    python examples/random_rollout_torchrl.py             # 8 envs, 3 agents, budget 2
    python examples/random_rollout_torchrl.py --smoke     # tiny config, a few steps (CI)

Every env plays its first episode with uniformly random feasible actions (TorchRL's random
policy draws from the action spec, which ``ActionMask`` restricts to the feasibility mask);
finished envs reset on their own, and the script reports each env's first episode: its
final Tr(P) (the posterior variance left in the high-interest region), RMSE and evidence.
"""

from __future__ import annotations

import argparse
import time

import torch
from torchrl.envs import ActionMask, TransformedEnv

from maipp_bench.envs import MAIPPConfig, MAIPPEnv


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--envs", type=int, default=8, help="episodes played at once (E)")
    parser.add_argument("--steps", type=int, default=200, help="rollout length")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--smoke", action="store_true", help="tiny config, few steps")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)  # small tensors: one thread is fastest

    if args.smoke:
        cfg = MAIPPConfig(n_agents=2, budget=0.5, n_nodes=40, k_neighbors=8, max_steps=10)
        envs, steps = 2, 12
    else:
        cfg = MAIPPConfig(n_agents=3, budget=2.0)
        envs, steps = args.envs, args.steps
    env = TransformedEnv(
        MAIPPEnv(cfg, batch_size=[envs]),
        ActionMask(action_key=("agents", "action"), mask_key=("agents", "action_mask")),
    )
    env.set_seed(args.seed)
    torch.manual_seed(args.seed)  # the random actions use torch's global generator

    start = time.perf_counter()
    td = env.rollout(steps, break_when_any_done=False)  # [E, T]
    seconds = time.perf_counter() - start
    print(f"{envs} envs x {td.shape[1]} steps in {seconds:.2f} s "
          f"({cfg.n_agents} agents, budget {cfg.budget:g}, risk "
          f"{'on' if cfg.risk_enabled else 'off'})")

    done = td["next", "done"].squeeze(-1)  # [E, T]
    metrics = td["next", "metrics"]
    tr0 = float(cfg.n_grid)
    for e in range(envs):
        ends = done[e].nonzero().squeeze(-1)
        t = int(ends[0]) if len(ends) else td.shape[1] - 1
        status = f"done after {t + 1:3d} steps" if len(ends) else f"running at step {t + 1:3d}"
        print(f"env {e}: {status}  Tr(P) {float(metrics['trace'][e, t]):7.2f} "
              f"(from {tr0:.0f})  RMSE {float(metrics['rmse'][e, t]):.3f}  evidence "
              f"{int(metrics['evidence_inside'][e, t] + metrics['evidence_outside'][e, t])}"
              f"/{int(metrics['evidence_total'][e, t])}  traps {int(metrics['traps'][e, t])}")


if __name__ == "__main__":
    main()
