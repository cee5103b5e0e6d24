"""``random``: a uniform choice among the allowed slots: the floor every method must beat."""

from __future__ import annotations

import torch

from maipp_bench.algos.base import PlannerPolicy
from maipp_bench.algos.registry import register_policy
from maipp_bench.envs.maipp_env import EpisodeState


@register_policy("random")
class RandomPolicy(PlannerPolicy):
    """Uniform over each deciding agent's feasibility mask (seeded per episode)."""

    def act(self, st: EpisodeState) -> torch.Tensor:
        e, m, k = st.mask.shape
        u = self.uniforms(st, (m, k))
        return torch.where(st.mask, u, -1.0).argmax(-1)
