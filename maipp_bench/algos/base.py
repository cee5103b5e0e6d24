"""Planner policies: batched decision makers that read the env's belief through its API."""

from __future__ import annotations

from collections.abc import Iterator
from typing import NamedTuple

import torch
from tensordict import TensorDictBase

from maipp_bench.envs import rng
from maipp_bench.envs.belief import GPBelief
from maipp_bench.envs.dynamics import edge_points, sample_offsets
from maipp_bench.envs.maipp_env import EpisodeState, MAIPPEnv


class PlanStart(NamedTuple):
    """What every SGA planner sets up before its rounds (see :meth:`PlannerPolicy.start`)."""

    ar: torch.Tensor  # [E] env indices
    held: torch.Tensor  # [E, m, R, 2] each agent's committed measurement points
    held_mask: torch.Tensor  # [E, m, R]
    contact: torch.Tensor  # [E, m, m] communication components
    action: torch.Tensor  # [E, m] slots, zero for agents that do not decide


class PlannerPolicy:
    """Base of non-learned methods: ``policy(td)`` writes ``("agents", "action")``.

    Args:
        env: the batched env the policy acts in (it reads ``env.episode``).
        seeds: ``[E]`` int64 method seeds, one per episode; all randomness of a policy is
            keyed by (seed, step), so an episode's actions do not depend on the batch.
    """

    version = 1  # bump when a subclass's algorithm changes (see MethodSpec.fingerprint)

    def __init__(self, env: MAIPPEnv, seeds: torch.Tensor) -> None:
        self.env = env
        self.keys = rng.derive(rng.seed_key(0x5EED, env.device), seeds.to(env.device))

    def __call__(self, td: TensorDictBase) -> TensorDictBase:
        td.set(("agents", "action"), self.act(self.env.episode))
        return td

    def act(self, st: EpisodeState) -> torch.Tensor:
        """Slots ``[E, m]`` for the deciding agents (others are ignored by the env)."""
        raise NotImplementedError

    def start(self, st: EpisodeState) -> PlanStart:
        """Committed points, contacts and an empty action table for this decision event."""
        e, m = st.deciding.shape
        held, held_mask = committed_points(self.env, st)
        return PlanStart(torch.arange(e, device=self.env.device), held, held_mask,
                         self.env.in_contact(),
                         torch.zeros(e, m, dtype=torch.int64, device=self.env.device))

    def uniforms(self, st: EpisodeState, shape: tuple[int, ...], tag: int = 0) -> torch.Tensor:
        """Per-episode uniforms ``[E, *shape]`` keyed by (seed, step, tag)."""
        return rng.uniform(rng.derive(self.keys, st.steps, tag), shape)


def candidate_points(env: MAIPPEnv, st: EpisodeState) -> tuple[torch.Tensor, torch.Tensor]:
    """Measurement points each agent would take on each of its neighbour edges.

    Returns ``points [E, m, k, R, 2]`` and ``mask [E, m, k, R]`` (offsets carry each
    agent's distance since its last measurement, exactly as the env measures).
    """
    nodes = st.roadmap.nodes
    e, m, k = st.nbr.shape
    since = st.since_sample.unsqueeze(-1).expand(e, m, k)
    offsets, mask, _ = sample_offsets(since, st.nbr_len, env.config.sample_spacing)
    src = st.edge_ends()[0].unsqueeze(2).expand(e, m, k, 2)
    dst = nodes.gather(1, st.nbr.reshape(e, -1, 1).expand(-1, -1, 2)).view(e, m, k, 2)
    return edge_points(src, dst, st.nbr_len, offsets), mask


def committed_points(env: MAIPPEnv, st: EpisodeState) -> tuple[torch.Tensor, torch.Tensor]:
    """Measurement points still ahead of each moving agent on its current edge.

    Returns ``points [E, m, R, 2]`` and ``mask [E, m, R]`` (empty for resting agents).
    """
    left = torch.where(st.edge_len > 0, st.edge_len - st.progress, 0.0)
    offsets, mask, _ = sample_offsets(st.since_sample, left, env.config.sample_spacing)
    src, dst = st.edge_ends()
    return edge_points(src, dst, st.edge_len, st.progress.unsqueeze(-1) + offsets), mask


