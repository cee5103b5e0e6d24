"""Render one MAIPP episode: a PNG of the final state and a GIF with one frame per step.

    python examples/render_episode.py --out docs/img        # the pictures of docs/interop.md
    python examples/render_episode.py --policy random       # masked random actions instead
    python examples/render_episode.py --smoke --out /tmp/x  # tiny config, a few steps (CI)

The panels are those of the paper's Figure 3 (``maipp_bench.viz``): interest mean with the
trajectories, ground truth, risk, GP std, the high-interest region X_I and the intents.
The default policy is the ``greedy`` planner; with ``--intents`` (on by default) every
deciding agent also broadcasts an intent, the Gaussian fitted to the nodes of a few random
walks that start with its chosen edge (a stand-in for a learned policy's sampled future
trajectories), so panel (f) has something to show.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch
from tensordict import TensorDictBase

from maipp_bench import viz
from maipp_bench.algos import get_method
from maipp_bench.envs import MAIPPConfig, MAIPPEnv
from maipp_bench.envs.intent import fit_intent

REPO = Path(__file__).resolve().parent.parent


class BroadcastIntents:
    """Wrap ``policy(td) -> td``: deciding agents also broadcast an intent Gaussian, fitted
    (``fit_intent``) to the nodes of ``walks`` random walks of ``depth`` nodes whose first
    node is the one the agent just chose."""

    def __init__(self, env: MAIPPEnv, policy, walks: int = 8, depth: int = 4,
                 seed: int = 0) -> None:
        self.env, self.policy, self.walks, self.depth = env, policy, walks, depth
        self.gen = torch.Generator(device=env.device).manual_seed(seed)

    def __call__(self, td: TensorDictBase) -> TensorDictBase:
        td = self.policy(td) if self.policy is not None else self.env.rand_action(td)
        st, env = self.env.episode, self.env
        e, m, k = st.nbr.shape
        rm, w = st.roadmap, self.walks
        action = td.get(("agents", "action")).to(torch.int64)
        node = st.nbr.gather(-1, action.unsqueeze(-1)).expand(e, m, w)  # chosen node
        points = []
        for step in range(self.depth):
            flat = node.reshape(e, -1, 1)
            points.append(rm.nodes.gather(1, flat.expand(-1, -1, 2)).view(e, m, w, 2))
            if step + 1 == self.depth:
                break
            nbr = rm.neighbors.gather(1, flat.expand(-1, -1, k)).view(e, m, w, k)
            ok = rm.neighbor_valid.gather(1, flat.expand(-1, -1, k)).view(e, m, w, k)
            u = torch.rand(e, m, w, k, generator=self.gen, dtype=torch.float64,
                           device=env.device)
            slot = torch.where(ok, u, -1.0).argmax(-1, keepdim=True)
            node = nbr.gather(-1, slot).squeeze(-1)
        pts = torch.stack(points, -2).flatten(-3, -2)  # [E, m, walks * depth, 2]
        mask = torch.ones(pts.shape[:-1], dtype=torch.bool, device=env.device)
        mean, cov = fit_intent(pts, mask, env.config.intent_cov_floor)
        td.set(("agents", "intent", "mean"), mean)
        td.set(("agents", "intent", "cov"), cov)
        td.set(("agents", "intent", "valid"), st.deciding.clone())
        return td


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=REPO / "docs" / "img",
                        help="output folder (default: docs/img)")
    parser.add_argument("--name", default="episode", help="file name prefix")
    parser.add_argument("--policy", choices=("greedy", "random"), default="greedy")
    parser.add_argument("--intents", action=argparse.BooleanOptionalAction, default=True,
                        help="agents broadcast random-walk intents (panel f)")
    parser.add_argument("--seed", type=int, default=0, help="env and policy seed")
    parser.add_argument("--fps", type=float, default=6.0)
    parser.add_argument("--smoke", action="store_true", help="tiny config, few steps")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)

    if args.smoke:
        cfg = MAIPPConfig(n_agents=2, budget=0.5, n_nodes=40, k_neighbors=8, max_steps=6,
                          aoi_enabled=True, seed=args.seed)
    else:
        cfg = MAIPPConfig(n_agents=3, budget=2.0, aoi_enabled=True, seed=args.seed)
    env = MAIPPEnv(cfg, batch_size=[1])
    torch.manual_seed(args.seed)
    policy = None
    if args.policy != "random":
        policy = get_method(args.policy).build(env, torch.tensor([args.seed]))
    if args.intents:
        policy = BroadcastIntents(env, policy, seed=args.seed)

    start = time.perf_counter()
    png, gif = viz.save_episode(env, args.out / args.name, policy=policy, fps=args.fps)
    seconds = time.perf_counter() - start
    st = env.episode
    print(f"{int(st.steps[0])} steps ({args.policy}{' + intents' if args.intents else ''}) "
          f"rendered in {seconds:.1f} s: Tr(P) {float(st.trace[0]):.1f}, evidence "
          f"{int((st.evidence_found & st.world.interest_valid)[0].sum())}"
          f"/{int(st.world.interest_valid[0].sum())}")
    for path in (png, gif):
        print(f"wrote {path} ({path.stat().st_size / 1024:.0f} KiB)")


if __name__ == "__main__":
    main()
