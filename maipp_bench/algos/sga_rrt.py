"""``sga_rrt_<a>_<b>``: the paper's SGA+RRT(a, b) baseline, batched over envs.

Per deciding agent, in sequential greedy assignment order (agent index): grow a plain RRT
from the agent's node (ref: 400 iterations, step 0.1, no rewiring), take the tree branches
whose length lies in [a, b] as candidate paths, score each by Tr(P) after fantasy
measurements along it (every 0.2, carrying the agent's leftover distance) on the agent's
belief, conditioned first on its teammates' planned paths and remaining edges, and keep the
best. The env moves on the roadmap, so executing "the first 0.2 of the best path" means
taking the feasible neighbour nearest to the point 0.2 along it; the agent replans at its
next decision (ours: the roadmap adaptation of the reference's continuous execution).
With ``reuse_plan`` (ours, on in the YAMLs) the next tree starts from the unexecuted rest
of the last best path, so a good plan survives the replan: fresh trees at every edge made
the agents dither (docs/protocol.md).
"""

from __future__ import annotations

import math

import torch

from maipp_bench.algos.base import (
    PlannerPolicy,
    conditioned_belief,
    known_commitments,
    sga_rounds,
)
from maipp_bench.algos.paths import measurement_points, points_at, polyline_lengths
from maipp_bench.algos.registry import register_policy
from maipp_bench.envs import rng
from maipp_bench.envs.belief import interest_trace
from maipp_bench.envs.maipp_env import EpisodeState, MAIPPEnv

_KEPT_VERTICES = 32  # vertices of a best path kept for the next plan (RRT step 0.1: ~3.2)