def append_points(
    held: torch.Tensor, held_mask: torch.Tensor, a: torch.Tensor, pts: torch.Tensor,
    mask: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Replace agent ``a[e]``'s committed points by ``pts [E, R, 2]`` where ``mask`` has any
    point (padding both to a common length)."""
    e, m, r0, _ = held.shape
    r = max(r0, pts.shape[1])
    pad = torch.nn.functional.pad
    held, held_mask = pad(held, (0, 0, 0, r - r0)), pad(held_mask, (0, r - r0))
    pts, mask = pad(pts, (0, 0, 0, r - pts.shape[1])), pad(mask, (0, r - mask.shape[1]))
    sel = torch.zeros(e, m, dtype=torch.bool, device=held.device)
    sel[torch.arange(e, device=held.device), a] = True
    sel = sel & mask.any(-1, keepdim=True)
    held = torch.where(sel[..., None, None], pts.unsqueeze(1), held)
    held_mask = torch.where(sel[..., None], mask.unsqueeze(1), held_mask)
    return held, held_mask


def conditioned_belief(
    env: MAIPPEnv,
    st: EpisodeState,
    a: torch.Tensor,
    points: torch.Tensor,
    mask: torch.Tensor,
    values: torch.Tensor | None = None,
    dtype: torch.dtype = torch.float32,
) -> tuple[torch.Tensor, GPBelief]:
    """Agent ``a[e]``'s belief in every env, copied in ``dtype`` and conditioned on the
    teammates' committed measurement ``points [E, P, 2]`` (``mask [E, P]``).

    Returns the agent's current interest mean on the grid ``[E, G2]`` (before any fantasy)
    and the conditioned copy. ``values [E, P]`` are what the points would read: variances
    do not depend on them, so planners that only need variances leave them at zero.
    """
    ar = torch.arange(st.batch_size[0], device=env.device)
    belief = st.belief[ar, env.agent_belief_index[a]]
    mu = belief.mu[:, : env.config.n_grid, 0].to(dtype)
    belief = belief.grown(points.shape[1], dtype)
    y = torch.zeros(points.shape[:-1], dtype=dtype, device=env.device) if values is None \
        else values.to(dtype)
    belief.add(env.prior, st.query, points, y.unsqueeze(-1).expand(-1, -1, 2), mask)
    return mu, belief


def sga_rounds(st: EpisodeState) -> Iterator[tuple[torch.Tensor, torch.Tensor]]:
    """Sequential greedy assignment, batched over envs: round r yields the r-th deciding
    agent ``a [E]`` of every env (agent-index priority) and ``active [E]`` (env has one).
    Usually a single round, since decisions are asynchronous."""
    rank = torch.cumsum(st.deciding.to(torch.int64), -1) - 1
    rounds = int(st.deciding.sum(-1).max()) if bool(st.deciding.any()) else 0
    for r in range(rounds):
        who = st.deciding & (rank == r)
        yield who.to(torch.int64).argmax(-1), who.any(-1)


def teammates_of(contact: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
    """``[E, m]``: the agents agent ``a[e]`` is in contact with, itself excluded."""
    e, m, _ = contact.shape
    ar = torch.arange(e, device=contact.device)
    return contact[ar, a] & (torch.arange(m, device=contact.device) != a.unsqueeze(-1))


def known_commitments(
    held: torch.Tensor, held_mask: torch.Tensor, contact: torch.Tensor, a: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """The committed points of agent ``a[e]``'s teammates in contact, flattened over agents:
    ``[E, m*R, 2]`` and their mask."""
    known = teammates_of(contact, a)
    return held.flatten(1, 2), (held_mask & known.unsqueeze(-1)).flatten(1, 2)
