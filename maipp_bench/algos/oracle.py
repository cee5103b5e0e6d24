"""``oracle``: a clairvoyant yardstick, not a competitor.

It knows the true fields, so it can predict what its measurements will read, hence the
future belief mean, hence the future high-interest region X_I and the metric Tr(P)
itself, not only its variance part. It plans non-myopically: for each deciding agent (SGA
order) it scores ``walks_per_slot`` random roadmap walks of ``depth`` edges behind every
feasible first edge by the drop of the predicted Tr(P) per unit distance (fantasy
measurements carrying the true values along the walk, after its teammates' committed
points, truncated at the remaining budget) and takes the first edge of the best walk. It
shows how far the others are from good, not what is achievable without the fields.
"""

from __future__ import annotations

import torch

from maipp_bench.algos.base import (
    PlannerPolicy,
    append_points,
    conditioned_belief,
    known_commitments,
    sga_rounds,
)
from maipp_bench.algos.paths import measurement_points, polyline_lengths
from maipp_bench.algos.registry import register_policy
from maipp_bench.envs import rng
from maipp_bench.envs.belief import interest_trace
from maipp_bench.envs.maipp_env import EpisodeState, MAIPPEnv


@register_policy("oracle")
class OraclePolicy(PlannerPolicy):
    """Random-walk lookahead on the exact future metric (clairvoyant)."""

    def __init__(self, env: MAIPPEnv, seeds: torch.Tensor, depth: int = 3,
                 walks_per_slot: int = 2) -> None:
        super().__init__(env, seeds)
        if depth < 1 or walks_per_slot < 1:
            raise ValueError("oracle: depth and walks_per_slot must be >= 1")
        self.depth, self.walks = depth, walks_per_slot

    def act(self, st: EpisodeState) -> torch.Tensor:
        env, cfg = self.env, self.env.config
        e, m, k = st.mask.shape
        g2 = cfg.n_grid
        ar, held, held_mask, contact, action = self.start(st)
        left = (st.team_budget - st.budget_used).clamp_min(0)
        max_pts = int((self.depth * st.roadmap.neighbor_dist.masked_fill(
            ~st.roadmap.neighbor_valid, 0).amax() + cfg.sample_spacing) / cfg.sample_spacing) + 1
        for a, active in sga_rounds(st):  # one round per deciding agent, all envs at once
            walks, wmask, first = self._walks(st, a, rng.derive(self.keys, st.steps, a))
            # Truncate each walk at the remaining team budget.
            cum = polyline_lengths(walks, wmask)
            wmask = wmask & (cum <= left.view(e, 1, 1) + 1e-9)
            length = polyline_lengths(walks, wmask).amax(-1).clamp_min(1e-9)
            since = st.since_sample[ar, a].unsqueeze(-1).expand(-1, walks.shape[1])
            pts, pmask = measurement_points(walks, wmask, since, cfg.sample_spacing, max_pts)
            team, team_mask = known_commitments(held, held_mask, contact, a)
            _, belief = conditioned_belief(env, st, a, team, team_mask, self._truth(st, team))
            values = self._truth(st, pts.flatten(1, 2)).view(pmask.shape)
            mean, var = belief.fantasy_posterior(env.prior, st.query, pts, values, pmask,
                                                 n_query=g2)
            beta, th = cfg.interest_beta, cfg.interest_threshold
            base = interest_trace(belief.mu[:, :g2, 0], belief.sigma2[:, :g2], beta, th)
            after = interest_trace(mean, var, beta, th)
            score = (base.unsqueeze(-1) - after).to(torch.float64) / length
            ok = st.mask[ar, a].gather(-1, first)
            best = torch.where(ok, score, -torch.inf).argmax(-1)
            choice = first[ar, best]
            action[ar[active], a[active]] = choice[active]
            chosen_mask = pmask[ar, best] & active.unsqueeze(-1)
            held, held_mask = append_points(held, held_mask, a, pts[ar, best], chosen_mask)
        return action

    def _truth(self, st: EpisodeState, points: torch.Tensor) -> torch.Tensor:
        """The true interest signal at ``points [E, P, 2]`` (what a measurement reads)."""
        return st.world.signal(points.to(torch.float64), self.env.config.risk_mix_lambda)

    def _walks(self, st: EpisodeState, a: torch.Tensor, key: torch.Tensor):
        """``walks_per_slot`` random walks of ``depth`` edges behind every slot of agent a:
        polylines ``[E, k*w, depth+1, 2]``, vertex mask, and the first slot of each."""
        rm = st.roadmap
        e, _, k = rm.neighbors.shape
        ar = torch.arange(e, device=rm.nodes.device).unsqueeze(-1)
        w = self.walks
        first = torch.arange(k, device=rm.nodes.device).repeat_interleave(w).expand(e, -1)
        node = st.nbr[ar.squeeze(-1), a].repeat_interleave(w, dim=-1)  # [E, k*w]
        seq = [st.cur[ar.squeeze(-1), a].unsqueeze(-1).expand(-1, k * w), node]
        vmask = [torch.ones_like(node, dtype=torch.bool), rm.neighbor_valid[
            ar.squeeze(-1), st.cur[ar.squeeze(-1), a]].repeat_interleave(w, dim=-1)]
        for d in range(1, self.depth):
            u = rng.uniform(rng.derive(key, d), (k * w, k))
            valid = rm.neighbor_valid[ar, node]  # [E, k*w, k]
            slot = torch.where(valid, u, -1.0).argmax(-1)
            node = rm.neighbors[ar, node, slot]
            seq.append(node)
            vmask.append(vmask[-1] & valid.any(-1))
        nodes = torch.stack(seq, -1)  # [E, k*w, depth+1]
        pts = rm.nodes[ar.unsqueeze(-1), nodes]
        return pts, torch.stack(vmask, -1), first
