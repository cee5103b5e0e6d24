"""Learned methods at evaluation time: greedy decoding or trajectory intent TI(a, j).

``mode: greedy`` takes the policy's most likely slot (CAtNIPP+Greedy, Ours+Greedy).
``mode: ti`` is the paper's trajectory intent (PROTOCOL: Communication and intent):
each deciding agent samples ``rollouts`` trajectories of ``depth`` nodes from its policy
on its own belief, with zero-valued fantasy measurements along them (the reference
code's choice; the risk mask and the risk mean keep the real belief, so a fantasy never
makes a risky node look safe), scores each by the Tr(P) it would leave, executes the
first move of the best, and broadcasts the Gaussian fitted to all sampled nodes as its
intent. Sampling uses the method seed of each episode (Gumbel-max on counter-based
uniforms), so episodes do not depend on the batch. Rollouts of several deciding agents
of one event run in parallel and do not see each other's new intents.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase

from maipp_bench.algos.base import PlannerPolicy
from maipp_bench.algos.checkpoint import load_core
from maipp_bench.algos.modules import AttentionCore, decision_rows
from maipp_bench.algos.registry import register_policy
from maipp_bench.envs.belief import interest_trace
from maipp_bench.envs.dynamics import EPS, edge_points, sample_offsets
from maipp_bench.envs.intent import fit_intent
from maipp_bench.envs.maipp_env import MAIPPEnv
from maipp_bench.envs.roadmap import Roadmap, laplacian_encoding

MODES = ("greedy", "ti")


def samples_per_edge(roadmap: Roadmap, spacing: float) -> int:
    """Measurement slots one move along any edge of ``roadmap`` can fill (an upper bound):
    the room a rollout needs per step for its fantasy measurements."""
    longest = float(roadmap.neighbor_dist.masked_fill(~roadmap.neighbor_valid, 0).amax())
    return int(longest / spacing) + 2


@register_policy("attention")
class LearnedPolicy(PlannerPolicy):
    """A trained attention policy (a checkpoint) acting in a protocol env.

    Args:
        env, seeds: as every policy (see :class:`~maipp_bench.algos.base.PlannerPolicy`).
        checkpoint: path or shipped name (``"ours"``); ignored when ``core`` is given.
        mode: ``"greedy"`` or ``"ti"``.
        rollouts, depth: TI(a, j) (paper: TI(8, 5)).
        core: an in-memory network (periodic evaluation during training).
    """

    # 2: the encoder's last layer runs only at the rows the decoder reads (same function,
    # float rounding differs, so rows of version 1 are recomputed, not mixed in).
    version = 2

    def __init__(self, env: MAIPPEnv, seeds: torch.Tensor, checkpoint: str | None = None,
                 mode: str = "greedy", rollouts: int = 8, depth: int = 5,
                 core: AttentionCore | None = None) -> None:
        super().__init__(env, seeds)
        if mode not in MODES:
            raise ValueError(f"mode={mode!r}; valid: {list(MODES)}")
        if rollouts < 1 or depth < 1:
            raise ValueError(f"TI(a, j) needs a >= 1 and j >= 1, got ({rollouts}, {depth})")
        if core is None:
            if checkpoint is None:
                raise ValueError("a learned method needs a checkpoint (path or shipped name)")
            core, _ = load_core(checkpoint, env.device)
        self.core, self.mode, self.rollouts, self.depth = core, mode, rollouts, depth
        self.hidden: torch.Tensor | None = None
        self.encoding: torch.Tensor | None = None

    def _track_episodes(self) -> None:
        """LSTM states and roadmap encodings of the episodes that just started."""
        st = self.env.episode
        e, m = st.cur.shape
        fresh = st.steps == 0
        if self.hidden is None:
            self.hidden = torch.zeros(e, m, 2, self.core.hidden_dim, device=self.env.device)
            self.encoding = torch.zeros(e, st.roadmap.nodes.shape[1], self.core.net.cfg.pe_dim,
                                        device=self.env.device)
        if bool(fresh.any()):
            rm = st.roadmap[fresh]
            self.hidden[fresh] = 0.0
            self.encoding[fresh] = laplacian_encoding(
                rm.neighbors, rm.neighbor_valid, self.core.net.cfg.pe_dim).float()

    @torch.no_grad()
    def __call__(self, td: TensorDictBase) -> TensorDictBase:
        self._track_episodes()
        st = self.env.episode
        e, m = st.deciding.shape
        e_idx, a_idx = st.deciding.nonzero(as_tuple=True)
        action = torch.zeros(e, m, dtype=torch.int64, device=self.env.device)
        view = td.clone(False)
        view.set("node_encoding", self.encoding)
        rows = decision_rows(view, e_idx, a_idx, self.hidden)
        if e_idx.numel():
            logits, _, hidden = self.core(*(rows.get(k) for k in (
                "node_features", "node_encoding", "current_node", "budget", "neighbors",
                "action_mask", "hidden")))
            self.hidden[e_idx, a_idx] = hidden
            if self.mode == "greedy":
                action[e_idx, a_idx] = logits.argmax(-1)
            else:
                choice, mean, cov = self._trajectory_intent(rows, logits, hidden, e_idx, a_idx)
                action[e_idx, a_idx] = choice
                dt = st.intent_mean.dtype
                intent_mean = torch.zeros(e, m, 2, dtype=dt, device=self.env.device)
                intent_cov = torch.eye(2, dtype=dt, device=self.env.device).repeat(e, m, 1, 1)
                intent_mean[e_idx, a_idx], intent_cov[e_idx, a_idx] = mean.to(dt), cov.to(dt)
                td.set(("agents", "intent", "mean"), intent_mean)
                td.set(("agents", "intent", "cov"), intent_cov)
        td.set(("agents", "action"), action)
        return td

    def _trajectory_intent(self, rows, logits, hidden, e_idx, a_idx):
        """TI(a, j) for B deciding agents: first slots ``[B]``, intent mean and covariance."""
        env, cfg, st = self.env, self.env.config, self.env.episode
        a, j, g2 = self.rollouts, self.depth, cfg.n_grid
        b, k = logits.shape
        rep = lambda x: x.repeat_interleave(a, 0)  # noqa: E731  [B, ...] -> [B * a, ...]
        u = self.uniforms(st, (self.env.n_agents, a, j, k))[e_idx, a_idx]  # [B, a, j, k]
        # Row b * a + r is rollout r of decision b (the order of repeat_interleave).
        gumbel = -torch.log(-torch.log(u.clamp(1e-12, 1 - 1e-12))).float().reshape(b * a, j, k)

        er, ar = rep(e_idx), rep(a_idx)
        rm = st.roadmap[er]
        nodes = rm.nodes
        g_idx = env.agent_belief_index[a_idx]
        risk_mean = rep(st.belief.mu[e_idx, g_idx, g2:, 1])  # the real risk: mask and UCB
        per_edge = samples_per_edge(st.roadmap, cfg.sample_spacing)
        # Each agent's belief copied once (used slots only), then once per rollout.
        belief = st.belief.gathered((e_idx, g_idx), j * per_edge, torch.float32, repeats=a)
        query = rep(st.query[e_idx].float())
        feats, enc = rep(rows.get("node_features")).clone(), rep(rows.get("node_encoding"))
        cur, since = rep(rows.get("current_node")), st.since_sample[er, ar]
        pool = st.team_budget[er]
        left = pool - st.budget_used[er]
        nbr, nbr_len = rep(rows.get("neighbors")), st.nbr_len[er, ar]
        h = rep(hidden)
        alive = torch.ones(b * a, dtype=torch.bool, device=env.device)
        step_logits = rep(logits)
        first = None
        visited, visited_ok = [], []
        for step in range(j):
            if step > 0:  # the policy's input after the fantasy measurements so far
                sd = belief.sigma2[:, g2:].clamp_min(0).sqrt().to(feats.dtype)
                feats[..., 2] = belief.mu[:, g2:, 0].to(feats.dtype)
                feats[..., 3] = sd
                if cfg.risk_enabled:
                    feats[..., 4] = risk_mean.to(feats.dtype) + cfg.risk_beta * sd
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
                step_logits, _, h = self.core(feats, enc, cur, budget, nbr, mask, h)
            choice = (step_logits + gumbel[:, step]).argmax(-1)
            if first is None:
                first = choice
            nxt = nbr.gather(1, choice.unsqueeze(-1)).squeeze(-1)
            length = torch.where(alive, nbr_len.gather(1, choice.unsqueeze(-1)).squeeze(-1), 0.0)
            offsets, valid, since = sample_offsets(since, length, cfg.sample_spacing)
            src = nodes.gather(1, cur.view(-1, 1, 1).expand(-1, 1, 2)).squeeze(1)
            dst = nodes.gather(1, nxt.view(-1, 1, 1).expand(-1, 1, 2)).squeeze(1)
            pts = edge_points(src, dst, length, offsets).float()
            zeros = torch.zeros(*pts.shape[:-1], 2, dtype=torch.float32, device=env.device)
            belief.add(env.prior, query, pts, zeros, valid & alive.unsqueeze(-1))
            left = left - length
            visited.append(dst)
            visited_ok.append(alive.clone())
            cur = torch.where(alive, nxt, cur)
        weight = st.grid_weight[er] if cfg.aoi_enabled else None
        trace = interest_trace(belief.mu[:, :g2, 0].double(), belief.sigma2[:, :g2].double(),
                               cfg.interest_beta, cfg.interest_threshold, weight)
        best = trace.view(b, a).argmin(-1)
        choice = first.view(b, a).gather(1, best.unsqueeze(-1)).squeeze(-1)
        points = torch.stack(visited, 1).view(b, a * j, 2)
        mean, cov = fit_intent(points, torch.stack(visited_ok, 1).view(b, a * j),
                               cfg.intent_cov_floor)
        return choice, mean, cov
