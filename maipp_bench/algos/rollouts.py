"""Trajectory rollouts with fantasy measurements: what TI(a, j) samples and scores.

Each deciding agent samples ``a`` trajectories of ``j`` nodes from its policy on its own
belief, adding zero-valued fantasy measurements along them (the reference code's choice;
the risk mask and the risk mean keep the real belief, so a fantasy never makes a risky
node look safe). The rollouts give the Tr(P) each would leave (TI executes the first
move of the best) and the visited nodes, to which the agent fits its broadcast intent.

Used at evaluation (:class:`~maipp_bench.algos.learned.LearnedPolicy`, ``mode: ti``, with
the episode's counter-based noise) and while collecting training data
(:class:`IntentBroadcast`, so the network learns from the intents it will see).
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import torch
from tensordict import TensorDictBase

from maipp_bench.algos.attention import FEATURE_SETS
from maipp_bench.algos.modules import AttentionCore, autocast_to
from maipp_bench.envs.belief import interest_trace
from maipp_bench.envs.dynamics import EPS, edge_points, sample_offsets
from maipp_bench.envs.intent import fit_intent
from maipp_bench.envs.maipp_env import MAIPPEnv
from maipp_bench.envs.roadmap import Roadmap


def check_training_intents(algo: Any) -> None:
    """A clear error for bad ``algo.intent_rollouts`` / ``algo.intent_depth`` values, or
    intents for a network that does not read them (checked before training starts)."""
    a, j = algo.intent_rollouts, algo.intent_depth
    feature_set_columns = FEATURE_SETS.get(algo.feature_set, ())
    if a < 0 or (a > 0 and j < 1):
        raise ValueError(f"algo.intent_rollouts={a}, algo.intent_depth={j}: training intents "
                         f"are TI(a, j) with a >= 1 and j >= 1, or a = 0 for none")
    if a > 0 and "intent" not in feature_set_columns:
        raise ValueError(f"algo.intent_rollouts={a}: feature set {algo.feature_set!r} does "
                         f"not read intents ({list(feature_set_columns)}); set it to 0")


def samples_per_edge(roadmap: Roadmap, spacing: float) -> int:
    """Measurement slots one move along any edge of ``roadmap`` can fill (an upper bound):
    the room a rollout needs per step for its fantasy measurements."""
    longest = float(roadmap.neighbor_dist.masked_fill(~roadmap.neighbor_valid, 0).amax())
    return int(longest / spacing) + 2


@dataclass
class Rollouts:
    """``a`` rollouts of ``j`` steps for each of ``B`` deciding agents."""

    first: torch.Tensor  # [B, a] first slot of each rollout
    trace: torch.Tensor  # [B, a] Tr(P) (float64) the rollout's fantasy measurements leave
    nodes: torch.Tensor  # [B, a * j, 2] positions of the sampled nodes
    valid: torch.Tensor  # [B, a * j] whether the rollout was still moving there

    def best_first(self) -> torch.Tensor:
        """``[B]``: the first slot of the rollout that leaves the least Tr(P)."""
        best = self.trace.argmin(-1, keepdim=True)
        return self.first.gather(1, best).squeeze(-1)

    def reject(self, unsafe: torch.Tensor) -> None:
        """TI's safety layer: a rollout whose first slot is ``unsafe [B, k]`` can no longer
        be best, unless every rollout of its agent is (then TI's choice stands). The layer
        only picks among what the policy sampled; the intent is still fitted to all of it."""
        bad = unsafe.gather(1, self.first)
        self.trace = torch.where(bad & ~bad.all(-1, keepdim=True), torch.inf, self.trace)

    def intent(self, cov_floor: float) -> tuple[torch.Tensor, torch.Tensor]:
        """The Gaussian fitted to all sampled nodes: mean ``[B, 2]``, covariance ``[B, 2, 2]``."""
        return fit_intent(self.nodes, self.valid, cov_floor)


def distinct_rows(key: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """For integer rows ``key [R, c]``: the index of one row per distinct value ``[U]`` and,
    for every row, the position of its value among them ``[R]`` (so ``key[keep][back]``
    equals ``key``)."""
    values, back = torch.unique(key, dim=0, return_inverse=True)
    r = torch.arange(key.shape[0], device=key.device)
    keep = torch.full((values.shape[0],), key.shape[0], dtype=torch.long, device=key.device)
    return keep.scatter_reduce(0, back, r, "amin"), back


def every_row(key: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`distinct_rows` without merging: every row kept."""
    r = torch.arange(key.shape[0], device=key.device)
    return r, r


_merge_paths = True  # read by fantasy_rollouts; set only through path_merging


@contextmanager
def path_merging(on: bool) -> Iterator[None]:
    """Within it, rollouts that sampled the same path share one network pass (``on``, what
    every method does) or each get their own (off: the reference that tests and benchmarks
    compare against; the same bits from more network rows)."""
    global _merge_paths
    before, _merge_paths = _merge_paths, on
    try:
        yield
    finally:
        _merge_paths = before


def fantasy_rollouts(core: AttentionCore, env: MAIPPEnv, rows: TensorDictBase,
                     logits: torch.Tensor, hidden: torch.Tensor, e_idx: torch.Tensor,
                     a_idx: torch.Tensor, gumbel: torch.Tensor,
                     dtype: torch.dtype = torch.float32) -> Rollouts:
    """Rollouts of the deciding agents ``(e_idx, a_idx)`` from the env's current state.

    Args:
        core: the policy network.
        env: the env (its ``episode`` is the state the rows were read from).
        rows: the agents' decision rows (:func:`~maipp_bench.algos.modules.decision_rows`).
        logits, hidden: the network's output on ``rows`` (the first step's distribution and
            the LSTM state after it).
        gumbel: ``[B * a, j, k]`` Gumbel noise (row ``b * a + r``: rollout r of decision b);
            step s samples ``argmax(logits + gumbel[:, s])``.
        dtype: the fantasy beliefs' dtype: float32 (every registered TI method; faster) or
            float64, whose Tr(P) other float kernels round alike far more often
            (docs/protocol.md, "Another CPU").
    """
    cfg, st = env.config, env.episode
    g2 = cfg.n_grid
    b, k = logits.shape
    a, j = gumbel.shape[0] // max(b, 1), gumbel.shape[1]
    if gumbel.shape != (b * a, j, k) or a < 1:
        raise ValueError(f"gumbel noise must be [B * a, j, k] with B = {b}, k = {k}; "
                         f"got {list(gumbel.shape)}")
    rep = lambda x: x.repeat_interleave(a, 0)  # noqa: E731  [B, ...] -> [B * a, ...]
    er, ar = rep(e_idx), rep(a_idx)
    rm = st.roadmap[er]
    nodes = rm.nodes
    g_idx = env.agent_belief_index[a_idx]
    risk_mean = rep(st.belief.mu[e_idx, g_idx, g2:, 1])  # the real risk: mask and UCB
    per_edge = samples_per_edge(st.roadmap, cfg.sample_spacing)
    # Each agent's belief copied once (used slots only), then once per rollout.
    belief = st.belief.gathered((e_idx, g_idx), j * per_edge, dtype, repeats=a)
    query = rep(st.query[e_idx].to(dtype))
    # Float32 inputs, as the network reads them, converted once; the roadmap, and so its
    # position embedding, is the same at every step. The risk column is still summed in
    # the env's dtype, as the env does, and rounded when written.
    obs_dtype = rows.get("node_features").dtype
    feats = rep(rows.get("node_features").float())  # a copy (repeat_interleave): written below
    with autocast_to(core.autocast, query.device):  # as the core's own calls (precision)
        positions = core.net.pos(rows.get("node_encoding").float())  # [B, N, d]: rollout row
    # b * a + r reads positions[b]
    cur, since = rep(rows.get("current_node")), st.since_sample[er, ar]
    pool = st.team_budget[er]
    left = pool - st.budget_used[er]
    nbr, nbr_len = rep(rows.get("neighbors")), st.nbr_len[er, ar]
    h = rep(hidden)
    alive = torch.ones(b * a, dtype=torch.bool, device=env.device)
    step_logits = rep(logits)
    # Each rollout's deciding agent, then the slots it sampled so far.
    path = torch.arange(b, device=env.device).repeat_interleave(a).unsqueeze(-1)
    visited, visited_ok = [], []
    for step in range(j):
        if step > 0:  # the policy's input after the fantasy measurements so far
            sd = belief.sigma2[:, g2:].clamp_min(0).sqrt()
            feats[..., 2] = belief.mu[:, g2:, 0]
            feats[..., 3] = sd
            if cfg.risk_enabled:
                feats[..., 4] = risk_mean.to(obs_dtype) + cfg.risk_beta * sd.to(obs_dtype)
            nbr = rm.neighbors.gather(1, cur.view(-1, 1, 1).expand(-1, 1, k)).squeeze(1)
            nbr_len = rm.neighbor_dist.gather(1, cur.view(-1, 1, 1).expand(-1, 1, k))
            nbr_len = nbr_len.squeeze(1)
            ok = rm.neighbor_valid.gather(1, cur.view(-1, 1, 1).expand(-1, 1, k)).squeeze(1)
            ok &= nbr_len <= left.unsqueeze(-1) + EPS
            if cfg.risk_enabled:
                ok &= risk_mean.gather(1, nbr) <= cfg.risk_mask_threshold
            alive &= ok.any(-1)
            mask = ok | ~alive.unsqueeze(-1)
            budget = (left / pool).clamp(0, 1).unsqueeze(-1)
            # Rollouts of one agent that sampled the same moves so far hold the same state,
            # so the network runs once per distinct path (a peaked policy repeats itself).
            keep, back = (distinct_rows if _merge_paths else every_row)(path)
            step_logits, _, h = core(feats[keep], None, cur[keep], budget[keep],
                                     nbr[keep], mask[keep], h[keep], positions[keep // a])
            step_logits, h = step_logits[back], h[back]
        choice = (step_logits + gumbel[:, step]).argmax(-1)
        path = torch.cat([path, choice.unsqueeze(-1)], 1)
        nxt = nbr.gather(1, choice.unsqueeze(-1)).squeeze(-1)
        length = torch.where(alive, nbr_len.gather(1, choice.unsqueeze(-1)).squeeze(-1), 0.0)
        offsets, valid, since = sample_offsets(since, length, cfg.sample_spacing)
        src = nodes.gather(1, cur.view(-1, 1, 1).expand(-1, 1, 2)).squeeze(1)
        dst = nodes.gather(1, nxt.view(-1, 1, 1).expand(-1, 1, 2)).squeeze(1)
        pts = edge_points(src, dst, length, offsets).to(dtype)
        zeros = torch.zeros(*pts.shape[:-1], 2, dtype=dtype, device=env.device)
        belief.add(env.prior, query, pts, zeros, valid & alive.unsqueeze(-1))
        left = left - length
        visited.append(dst)
        visited_ok.append(alive.clone())
        cur = torch.where(alive, nxt, cur)
    weight = st.grid_weight[er] if cfg.aoi_enabled else None
    trace = interest_trace(belief.mu[:, :g2, 0].double(), belief.sigma2[:, :g2].double(),
                           cfg.interest_beta, cfg.interest_threshold, weight)
    return Rollouts(first=path[:, 1].view(b, a), trace=trace.view(b, a),
                    nodes=torch.stack(visited, 1).view(b, a * j, 2),
                    valid=torch.stack(visited_ok, 1).view(b, a * j))


def broadcast(td: TensorDictBase, env: MAIPPEnv, e_idx: torch.Tensor, a_idx: torch.Tensor,
              mean: torch.Tensor, cov: torch.Tensor) -> None:
    """Write the deciding agents' intents into ``td`` as the env's intent input
    (``("agents", "intent", "mean" | "cov")``, ``[E, m, 2]`` / ``[E, m, 2, 2]``); the env
    takes them from deciding agents only."""
    e, m = env.episode.deciding.shape
    dt, dev = env.episode.intent_mean.dtype, env.device
    intent_mean = torch.zeros(e, m, 2, dtype=dt, device=dev)
    intent_cov = torch.eye(2, dtype=dt, device=dev).repeat(e, m, 1, 1)
    intent_mean[e_idx, a_idx], intent_cov[e_idx, a_idx] = mean.to(dt), cov.to(dt)
    td.set(("agents", "intent", "mean"), intent_mean)
    td.set(("agents", "intent", "cov"), intent_cov)


class IntentBroadcast:
    """Training's trajectory intents: each deciding agent samples TI(a, j) rollouts from the
    policy being trained and broadcasts the Gaussian fitted to them, as it will at
    evaluation, so the network learns from its teammates' intents (without this the
    intent feature is zero in every training step). The executed action stays the
    policy's own sample (PPO's data must come from the policy it scores); the noise is
    torch's global generator, which training seeds per update.

    Args:
        env: the base :class:`MAIPPEnv` the collector steps.
        core: the network being trained.
        rollouts, depth: TI(a, j).
    """

    KEYS = [("agents", "intent", "mean"), ("agents", "intent", "cov")]

    def __init__(self, env: MAIPPEnv, core: AttentionCore, rollouts: int, depth: int) -> None:
        if rollouts < 1 or depth < 1:
            raise ValueError(f"training intents need TI(a, j) with a, j >= 1, got "
                             f"({rollouts}, {depth})")
        self.env, self.core, self.rollouts, self.depth = env, core, rollouts, depth

    @torch.no_grad()
    def __call__(self, td: TensorDictBase, rows: TensorDictBase | None, e_idx: torch.Tensor,
                 a_idx: torch.Tensor) -> None:
        """Write the intents of the deciding agents ``(e_idx, a_idx)`` (their decision
        ``rows`` after the actor: ``logits``, ``next_hidden``) into ``td``; with no deciding
        agent (``rows`` None) the keys are still written, so every frame has them."""
        if rows is None:
            none = torch.zeros(0, 2, 2, dtype=torch.float64, device=self.env.device)
            broadcast(td, self.env, e_idx, a_idx, none[:, 0], none)
            return
        logits = rows.get("logits")
        u = torch.rand(logits.shape[0] * self.rollouts, self.depth, logits.shape[-1],
                       dtype=torch.float64, device=logits.device)
        out = fantasy_rollouts(self.core, self.env, rows, logits, rows.get("next_hidden"),
                               e_idx, a_idx, gumbel_noise(u))
        broadcast(td, self.env, e_idx, a_idx, *out.intent(self.env.config.intent_cov_floor))


def gumbel_noise(u: torch.Tensor) -> torch.Tensor:
    """Gumbel(0, 1) noise in float32 from uniforms (clamped away from 0 and 1)."""
    return -torch.log(-torch.log(u.clamp(1e-12, 1 - 1e-12))).float()
