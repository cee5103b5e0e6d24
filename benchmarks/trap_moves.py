"""Which moves trap: the risk belief at the node each deciding agent moves to, tabulated
by its standard deviation and its mean, with the share of such moves that ended in a trap
(true risk >= the trap threshold at that node). docs/results.md ("What it takes to meet
the targets") cites it: traps come mostly from moves into unmeasured ground, where the
belief cannot tell them apart.

Held-out episodes (training's seeds, never the protocol's), one batch, one core.

Usage:
    python benchmarks/trap_moves.py --method ours_ti --budget 5 --episodes 72
"""

from __future__ import annotations

import argparse

import torch

from maipp_bench.algos.checkpoint import load_core
from maipp_bench.algos.registry import get_method
from maipp_bench.allocator import keep_freed_memory
from maipp_bench.envs.config import MAIPPConfig
from maipp_bench.envs.maipp_env import MAIPPEnv
from maipp_bench.heldout import add_heldout_argument
from maipp_bench.train import heldout_rows

INF = float("inf")
SD_BINS = (0.0, 0.3, 0.5, 0.7, 0.8, 0.9, INF)
MEAN_BINS = (-INF, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, INF)


@torch.no_grad()
def moves(method: str, budget: float, episodes: int, heldout: int = 2
          ) -> tuple[torch.Tensor, ...]:
    """Risk mean, sd and whether it traps, at the target of every move of ``method``
    (checkpoint as registered) on training's held-out episodes; moves of ended episodes are
    left out (their actions are never read; trapped agents never decide)."""
    spec = get_method(method)
    if not spec.learned:
        raise ValueError(f"--method {method}: a learned method (a checkpoint) is needed")
    core, payload = load_core(str(spec.checkpoint(None)))
    out = []

    def record(env: MAIPPEnv, td) -> None:
        st, g2 = env.episode, env.config.n_grid
        e, a = (st.deciding & ~td.get("done").reshape(-1, 1)).nonzero(as_tuple=True)
        slot = td.get(("agents", "action"))[e, a]
        node = st.roadmap.neighbors[e, st.cur[e, a]].gather(1, slot.unsqueeze(1)).squeeze(1)
        g = env.agent_belief_index[a]
        traps = st.node_risk[e, node] >= env.config.trap_threshold
        out.append(torch.stack([st.belief.mu[e, g, g2 + node, 1],
                                st.belief.sigma2[e, g, g2 + node].clamp_min(0).sqrt(),
                                traps], -1).double())

    heldout_rows(core, MAIPPConfig.from_dict(payload["env"]), episodes, budget, spec,
                 on_action=record, heldout=heldout)
    mu, sd, traps = torch.cat(out).unbind(-1)
    return mu, sd, traps.bool()


def table(name: str, values: torch.Tensor, trap: torch.Tensor, bins: tuple) -> None:
    print(f"risk belief {name} at the target | moves | traps | share trapped")
    for lo, hi in zip(bins[:-1], bins[1:]):
        sel = (values >= lo) & (values < hi)
        n, t = int(sel.sum()), int((sel & trap).sum())
        print(f"  [{lo:5.2f}, {hi:5.2f}) | {n:5d} | {t:3d} | {t / max(n, 1):.3f}")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--method", default="ours_ti")
    p.add_argument("--budget", type=float, default=5.0)
    p.add_argument("--episodes", type=int, default=72)
    add_heldout_argument(p)
    args = p.parse_args()
    keep_freed_memory()  # as the CLIs do (maipp_bench/allocator.py)
    torch.set_num_threads(1)
    mu, sd, trap = moves(args.method, args.budget, args.episodes, args.heldout_set)
    print(f"{args.method}, B = {args.budget:g}, {args.episodes} held-out episodes: "
          f"{len(mu)} moves, {int(trap.sum())} into a trap")
    table("sd", sd, trap, SD_BINS)
    table("mean", mu, trap, MEAN_BINS)


if __name__ == "__main__":
    main()