@register_policy("sga_rrt")
class SGARRTPolicy(PlannerPolicy):
    """SGA over agents of RRT-sampled paths of length in [min_length, max_length]."""

    # 2: the last best path's remainder seeds the next tree (reuse_plan). 3: a measurement
    # at a branch's end lands there, not on the padding (the root): paths.points_at.
    version = 3

    def __init__(
        self,
        env: MAIPPEnv,
        seeds: torch.Tensor,
        min_length: float,
        max_length: float,
        iterations: int = 400,
        step: float = 0.1,
        execute: float = 0.2,
        max_candidates: int = 64,
        reuse_plan: bool = True,
    ) -> None:
        super().__init__(env, seeds)
        if not 0 < min_length <= max_length:
            raise ValueError(f"sga_rrt: need 0 < min_length <= max_length, got "
                             f"{min_length}, {max_length}")
        self.a, self.b = min_length, max_length
        self.iterations, self.step, self.execute = iterations, step, execute
        self.max_candidates = max_candidates
        self.reuse_plan = reuse_plan
        e, m = env.n_envs, env.n_agents
        self.max_points = int(math.floor((max_length + env.config.sample_spacing)
                                         / env.config.sample_spacing)) + 1
        # Each agent's current plan (measurement points), conditioning later planners.
        self.plans = torch.zeros(e, m, self.max_points, 2, dtype=torch.float64,
                                 device=env.device)
        self.plan_mask = torch.zeros(e, m, self.max_points, dtype=torch.bool, device=env.device)
        # Each agent's last best path (polyline, root first): what it has not executed yet
        # seeds its next tree, so a good plan survives the replan instead of being redrawn.
        self.path = torch.zeros(e, m, _KEPT_VERTICES, 2, dtype=torch.float64, device=env.device)
        self.path_mask = torch.zeros(e, m, _KEPT_VERTICES, dtype=torch.bool, device=env.device)

    # ------------------------------------------------------------------ RRT
    def _grow(self, root: torch.Tensor, key: torch.Tensor, chain: torch.Tensor | None = None,
              chain_mask: torch.Tensor | None = None):
        """Batched plain RRT from ``root [E, 2]``: nodes, parents, path costs, depths.

        ``chain [E, R, 2]`` (``chain_mask``: real vertices first) is a path from the root
        that the tree starts with; padding vertices sit on the root (never nearest: ties go
        to the root, index 0) with cost 0, so they are never candidates.
        """
        e = root.shape[0]
        r = 0 if chain is None else chain.shape[1]
        n = self.iterations + 1 + r
        samples = rng.uniform(key, (self.iterations, 2))
        nodes = torch.zeros(e, n, 2, dtype=torch.float64, device=root.device)
        parent = torch.zeros(e, n, dtype=torch.int64, device=root.device)
        cost = torch.zeros(e, n, dtype=torch.float64, device=root.device)
        depth = torch.zeros(e, n, dtype=torch.int64, device=root.device)
        nodes[:, 0] = root
        if r:
            nodes[:, 1 : r + 1] = torch.where(chain_mask.unsqueeze(-1), chain, root.unsqueeze(1))
            seg = (nodes[:, 1 : r + 1] - nodes[:, :r]).norm(dim=-1) * chain_mask
            cost[:, 1 : r + 1] = torch.cumsum(seg, -1)
            steps = torch.arange(1, r + 1, device=root.device)
            parent[:, 1 : r + 1] = torch.where(chain_mask, steps - 1, 0)
            depth[:, 1 : r + 1] = torch.where(chain_mask, steps, 0)
        ar = torch.arange(e, device=root.device)
        for i in range(r, r + self.iterations):
            s = samples[:, i - r]
            d2 = ((nodes[:, : i + 1] - s.unsqueeze(1)) ** 2).sum(-1)
            j = d2.argmin(-1)
            near = nodes[ar, j]
            gap = torch.sqrt(d2[ar, j])
            move = torch.clamp(gap, max=self.step)
            nodes[:, i + 1] = near + (s - near) * (move / gap.clamp_min(1e-12)).unsqueeze(-1)
            parent[:, i + 1], cost[:, i + 1] = j, cost[ar, j] + move
            depth[:, i + 1] = depth[ar, j] + 1
        return nodes, parent, cost, depth

    def _remainder(self, st: EpisodeState, ar: torch.Tensor, a: torch.Tensor):
        """The part of agent ``a``'s last best path beyond the ``execute`` it followed
        (empty at an episode's first decision): ``[E, R, 2]`` and its mask, real first."""
        path, mask = self.path[ar, a], self.path_mask[ar, a] & (st.steps > 0).unsqueeze(-1)
        mask = mask & (polyline_lengths(path, mask) > self.execute + 1e-9)
        order = torch.argsort((~mask).to(torch.int8), dim=-1, stable=True)
        return path.gather(-2, order.unsqueeze(-1).expand(-1, -1, 2)), mask.gather(-1, order)

    def _branches(self, nodes, parent, cost, depth, key):
        """Up to ``max_candidates`` branches with length in [a, b] (else the longest ones),
        as root-to-leaf polylines ``[E, C, D, 2]`` with a vertex mask."""
        e = nodes.shape[0]
        in_band = (cost >= self.a) & (cost <= self.b)
        fallback = ~in_band.any(-1, keepdim=True)  # tree never reached length a
        prio = rng.uniform(key, (nodes.shape[1],))  # random subset when many qualify
        score = torch.where(in_band, prio, -1.0)
        score = torch.where(fallback, cost / cost.amax(-1, keepdim=True).clamp_min(1e-12) - 1.0,
                            score)
        c = min(self.max_candidates, nodes.shape[1])
        top, leaf = score.topk(c, dim=-1)
        valid = (top >= 0) | fallback
        ar = torch.arange(e, device=nodes.device).unsqueeze(-1)
        d = int(depth[ar, leaf].max()) + 1
        chain = torch.zeros(e, c, d, dtype=torch.int64, device=nodes.device)
        cur = leaf
        for t in range(d):  # walk to the root; the root repeats once reached
            chain[:, :, t] = cur
            cur = parent[ar, cur]
        chain = chain.flip(-1)  # root first
        vmask = torch.ones_like(chain, dtype=torch.bool)
        # Drop the repeated roots at the front so each polyline starts at the root once.
        first = d - 1 - depth[ar, leaf]  # index of the root's last copy
        vmask = torch.arange(d, device=nodes.device) >= first.unsqueeze(-1)
        pts = nodes[ar.unsqueeze(-1), chain]
        # Shift valid vertices to the front.
        order = torch.argsort((~vmask).to(torch.int8), dim=-1, stable=True)
        pts = pts.gather(-2, order.unsqueeze(-1).expand(-1, -1, -1, 2))
        vmask = vmask.gather(-1, order)
        pts = torch.where(vmask.unsqueeze(-1), pts, pts[:, :, :1])
        return pts, vmask, valid

    # ------------------------------------------------------------------ act
    def act(self, st: EpisodeState) -> torch.Tensor:
        env, cfg = self.env, self.env.config
        e, m, k = st.mask.shape
        g2, dev = cfg.n_grid, env.device
        ar, held, held_mask, contact, action = self.start(st)
        for a, active in sga_rounds(st):  # one round per deciding agent, all envs at once
            key = rng.derive(self.keys, st.steps, a)
            root = st.roadmap.nodes[ar, st.cur[ar, a]]
            chain = self._remainder(st, ar, a) if self.reuse_plan else (None, None)
            paths, vmask, valid = self._branches(*self._grow(root, rng.derive(key, 1), *chain),
                                                 rng.derive(key, 2))
            pts, pmask = measurement_points(paths, vmask, st.since_sample[ar, a].unsqueeze(-1)
                                            .expand(-1, paths.shape[1]),
                                            cfg.sample_spacing, self.max_points)
            pmask &= valid.unsqueeze(-1)
            # Condition on teammates' plans and remaining edges (those in contact).
            held_pts, held_known = known_commitments(held, held_mask, contact, a)
            plan_pts, plan_known = known_commitments(self.plans, self.plan_mask, contact, a)
            team = torch.cat([held_pts, plan_pts], 1)
            team_mask = torch.cat([held_known, plan_known], 1)
            mu, belief = conditioned_belief(env, st, a, team, team_mask)
            var = belief.fantasy_variance(env.prior, st.query, pts, pmask, n_query=g2)
            tr = interest_trace(mu.unsqueeze(1), var, cfg.interest_beta, cfg.interest_threshold)
            tr = torch.where(valid, tr.to(torch.float64), torch.inf)
            best = tr.argmin(-1)
            # Execute the first `execute` of the best path: nearest feasible neighbour.
            path, pm = paths[ar, best], vmask[ar, best]
            cum = polyline_lengths(path, pm)
            goal = points_at(path, cum, torch.full((e, 1), self.execute, dtype=torch.float64,
                                                   device=dev).minimum(cum.amax(-1, True)))
            nbr_pos = st.roadmap.nodes[ar.unsqueeze(-1), st.nbr[ar, a]]  # [E, k, 2]
            gap = (nbr_pos - goal).norm(dim=-1)
            choice = torch.where(st.mask[ar, a], gap, torch.inf).argmin(-1)
            action[ar[active], a[active]] = choice[active]
            sel = torch.zeros(e, m, dtype=torch.bool, device=dev)
            sel[ar, a] = active
            self.plans = torch.where(sel[..., None, None], pts[ar, best].unsqueeze(1), self.plans)
            self.plan_mask = torch.where(sel[..., None], pmask[ar, best].unsqueeze(1),
                                         self.plan_mask)
            kept = min(_KEPT_VERTICES, path.shape[1])
            keep_path = torch.nn.functional.pad(path[:, :kept], (0, 0, 0, _KEPT_VERTICES - kept))
            keep_mask = torch.nn.functional.pad(pm[:, :kept], (0, _KEPT_VERTICES - kept))
            self.path = torch.where(sel[..., None, None], keep_path.unsqueeze(1), self.path)
            self.path_mask = torch.where(sel[..., None], keep_mask.unsqueeze(1), self.path_mask)
        return action
