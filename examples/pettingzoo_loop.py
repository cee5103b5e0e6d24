"""One MAIPP episode through the PettingZoo ``ParallelEnv`` API, with masked random actions.

    python examples/pettingzoo_loop.py            # 3 agents, budget 2, risk on
    python examples/pettingzoo_loop.py --smoke    # tiny config, a few steps (CI)

Every live agent submits an action sampled from its ``action_mask`` (the actions of agents
that are not deciding are ignored by the env, so this never fails); the loop ends when the
episode does, and the script prints the final metrics and each agent's return.
"""

from __future__ import annotations

import argparse

import torch

from maipp_bench.envs.pettingzoo import MAIPPParallelEnv


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--smoke", action="store_true", help="tiny config, few steps")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)

    if args.smoke:
        env = MAIPPParallelEnv(n_agents=2, budget=0.5, n_nodes=40, k_neighbors=8, max_steps=10)
    else:
        env = MAIPPParallelEnv(n_agents=3, budget=2.0)
    obs, infos = env.reset(seed=args.seed)
    for i, agent in enumerate(env.possible_agents):
        env.action_space(agent).seed(args.seed + i)  # reproducible sampling

    returns = dict.fromkeys(env.possible_agents, 0.0)
    decisions = dict.fromkeys(env.possible_agents, 0)
    steps = 0
    while env.agents:
        for agent in env.agents:
            decisions[agent] += int(infos[agent]["deciding"])
        actions = {a: env.action_space(a).sample(mask=obs[a]["action_mask"]) for a in env.agents}
        obs, rewards, terminations, truncations, infos = env.step(actions)
        for agent, r in rewards.items():
            returns[agent] += r
        steps += 1

    final = infos[env.possible_agents[0]]  # metrics are the team's: the same for all agents
    end = "truncated" if truncations[env.possible_agents[0]] else "terminated"
    print(f"episode {end} after {steps} steps, time {final['time']:.3f}, "
          f"distance {final['distance']:.3f} of {env.config.team_budget:g}")
    print(f"Tr(P) {final['trace']:.2f} (from {env.config.n_grid})  RMSE {final['rmse']:.4f}  "
          f"evidence {final['evidence_inside'] + final['evidence_outside']}"
          f"/{final['evidence_total']}  traps {final['traps']}  "
          f"measurements {final['measurements']}")
    for agent in env.possible_agents:
        print(f"  {agent}: {decisions[agent]} decisions, return {returns[agent]:+.4f}")
    env.close()


if __name__ == "__main__":
    main()
