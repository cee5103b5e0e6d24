"""``greedy``: myopic sequential greedy assignment (SGA) on fantasy measurements.

Each deciding agent takes the neighbour whose edge gives the largest drop of Tr(P) per
unit distance, measured on its own belief by fantasy measurements along the edge, after
the measurements its teammates have already committed to: the rest of every moving
teammate's edge (teammates it can communicate with) and the edges chosen by deciding
agents ranked before it at this event (SGA order = agent index). No GP is refit.
"""

from __future__ import annotations

import torch

from maipp_bench.algos.base import (
    PlannerPolicy,
    append_points,
    candidate_points,
    conditioned_belief,
    known_commitments,
    sga_rounds,
)
from maipp_bench.algos.registry import register_policy
from maipp_bench.envs.belief import interest_trace
from maipp_bench.envs.maipp_env import EpisodeState, MAIPPEnv


@register_policy("greedy")
class GreedyPolicy(PlannerPolicy):
    """Tr(P) drop per unit distance, one SGA round per deciding agent (batched over envs)."""

    def __init__(self, env: MAIPPEnv, seeds: torch.Tensor, tie_break: float = 1e-9) -> None:
        super().__init__(env, seeds)
        self.tie_break = tie_break

    def act(self, st: EpisodeState) -> torch.Tensor:
        env, cfg = self.env, self.env.config
        e, m, k = st.mask.shape
        g2 = cfg.n_grid
        ar, held, held_mask, contact, action = self.start(st)
        cand, cand_mask = candidate_points(env, st)  # [E, m, k, R, 2]
        noise = self.uniforms(st, (m, k))
        for a, active in sga_rounds(st):  # one round per deciding agent, all envs at once
            # Condition on the teammates' committed points this agent knows of.
            team, team_mask = known_commitments(held, held_mask, contact, a)
            mu, belief = conditioned_belief(env, st, a, team, team_mask)
            var = belief.fantasy_variance(env.prior, st.query, cand[ar, a], cand_mask[ar, a],
                                          n_query=g2)
            beta, th = cfg.interest_beta, cfg.interest_threshold
            tr = interest_trace(mu.unsqueeze(1), var, beta, th)  # [E, k]
            tr0 = interest_trace(mu, belief.sigma2[:, :g2], beta, th)  # [E]
            length = st.nbr_len[ar, a].clamp_min(1e-9)
            gain = (tr0.unsqueeze(-1) - tr).to(torch.float64) / length
            score = gain + self.tie_break * noise[ar, a]
            choice = torch.where(st.mask[ar, a], score, -torch.inf).argmax(-1)
            action[ar[active], a[active]] = choice[active]
            # Later agents condition on this agent's chosen edge.
            chosen = cand[ar, a, choice]  # [E, R, 2]
            chosen_mask = cand_mask[ar, a, choice] & active.unsqueeze(-1)
            held, held_mask = append_points(held, held_mask, a, chosen, chosen_mask)
        return action

