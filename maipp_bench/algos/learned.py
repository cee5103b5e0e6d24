"""Learned methods at evaluation time: greedy decoding or trajectory intent TI(a, j).

``mode: greedy`` takes the policy's most likely slot (CAtNIPP+Greedy, Ours+Greedy).
``mode: ti`` is the paper's trajectory intent (PROTOCOL: Communication and intent):
each deciding agent samples ``rollouts`` trajectories of ``depth`` nodes from its policy
on its own belief with fantasy measurements (:mod:`maipp_bench.algos.rollouts`), executes
the first move of the one that leaves the least Tr(P), and broadcasts the Gaussian fitted
to all sampled nodes as its intent. Sampling uses the method seed of each episode
(Gumbel-max on counter-based uniforms), so episodes do not depend on the batch. Rollouts
of several deciding agents of one event run in parallel and do not see each other's new
intents.
"""

from __future__ import annotations

import inspect
from collections.abc import Mapping
from typing import Any

import torch
from tensordict import TensorDictBase

from maipp_bench.algos.base import PlannerPolicy
from maipp_bench.algos.checkpoint import load_core
from maipp_bench.algos.modules import AttentionCore, decision_rows
from maipp_bench.algos.registry import register_policy
from maipp_bench.algos.rollouts import broadcast, fantasy_rollouts, gumbel_noise
from maipp_bench.envs.maipp_env import MAIPPEnv
from maipp_bench.envs.roadmap import laplacian_encoding

MODES = ("greedy", "ti")
FANTASY_DTYPES = {"float32": torch.float32, "float64": torch.float64}


@register_policy("attention")
class LearnedPolicy(PlannerPolicy):
    """A trained attention policy (a checkpoint) acting in a protocol env.

    Args:
        env, seeds: as every policy (see :class:`~maipp_bench.algos.base.PlannerPolicy`).
        checkpoint: path or shipped name (``"ours"``); ignored when ``core`` is given.
        mode: ``"greedy"`` or ``"ti"``.
        rollouts, depth: TI(a, j) (paper: TI(8, 5)).
        intents: whether TI broadcasts its intents (False: a diagnostic that plans with TI
            but tells the teammates nothing, to measure what intents are worth).
        safe_risk, safe_beta: TI's safety layer (paper: a layer that rejects candidate
            trajectories which may enter non-recoverable terrain): a rollout whose first node
            has risk belief ``mu_rk + safe_beta * sigma_rk > safe_risk`` cannot be chosen
            unless all of them have (the env's mask stays the hard rule); the intent is
            still fitted to every sampled rollout, as without the layer. A buffer below
            the mask's threshold (0.7), because true risk above the trap threshold hides
            behind beliefs below it. None: no layer; without risk it has nothing to do.
        fantasy_dtype: ``"float32"`` (default) or ``"float64"``: the dtype of TI's fantasy
            beliefs. float32 is faster (float64 plans 1.12-1.14x slower on one core), but
            under MKL's default kernels another CPU's float32 rounding can flip a decision
            where a cell sits at the interest threshold; eval pins MKL's CPU-independent
            kernels (maipp_bench/kernels.py; docs/protocol.md, "Another CPU").
        core: an in-memory network (periodic evaluation during training).
    """

    # 2: the encoder's last layer runs only at the rows the decoder reads (same function,
    # float rounding differs, so rows of version 1 are recomputed, not mixed in).
    version = 2

    def __init__(self, env: MAIPPEnv, seeds: torch.Tensor, checkpoint: str | None = None,
                 mode: str = "greedy", rollouts: int = 8, depth: int = 5,
                 intents: bool = True, safe_risk: float | None = None, safe_beta: float = 0.0,
                 fantasy_dtype: str = "float32", core: AttentionCore | None = None) -> None:
        super().__init__(env, seeds)
        if mode not in MODES:
            raise ValueError(f"mode={mode!r}; valid: {list(MODES)}")
        if rollouts < 1 or depth < 1:
            raise ValueError(f"TI(a, j) needs a >= 1 and j >= 1, got ({rollouts}, {depth})")
        if safe_risk is not None and mode != "ti":
            raise ValueError(f"safe_risk={safe_risk}: the safety layer picks among TI's "
                             f"rollouts and needs mode 'ti' (got {mode!r})")
        if safe_beta < 0 or (safe_beta and safe_risk is None):
            raise ValueError(f"safe_beta={safe_beta}: must be >= 0, and is read only with "
                             f"safe_risk (got {safe_risk})")
        if fantasy_dtype not in FANTASY_DTYPES or (fantasy_dtype != "float32" and mode != "ti"):
            raise ValueError(f"fantasy_dtype={fantasy_dtype!r}: one of {list(FANTASY_DTYPES)}, "
                             f"read by mode 'ti' only (got mode {mode!r})")
        if core is None:
            if checkpoint is None:
                raise ValueError("a learned method needs a checkpoint (path or shipped name)")
            core, _ = load_core(checkpoint, env.device)
        self.core, self.mode, self.rollouts, self.depth = core, mode, rollouts, depth
        self.intents, self.safe_risk, self.safe_beta = intents, safe_risk, safe_beta
        self.fantasy_dtype = FANTASY_DTYPES[fantasy_dtype]
        self.hidden: torch.Tensor | None = None
        self.encoding: torch.Tensor | None = None

    @staticmethod
    def sends_intents(params: Mapping[str, Any]) -> bool:
        """Whether a method with these YAML ``params`` broadcasts intents (TI with
        ``intents`` on; a param left out takes this class's default)."""
        args = {**_INIT_DEFAULTS, **params}
        return args["mode"] == "ti" and bool(args["intents"])

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
                if self.intents:
                    broadcast(td, self.env, e_idx, a_idx, mean, cov)
        td.set(("agents", "action"), action)
        return td

    def _trajectory_intent(self, rows, logits, hidden, e_idx, a_idx):
        """TI(a, j) for B deciding agents: first slots ``[B]``, intent mean and covariance."""
        st, k = self.env.episode, logits.shape[-1]
        u = self.uniforms(st, (self.env.n_agents, self.rollouts, self.depth, k))[e_idx, a_idx]
        gumbel = gumbel_noise(u).reshape(-1, self.depth, k)  # row b * a + r: rollout r of b
        rollouts = fantasy_rollouts(self.core, self.env, rows, logits, hidden, e_idx, a_idx,
                                    gumbel, self.fantasy_dtype)
        if self.safe_risk is not None and self.env.config.risk_enabled:
            rollouts.reject(self._unsafe(rows, e_idx, a_idx))
        return (rollouts.best_first(), *rollouts.intent(self.env.config.intent_cov_floor))

    def _unsafe(self, rows, e_idx, a_idx) -> torch.Tensor:
        """``[B, k]``: neighbour slots the safety layer rejects (on each agent's own belief)."""
        st, g2 = self.env.episode, self.env.config.n_grid
        g_idx = self.env.agent_belief_index[a_idx]
        nbr = rows.get("neighbors") + g2  # [B, k] query rows of the neighbour nodes
        mu = st.belief.mu[e_idx, g_idx, :, 1].gather(1, nbr)
        sd = st.belief.sigma2[e_idx, g_idx].gather(1, nbr).clamp_min(0).sqrt()
        return mu + self.safe_beta * sd > self.safe_risk


# The constructor's defaults, which a method YAML's omitted params take.
_INIT_DEFAULTS = {name: p.default for name, p in
                  inspect.signature(LearnedPolicy.__init__).parameters.items()
                  if p.default is not inspect.Parameter.empty}
