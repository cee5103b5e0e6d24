"""The batched MAIPP environment: E independent shared-budget episodes as a TorchRL env.

One ``_step`` applies the deciding agents' moves, then advances simulated time event by
event until some agent has arrived and can decide (or the episode ends). See
docs/environment.md for every key and every rule; PROTOCOL v1 is the specification.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase, tensorclass
from torchrl.data import Binary, Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from maipp_bench.envs import rng
from maipp_bench.envs.belief import GPBelief, GPPrior, interest_trace
from maipp_bench.envs.config import MAIPPConfig, check_device
from maipp_bench.envs.dynamics import EPS, edge_points, reachability, sample_offsets
from maipp_bench.envs.intent import check_intent, intent_feature
from maipp_bench.envs.roadmap import Roadmap, build_roadmap, laplacian_encoding
from maipp_bench.envs.world import World, generate_world, grid_points

# Per-node observation features, in order (docs/environment.md).
NODE_FEATURES = ("x", "y", "interest_mean", "interest_std", "risk_ucb", "intent", "in_aoi")
STATE_FEATURES = NODE_FEATURES[:5] + ("agents_targeting", "in_aoi", "budget_left")
METRICS = (
    "trace", "objective", "rmse", "distance", "time", "evidence_inside", "evidence_outside",
    "evidence_total", "traps", "measurements",
)
COUNT_METRICS = {"evidence_inside", "evidence_outside", "evidence_total", "traps",
                  "measurements"}
_INSTANCE_TAG, _TRIAL_TAG = 0x1A57, 0x7B1A  # explicit protocol seeds live in own streams
_BUDGET_TAG = 0xB0D6


@tensorclass
class EpisodeState:
    """Everything that changes during an episode, batched over envs (leading dim E)."""

    world: World
    roadmap: Roadmap
    belief: GPBelief  # [E, G]: G = 1 (shared) or m + 1 (per agent, then the team)
    in_belief: torch.Tensor  # [E, G, M] bool: log slot already added to belief g
    query: torch.Tensor  # [E, Q, 2] grid points then roadmap nodes
    grid_truth: torch.Tensor  # [E, G2] true interest signal on the grid
    grid_weight: torch.Tensor  # [E, G2] AOI weight of each grid cell
    node_risk: torch.Tensor  # [E, N] true risk at roadmap nodes
    node_in_aoi: torch.Tensor  # [E, N] bool
    evidence_in_aoi: torch.Tensor  # [E, Ki] bool
    evidence_found: torch.Tensor  # [E, Ki] bool
    noise_key: torch.Tensor  # [E] int64
    time: torch.Tensor  # [E]
    steps: torch.Tensor  # [E] int64
    terminated: torch.Tensor  # [E] bool: how the episode ended (kept while a finished env
    truncated: torch.Tensor  # [E] bool   is stepped again: it stays exactly as it ended)
    team_budget: torch.Tensor  # [E] the episode's shared pool m * B
    budget_used: torch.Tensor  # [E] team distance committed so far
    cur: torch.Tensor  # [E, m] last node reached
    tgt: torch.Tensor  # [E, m] node being travelled to (== cur when resting)
    edge_len: torch.Tensor  # [E, m] length of the edge in progress (0: resting)
    progress: torch.Tensor  # [E, m] distance travelled along it
    since_sample: torch.Tensor  # [E, m] distance since the last measurement
    trapped: torch.Tensor  # [E, m] bool
    history: torch.Tensor  # [E, m, W] previous nodes (backtracking penalty), -1 = none
    traj: torch.Tensor  # [E, m, T] visited nodes
    traj_len: torch.Tensor  # [E, m]
    meas_x: torch.Tensor  # [E, M, 2] team measurement log
    meas_y: torch.Tensor  # [E, M, 2] (interest signal, risk) with noise
    meas_agent: torch.Tensor  # [E, M]
    meas_time: torch.Tensor  # [E, M]
    meas_count: torch.Tensor  # [E]
    known: torch.Tensor  # [E, m, M] bool: measurements each agent holds
    intent_mean: torch.Tensor  # [E, m, 2] latest intent each agent broadcast
    intent_cov: torch.Tensor  # [E, m, 2, 2]
    intent_valid: torch.Tensor  # [E, m]
    recv_mean: torch.Tensor  # [E, m, m, 2] intent of b as held by a, at [a, b]
    recv_cov: torch.Tensor  # [E, m, m, 2, 2]
    recv_valid: torch.Tensor  # [E, m, m]
    nbr: torch.Tensor  # [E, m, k] neighbour nodes of each agent's node
    nbr_len: torch.Tensor  # [E, m, k]
    mask: torch.Tensor  # [E, m, k] feasibility mask of deciding agents
    deciding: torch.Tensor  # [E, m]
    trace: torch.Tensor  # [E] Tr(P) of the team belief over X_I
    objective: torch.Tensor  # [E] AOI-weighted Tr(P) (the reward's Phi)
    rmse: torch.Tensor  # [E] RMSE of the team's interest mean on the grid
    node_encoding: torch.Tensor  # [E, N, D] Laplacian encoding of the roadmap (D may be 0)

    def edge_ends(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Positions of each agent's last node and target node, ``[E, m, 2]`` each."""
        nodes = self.roadmap.nodes
        src = nodes.gather(1, self.cur.unsqueeze(-1).expand(-1, -1, 2))
        dst = nodes.gather(1, self.tgt.unsqueeze(-1).expand(-1, -1, 2))
        return src, dst


class MAIPPEnv(EnvBase):
    """Shared-budget multi-agent informative path planning, batched over E envs.

    Keys (``E`` envs, ``m`` agents, ``N`` roadmap nodes, ``k`` neighbour slots):

    * ``("agents", "observation")``: ``node_features [E, m, N, 7]`` (see
      ``NODE_FEATURES``), ``current_node [E, m]``, ``budget [E, m, 1]`` (remaining team
      budget fraction), ``neighbors [E, m, k]`` and ``neighbor_dist [E, m, k]``;
    * ``("agents", "action")``: neighbour slot in ``[0, k)``, ``[E, m]``;
    * ``("agents", "action_mask")`` bool ``[E, m, k]`` and ``("agents", "deciding")``
      bool ``[E, m]``: only deciding agents' actions are used; their mask is the
      feasibility mask, other agents' masks are all True and their actions ignored;
    * optional input ``("agents", "intent", "mean"|"cov")`` ``[E, m, 2]`` / ``[E, m, 2, 2]``;
    * ``("agents", "reward") [E, m, 1]``; ``done``, ``terminated``, ``truncated [E, 1]``;
    * ``state [E, N, 8]`` (team view, for centralised critics) and ``metrics`` (``[E]``).

    A reset may carry ``instance_seed`` and ``trial_seed`` (``[E]`` int64) to pin the
    world and the roadmap (the evaluation protocol does); otherwise env ``e`` draws its
    k-th episode from ``(seed, e, k)``, whatever the batch size.

    Example:
        >>> env = MAIPPEnv(MAIPPConfig(budget=1.0), batch_size=[2])
        >>> td = env.rollout(3)
        >>> td["next", "agents", "reward"].shape
        torch.Size([2, 3, 3, 1])
    """

    batch_locked = True

    def __init__(
        self,
        config: MAIPPConfig | None = None,
        batch_size: int | Sequence[int] = (1,),
        device: torch.device | str = "cpu",
        **overrides: Any,
    ) -> None:
        cfg = config if config is not None else MAIPPConfig()
        if overrides:
            cfg = cfg.replace(**overrides)
        if isinstance(batch_size, int):
            batch_size = (batch_size,)
        batch_size = torch.Size(batch_size)
        if len(batch_size) != 1 or batch_size[0] < 1:
            raise ValueError(
                f"MAIPPEnv: batch_size must be [E] with E >= 1, got {list(batch_size)}"
            )
        super().__init__(device=check_device(device, "MAIPPEnv device"), batch_size=batch_size)
        self.config = cfg
        self.prior = GPPrior(cfg.kernel, cfg.length_scale, cfg.prior_variance,
                             cfg.gp_noise_variance)
        self.n_envs, self.n_agents = batch_size[0], cfg.n_agents
        self.n_beliefs = 1 if cfg.shared_belief else cfg.n_agents + 1
        self._grid = grid_points(cfg.grid_size, torch.float64, self.device)
        self._agent_belief = (
            torch.zeros(cfg.n_agents, dtype=torch.int64, device=self.device)
            if cfg.shared_belief else torch.arange(cfg.n_agents, device=self.device)
        )
        # The RNG exists from construction: episodes are keyed by (seed, env, episode).
        self._seed_key = rng.seed_key(cfg.seed, self.device)
        self._episode = torch.zeros(self.n_envs, dtype=torch.int64, device=self.device)
        self._state: EpisodeState | None = None
        self._make_specs()

    # ================================================================== specs
    def _make_specs(self) -> None:
        cfg, e, m = self.config, self.n_envs, self.n_agents
        n, k, dt = cfg.n_roadmap_nodes, cfg.k_neighbors, cfg.torch_dtype
        dev = self.device
        obs = Composite(
            node_features=Unbounded((e, m, n, len(NODE_FEATURES)), dtype=dt, device=dev),
            current_node=Categorical(n, (e, m), device=dev),
            budget=Bounded(0.0, 1.0, (e, m, 1), dtype=dt, device=dev),
            neighbors=Bounded(0, n - 1, (e, m, k), dtype=torch.int64, device=dev),
            neighbor_dist=Unbounded((e, m, k), dtype=dt, device=dev),
            shape=(e, m), device=dev,
        )
        agents = Composite(
            observation=obs,
            action_mask=Binary(k, (e, m, k), dtype=torch.bool, device=dev),
            deciding=Categorical(2, (e, m), dtype=torch.bool, device=dev),
            shape=(e, m), device=dev,
        )
        metrics = Composite(
            {name: Unbounded((e,), dtype=torch.int64 if name in COUNT_METRICS else dt,
                             device=dev) for name in METRICS},
            shape=(e,), device=dev,
        )
        self.observation_spec = Composite(
            agents=agents,
            state=Unbounded((e, n, len(STATE_FEATURES)), dtype=dt, device=dev),
            metrics=metrics,
            shape=(e,), device=dev,
        )
        if cfg.node_encoding_dim:
            self.observation_spec["node_encoding"] = Unbounded(
                (e, n, cfg.node_encoding_dim), dtype=dt, device=dev)
        self.action_spec = Composite(
            agents=Composite(action=Categorical(k, (e, m), device=dev), shape=(e, m),
                             device=dev),
            shape=(e,), device=dev,
        )
        self.reward_spec = Composite(
            agents=Composite(reward=Unbounded((e, m, 1), dtype=dt, device=dev),
                             shape=(e, m), device=dev),
            shape=(e,), device=dev,
        )
        self.done_spec = Composite(
            {key: Categorical(2, (e, 1), dtype=torch.bool, device=dev)
             for key in ("done", "terminated", "truncated")},
            shape=(e,), device=dev,
        )

    # ================================================================== seeding
    def _set_seed(self, seed: int | None) -> None:
        seed = 0 if seed is None else int(seed)
        self._seed_key = rng.seed_key(seed, self.device)
        self._episode.zero_()

    # ================================================================== reset
    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs: Any) -> TensorDictBase:
        e = self.n_envs
        which = torch.ones(e, dtype=torch.bool, device=self.device)
        if tensordict is not None and "_reset" in tensordict.keys():
            which = tensordict.get("_reset").reshape(e)
        if self._state is None:
            which = torch.ones_like(which)  # the first reset builds every env
        idx = which.nonzero().squeeze(-1)
        if idx.numel():
            self._start_episodes(idx, tensordict)
        # Envs not reset report their own flags (a finished env left alone stays done).
        return self._observe(self._state, self._state.terminated, self._state.truncated)

    def _start_episodes(self, idx: torch.Tensor, tensordict: TensorDictBase | None) -> None:
        """Envs ``idx`` start their next episode (seeds from ``tensordict`` if it pins them)."""
        e = self.n_envs
        # Env e's k-th episode is keyed by (seed, e, k): independent of the batch size.
        ik = rng.derive(self._seed_key, idx, self._episode[idx], 0)
        tk = rng.derive(self._seed_key, idx, self._episode[idx], 1)
        if tensordict is not None:
            for name, tag, dst in (("instance_seed", _INSTANCE_TAG, ik),
                                   ("trial_seed", _TRIAL_TAG, tk)):
                if name in tensordict.keys():
                    seeds = tensordict.get(name).reshape(e)[idx].to(torch.int64)
                    dst.copy_(rng.derive(rng.mix(torch.tensor(tag, device=self.device)), seeds))
        self._episode[idx] += 1
        fresh = self._new_episodes(ik, tk)
        if self._state is None:
            self._state = fresh
        else:
            self._state[idx] = fresh

    def _reset_proc_data(self, tensordict: TensorDictBase | None,
                         tensordict_reset: TensorDictBase) -> TensorDictBase:
        """Merge a partial reset's output into ``tensordict`` without a ``where`` per key.

        TorchRL merges a partial reset key by key with a masked ``where`` over all E envs
        (at E = 1024 about a tenth of a ``step_and_maybe_reset`` step). ``_reset`` returns
        every env's current data, reset or not (done flags included), so when the input
        holds the env's latest output (as in ``step_and_maybe_reset``) a plain update gives
        the same result; TorchRL's zero padding is kept for entries only one side has.
        Wrappers (``TransformedEnv``, batched envs) merge with TorchRL's own code.
        """
        if tensordict is None or "_reset" not in tensordict.keys():
            return super()._reset_proc_data(tensordict, tensordict_reset)  # a full reset
        self._complete_done(self.full_done_spec, tensordict_reset)
        self._reset_check_done(tensordict, tensordict_reset)
        reset = tensordict.pop("_reset").reshape(self.batch_size)
        if not bool(reset.all()):  # TorchRL pads: a full reset is a plain update there too
            present, produced = (set(td.keys(True, True)) for td in (tensordict,
                                                                     tensordict_reset))
            for td, keys, rows in ((tensordict, present - produced, reset),
                                   (tensordict_reset, produced - present, ~reset)):
                for key in keys:  # e.g. a policy's recurrent state restarts at 0
                    value = td.get(key)
                    fill = rows.view(*rows.shape, *(1,) * (value.ndim - rows.ndim))
                    td.set(key, value.masked_fill(fill, 0))
        return tensordict.update(tensordict_reset)

    def _new_episodes(self, ik: torch.Tensor, tk: torch.Tensor) -> EpisodeState:
        cfg, dev = self.config, self.device
        e, m = ik.shape[0], self.n_agents
        big_m, g2 = cfg.measurement_capacity, cfg.n_grid
        world = generate_world(cfg, ik)
        node_filter = None
        if cfg.prune_risky_nodes:  # paper: risk-unaware baselines lose nodes of risk > 0.7
            node_filter = lambda pts: world.risk(pts) <= cfg.risk_mask_threshold  # noqa: E731
        roadmap = build_roadmap(tk, cfg.n_nodes, cfg.k_neighbors, node_filter)
        grid = self._grid.expand(e, -1, -1)
        query = torch.cat([grid, roadmap.nodes], dim=1)
        grid_weight = torch.ones(e, g2, dtype=torch.float64, device=dev)
        if cfg.aoi_enabled:
            grid_weight = torch.where(world.in_aoi(grid), 1.0, cfg.aoi_outside_weight)
        n_nodes, k = cfg.n_roadmap_nodes, cfg.k_neighbors
        f64 = dict(dtype=torch.float64, device=dev)
        i64 = dict(dtype=torch.int64, device=dev)
        b = dict(dtype=torch.bool, device=dev)
        zeros_em = torch.zeros(e, m, **f64)
        team_budget = torch.full((e,), cfg.team_budget, **f64)
        if cfg.budget_min > 0:  # training across a suite's budgets: B ~ U[budget_min, budget]
            u = rng.uniform(rng.derive(tk, _BUDGET_TAG), ())
            team_budget = m * (cfg.budget_min + (cfg.budget - cfg.budget_min) * u)
        encoding = torch.zeros(e, n_nodes, 0, dtype=cfg.torch_dtype, device=dev)
        if cfg.node_encoding_dim:
            encoding = laplacian_encoding(roadmap.neighbors, roadmap.neighbor_valid,
                                          cfg.node_encoding_dim).to(cfg.torch_dtype)
        st = EpisodeState(
            world=world,
            roadmap=roadmap,
            belief=GPBelief.empty((e, self.n_beliefs), big_m, g2 + n_nodes, 2,
                                  cfg.prior_variance, cfg.torch_dtype, dev),
            in_belief=torch.zeros(e, self.n_beliefs, big_m, **b),
            query=query,
            grid_truth=world.grid_signal(cfg.grid_size, cfg.risk_mix_lambda),
            grid_weight=grid_weight,
            node_risk=world.risk(roadmap.nodes),
            node_in_aoi=world.in_aoi(roadmap.nodes),
            evidence_in_aoi=world.in_aoi(world.evidence),
            evidence_found=torch.zeros_like(world.interest_valid),
            noise_key=rng.derive(ik, tk),
            time=torch.zeros(e, **f64),
            steps=torch.zeros(e, **i64),
            terminated=torch.zeros(e, **b),
            truncated=torch.zeros(e, **b),
            team_budget=team_budget,
            budget_used=torch.zeros(e, **f64),
            cur=torch.zeros(e, m, **i64),
            tgt=torch.zeros(e, m, **i64),
            edge_len=zeros_em.clone(),
            progress=zeros_em.clone(),
            since_sample=zeros_em.clone(),
            trapped=torch.zeros(e, m, **b),
            history=torch.full((e, m, cfg.backtrack_window), -1, **i64),
            traj=torch.zeros(e, m, cfg.max_steps + 1, **i64),
            traj_len=torch.ones(e, m, **i64),
            meas_x=torch.zeros(e, big_m, 2, **f64),
            meas_y=torch.zeros(e, big_m, 2, **f64),
            meas_agent=torch.full((e, big_m), -1, **i64),
            meas_time=torch.zeros(e, big_m, **f64),
            meas_count=torch.zeros(e, **i64),
            known=torch.zeros(e, m, big_m, **b),
            intent_mean=torch.zeros(e, m, 2, **f64),
            intent_cov=torch.eye(2, **f64).expand(e, m, 2, 2).clone(),
            intent_valid=torch.zeros(e, m, **b),
            recv_mean=torch.zeros(e, m, m, 2, **f64),
            recv_cov=torch.eye(2, **f64).expand(e, m, m, 2, 2).clone(),
            recv_valid=torch.zeros(e, m, m, **b),
            nbr=torch.zeros(e, m, k, **i64),
            nbr_len=torch.zeros(e, m, k, **f64),
            mask=torch.ones(e, m, k, **b),
            deciding=torch.zeros(e, m, **b),
            trace=torch.zeros(e, **f64),
            objective=torch.zeros(e, **f64),
            rmse=torch.zeros(e, **f64),
            node_encoding=encoding,
            batch_size=[e],
        )
        # Every agent measures at the shared start node (PROTOCOL: "at the start").
        start = roadmap.nodes[:, :1].expand(e, m, 2)
        agent = torch.arange(m, device=dev).expand(e, m)
        self._log_measurements(st, start, agent, torch.ones(e, m, **b), torch.zeros(e, m, **f64))
        self._decision_event(st, torch.ones(e, **b))
        return st

    # ================================================================== step
    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        st, cfg = self._require_state(), self.config
        e, m, k = self.n_envs, self.n_agents, cfg.k_neighbors
        action = tensordict.get(("agents", "action"))
        if action.shape != (e, m) or action.dtype.is_floating_point:
            raise ValueError(
                f"('agents', 'action') must be an integer tensor of shape {[e, m]}, "
                f"got {action.dtype} {list(action.shape)}"
            )
        action = action.to(torch.int64)
        deciding = st.deciding
        in_range = (action >= 0) & (action < k)
        allowed = st.mask.gather(-1, action.clamp(0, k - 1).unsqueeze(-1)).squeeze(-1)
        bad = deciding & ~(in_range & allowed)
        if bool(bad.any()):
            where = bad.nonzero().tolist()
            ex_e, ex_a = where[0]
            raise ValueError(
                f"masked or out-of-range action for deciding agent(s) [env, agent] "
                f"{where[:8]}{' ...' if len(where) > 8 else ''}: e.g. env {ex_e} agent {ex_a} "
                f"chose slot {int(action[ex_e, ex_a])}, allowed slots are "
                f"{st.mask[ex_e, ex_a].nonzero().squeeze(-1).tolist()}"
            )
        self._take_intents(st, tensordict, deciding)
        live = ~(st.terminated | st.truncated)  # a finished env stays as it ended, earns 0

        penalty = torch.zeros(e, m, dtype=torch.float64, device=self.device)
        terminated = self._apply_moves(st, action, deciding, penalty)
        objective_before = st.objective.clone()
        ended = terminated | ~live  # finished envs are not advanced
        self._advance(st, ended, penalty)
        st.steps += live.to(st.steps.dtype)
        terminated = torch.where(live, ended, st.terminated)
        truncated = torch.where(live, (st.steps >= cfg.max_steps) & ~terminated, st.truncated)
        st.terminated, st.truncated = terminated, truncated
        done = terminated | truncated
        st.deciding &= ~done.unsqueeze(-1)
        st.mask |= ~st.deciding.unsqueeze(-1)

        # r = max(0, relative drop of Phi) - penalties, and -Phi_T / 900 at the end.
        gain = ((objective_before - st.objective) / objective_before.clamp_min(1e-12)).clamp_min(0)
        reward = gain.unsqueeze(-1) - penalty
        reward = reward - (cfg.terminal_scale * st.objective * (done & live)).unsqueeze(-1)
        return self._observe(st, terminated, truncated, reward)

    def _take_intents(self, st: EpisodeState, td: TensorDictBase, deciding: torch.Tensor) -> None:
        """Deciding agents broadcast the intent that came with their action, if any."""
        mean = td.get(("agents", "intent", "mean"), None)
        cov = td.get(("agents", "intent", "cov"), None)
        if mean is None and cov is None:
            return
        if mean is None or cov is None:
            raise ValueError(
                "('agents', 'intent') needs both 'mean' [E, m, 2] and 'cov' [E, m, 2, 2]"
            )
        e, m = self.n_envs, self.n_agents
        if mean.shape != (e, m, 2) or cov.shape != (e, m, 2, 2):
            raise ValueError(
                f"('agents', 'intent'): expected mean {[e, m, 2]} and cov {[e, m, 2, 2]}, "
                f"got {list(mean.shape)} and {list(cov.shape)}"
            )
        mean, cov = mean.to(torch.float64), cov.to(torch.float64)
        send = deciding
        valid = td.get(("agents", "intent", "valid"), None)
        if valid is not None:
            send = send & valid.reshape(e, m).to(torch.bool)
        check_intent(mean, cov, send)
        st.intent_mean = torch.where(send.unsqueeze(-1), mean, st.intent_mean)
        st.intent_cov = torch.where(send[..., None, None], cov, st.intent_cov)
        st.intent_valid = st.intent_valid | send

    def _apply_moves(self, st, action, deciding, penalty) -> torch.Tensor:
        """Commit the deciding agents' moves in agent order; returns budget overflow [E]."""
        cfg, m = self.config, self.n_agents
        action = torch.where(deciding, action, 0)  # others' actions are ignored, never read
        tgt = st.nbr.gather(-1, action.unsqueeze(-1)).squeeze(-1)
        length = st.nbr_len.gather(-1, action.unsqueeze(-1)).squeeze(-1)
        # Simultaneous deciders choosing one node: the lower index wins, the other waits.
        earlier = torch.ones(m, m, dtype=torch.bool, device=self.device).tril(-1)
        clash = (tgt.unsqueeze(-1) == tgt.unsqueeze(-2)) & deciding.unsqueeze(-2) & earlier
        collided = deciding & clash.any(-1)
        accepted = deciding & ~collided
        committed = torch.cumsum(torch.where(accepted, length, 0.0), dim=-1)
        pool = st.team_budget.unsqueeze(-1)
        overflow = accepted & (st.budget_used.unsqueeze(-1) + committed > pool + EPS)
        accepted &= ~overflow
        backtrack = accepted & (tgt.unsqueeze(-1) == st.history).any(-1)
        f64 = penalty.dtype
        penalty += (cfg.collision_penalty * collided.to(f64) + cfg.overflow_penalty
                    * overflow.to(f64) + cfg.backtrack_penalty * backtrack.to(f64))
        st.tgt = torch.where(accepted, tgt, st.tgt)
        st.edge_len = torch.where(accepted, length, st.edge_len)
        st.progress = torch.where(accepted, 0.0, st.progress)
        st.budget_used = st.budget_used + torch.where(accepted, length, 0.0).sum(-1)
        return overflow.any(-1)

    def _advance(self, st: EpisodeState, terminated: torch.Tensor, penalty: torch.Tensor) -> None:
        """Advance time event by event until some agent decides; mark stuck envs done."""
        e = terminated.shape[0]
        pending = ~terminated
        while True:
            stuck = pending & ~(st.edge_len > 0).any(-1)  # nobody moves, nobody can decide
            terminated |= stuck
            pending &= ~stuck
            n = int(pending.sum())
            if n == 0:
                return
            if 2 * n >= e:
                self._next_event(st, pending, penalty)
                decided = st.deciding.any(-1)
            else:  # a few stragglers: work on a copy of just those envs
                idx = pending.nonzero().squeeze(-1)
                sub, pen = st[idx], penalty[idx]
                self._next_event(sub, torch.ones(n, dtype=torch.bool, device=self.device), pen)
                st[idx], penalty[idx] = sub, pen
                decided = torch.zeros_like(pending)
                decided[idx] = sub.deciding.any(-1)
            pending &= ~decided

    def _next_event(self, st: EpisodeState, pending: torch.Tensor, penalty: torch.Tensor) -> None:
        """Move the pending envs to their next arrival and process that decision event."""
        moving = st.edge_len > 0
        left = torch.where(moving, st.edge_len - st.progress, torch.inf)
        dt = torch.where(pending, left.amin(-1), 0.0)
        travel = torch.where(moving & pending.unsqueeze(-1), dt.unsqueeze(-1), 0.0)
        self._travel(st, travel)
        st.time = st.time + dt
        arrived = moving & pending.unsqueeze(-1) & (left <= dt.unsqueeze(-1) + EPS)
        self._arrive(st, arrived, penalty)
        self._decision_event(st, pending)

    # ================================================================== motion
    def _positions(self, st: EpisodeState) -> torch.Tensor:
        src, dst = st.edge_ends()
        return edge_points(src, dst, st.edge_len, st.progress.unsqueeze(-1)).squeeze(-2)

    def _contact(self, st: EpisodeState) -> torch.Tensor:
        """``[E, m, m]``: agents in one communication component (reflexive)."""
        if self.config.shared_belief:
            e, m = st.cur.shape
            return torch.ones(e, m, m, dtype=torch.bool, device=self.device)
        pos = self._positions(st)
        return reachability(torch.cdist(pos, pos) <= self.config.comm_range)

    def _travel(self, st: EpisodeState, travel: torch.Tensor) -> None:
        """Move agents ``travel [E, m]`` along their edges, measuring every 0.2."""
        cfg = self.config
        offsets, valid, st.since_sample = sample_offsets(st.since_sample, travel,
                                                         cfg.sample_spacing)
        if valid.shape[-1]:
            src, dst = st.edge_ends()
            pts = edge_points(src, dst, st.edge_len, st.progress.unsqueeze(-1) + offsets)
            e, m, r = valid.shape
            agent = torch.arange(m, device=self.device).view(1, m, 1).expand(e, m, r)
            # Log in (round, agent) order: the order the measurements are taken.
            # Unit speed: a measurement `offset` into the leg is taken `offset` later.
            self._log_measurements(
                st, pts.transpose(1, 2).reshape(e, r * m, 2),
                agent.transpose(1, 2).reshape(e, r * m), valid.transpose(1, 2).reshape(e, r * m),
                (st.time.unsqueeze(-1).unsqueeze(-1) + offsets).transpose(1, 2).reshape(e, r * m),
            )
        st.progress = st.progress + travel

    def _log_measurements(self, st, pts, agent, valid, times) -> None:
        """Append noisy measurements ``pts [E, P, 2]`` to the team log; discover evidence."""
        cfg = self.config
        # About a quarter of the envs measure at a step: evaluate fields, noise and detection
        # there only (every value is computed per point, so the same bits as over all E).
        sel = valid.any(-1).nonzero().squeeze(-1)
        if sel.numel() == 0:
            return
        pts, agent, valid, times = pts[sel], agent[sel], valid[sel], times[sel]
        world = st.world[sel]
        row, p_idx = valid.nonzero(as_tuple=True)
        e_idx = sel[row]
        slot = st.meas_count[sel].unsqueeze(-1) + torch.cumsum(valid.to(torch.int64), -1) - 1
        noise = rng.normal(rng.derive(st.noise_key[sel].unsqueeze(-1), slot), (2,))
        values = torch.stack(world.measure(pts, cfg.risk_mix_lambda), -1)
        values = values + cfg.measurement_noise_std * noise
        s, a = slot[row, p_idx], agent[row, p_idx]
        st.meas_x[e_idx, s] = pts[row, p_idx]
        st.meas_y[e_idx, s] = values[row, p_idx]
        st.meas_agent[e_idx, s] = a
        st.meas_time[e_idx, s] = times[row, p_idx]
        st.known[e_idx, a, s] = True
        st.meas_count = st.meas_count.index_add(0, sel, valid.sum(-1))
        near = torch.cdist(pts, world.evidence) <= cfg.detect_radius  # [S, P, Ki]
        st.evidence_found[sel] |= (near & valid.unsqueeze(-1)).any(1)

    def _arrive(self, st: EpisodeState, arrived: torch.Tensor, penalty: torch.Tensor) -> None:
        cfg = self.config
        if st.history.shape[-1]:
            shifted = torch.cat([st.cur.unsqueeze(-1), st.history[..., :-1]], -1)
            st.history = torch.where(arrived.unsqueeze(-1), shifted, st.history)
        st.cur = torch.where(arrived, st.tgt, st.cur)
        st.edge_len = torch.where(arrived, 0.0, st.edge_len)
        st.progress = torch.where(arrived, 0.0, st.progress)
        e_idx, a_idx = arrived.nonzero(as_tuple=True)
        st.traj[e_idx, a_idx, st.traj_len[e_idx, a_idx]] = st.cur[e_idx, a_idx]
        st.traj_len = st.traj_len + arrived
        if cfg.risk_enabled:
            risk = st.node_risk.gather(1, st.cur)
            penalty += torch.where(arrived & (risk > cfg.risk_penalty_threshold), risk, 0.0)
            st.trapped = st.trapped | (arrived & (risk >= cfg.trap_threshold))

    # ================================================================== events
    def _decision_event(self, st: EpisodeState, at_event: torch.Tensor) -> None:
        """Communicate, bring beliefs up to date, and find the agents that decide."""
        cfg, m = self.config, self.n_agents
        big_m = st.known.shape[-1]
        eye = torch.eye(m, dtype=torch.bool, device=self.device)
        reach = torch.where(at_event[:, None, None], self._contact(st), eye)
        # Connected agents merge measurement sets and exchange intents.
        st.known = (reach.to(torch.float32) @ st.known.to(torch.float32)) > 0
        link = reach & ~eye & st.intent_valid.unsqueeze(-2)  # [a, b]: a hears b
        st.recv_mean = torch.where(link.unsqueeze(-1), st.intent_mean.unsqueeze(-3), st.recv_mean)
        st.recv_cov = torch.where(link[..., None, None], st.intent_cov.unsqueeze(-4), st.recv_cov)
        st.recv_valid = st.recv_valid | link
        # Beliefs take the log slots they should hold and do not yet: the team belief (last)
        # holds everything, agent beliefs what their agent knows.
        logged = torch.arange(big_m, device=self.device) < st.meas_count.unsqueeze(-1)
        want = logged.unsqueeze(1) if cfg.shared_belief else torch.cat(
            [st.known, logged.unsqueeze(1)], 1)
        self._sync_beliefs(st, want & ~st.in_belief)
        self._update_masks(st)

    def _sync_beliefs(self, st: EpisodeState, missing: torch.Tensor) -> None:
        """Add the ``missing [E, G, M]`` log slots to each belief, in log order; refresh
        the team metrics of the envs whose team belief changed."""
        count = missing.sum(-1)
        p = int(count.max())
        if p == 0:
            return
        slot_ids = torch.arange(missing.shape[-1], device=self.device)
        order = torch.where(missing, slot_ids, slot_ids + missing.shape[-1])
        take = order.sort(-1).values[..., :p] % missing.shape[-1]  # [E, G, p] in log order
        mask = torch.arange(p, device=self.device) < count.unsqueeze(-1)
        e, g = missing.shape[:2]
        take2 = take.unsqueeze(-1).expand(-1, -1, -1, 2)
        x = st.meas_x.unsqueeze(1).expand(e, g, -1, 2).gather(2, take2)
        y = st.meas_y.unsqueeze(1).expand(e, g, -1, 2).gather(2, take2)
        st.belief.add(self.prior, st.query.unsqueeze(1), x, y, mask)
        st.in_belief = st.in_belief | missing
        self._update_objective(st, count[:, -1] > 0)

    def _update_objective(self, st: EpisodeState, changed: torch.Tensor) -> None:
        """Tr(P), the objective and the RMSE of the team belief, for the ``changed [E]``
        envs only (a quarter of them per step at large E; rows are computed alike)."""
        cfg, g2 = self.config, self.config.n_grid
        idx = changed.nonzero().squeeze(-1)
        if idx.numel() == 0:
            return
        mu_dt = st.belief.mu[:, -1, :g2, 0][idx]  # not st.belief[idx]: that copies V too
        mu, var = mu_dt.to(torch.float64), st.belief.sigma2[:, -1, :g2][idx].to(torch.float64)
        trace = interest_trace(mu, var, cfg.interest_beta, cfg.interest_threshold)
        st.trace[idx] = trace
        st.objective[idx] = (interest_trace(mu, var, cfg.interest_beta, cfg.interest_threshold,
                                            st.grid_weight[idx]) if cfg.aoi_enabled else trace)
        st.rmse[idx] = torch.sqrt(((mu_dt - st.grid_truth[idx]) ** 2).mean(-1))

    def _update_masks(self, st: EpisodeState) -> None:
        """Feasibility mask M (paper): budget, node collision, hard risk constraint."""
        cfg, k = self.config, self.config.k_neighbors
        rm = st.roadmap
        e, m = st.cur.shape
        n = rm.neighbors.shape[1]
        # Each agent's node's slot row, by row index (faster than gather with an expanded index).
        rows = (st.cur + n * torch.arange(e, device=self.device).unsqueeze(-1)).reshape(-1)
        st.nbr = rm.neighbors.reshape(-1, k).index_select(0, rows).view(e, m, k)
        st.nbr_len = rm.neighbor_dist.reshape(-1, k).index_select(0, rows).view(e, m, k)
        ok = rm.neighbor_valid.reshape(-1, k).index_select(0, rows).view(e, m, k)
        ok &= st.nbr_len <= (st.team_budget - st.budget_used)[:, None, None] + EPS
        # Node collision: no two agents may target one node (a resting agent targets its own).
        other = ~torch.eye(m, dtype=torch.bool, device=self.device)
        taken = (st.nbr.unsqueeze(-1) == st.tgt[:, None, None, :]) & other[None, :, None, :]
        ok &= ~taken.any(-1)
        if cfg.risk_enabled:
            risk_mean = st.belief.mu[..., cfg.n_grid:, 1].reshape(e, -1)  # [E, G * N]
            at = (self._agent_belief.view(1, m, 1) * n + st.nbr).view(e, m * k)  # own belief
            ok &= (risk_mean.gather(1, at) <= cfg.risk_mask_threshold).view(e, m, k)
        resting = (st.edge_len == 0) & ~st.trapped
        st.deciding = resting & ok.any(-1)
        st.mask = ok | ~st.deciding.unsqueeze(-1)

    # ================================================================== observations
    def _observe(self, st, terminated, truncated, reward=None) -> TensorDictBase:
        cfg, e, m = self.config, self.n_envs, self.n_agents
        g2, dt = cfg.n_grid, cfg.torch_dtype
        nodes = st.roadmap.nodes
        n = nodes.shape[1]
        # Features of each belief once ([E, G, N, 7], intent column 0); agents then view
        # their own belief's rows. With one shared belief and no intents yet, every agent
        # sees the same features: an expanded view, not m copies.
        g = st.belief.batch_size[1]
        per_belief = torch.empty(e, g, n, len(NODE_FEATURES), dtype=dt, device=self.device)
        per_belief[..., 0:2] = nodes.to(dt).unsqueeze(1)
        per_belief[..., 2] = st.belief.mu[:, :, g2:, 0]
        sd = per_belief[..., 3]
        torch.sqrt(st.belief.sigma2[:, :, g2:].clamp_min(0), out=sd)
        if cfg.risk_enabled:
            torch.add(st.belief.mu[:, :, g2:, 1], sd, alpha=cfg.risk_beta, out=per_belief[..., 4])
        else:
            per_belief[..., 4] = 0
        per_belief[..., 5] = 0
        per_belief[..., 6] = st.node_in_aoi.to(dt).unsqueeze(1)
        if bool(st.recv_valid.any()):
            feats = per_belief.index_select(1, self._agent_belief)
            feats[..., 5] = intent_feature(nodes, st.recv_mean, st.recv_cov, st.recv_valid)
        elif g == 1:
            feats = per_belief.expand(e, m, n, len(NODE_FEATURES))
        else:
            feats = per_belief.index_select(1, self._agent_belief)
        budget_left = ((st.team_budget - st.budget_used) / st.team_budget).clamp(0, 1).to(dt)

        # The team view, written column by column (a cat of strided slices is slower).
        state = torch.empty(e, n, len(STATE_FEATURES), dtype=dt, device=self.device)
        state[..., :5] = per_belief[:, -1, :, :5]
        targeting = state[..., 5].zero_()  # agents travelling to (or resting at) each node
        targeting.scatter_add_(1, st.tgt, torch.ones(st.tgt.shape, dtype=dt, device=self.device))
        state[..., 6] = per_belief[:, -1, :, 6]
        state[..., 7] = budget_left.unsqueeze(-1)
        found = st.evidence_found & st.world.interest_valid
        metrics = {
            "trace": st.trace.to(dt, copy=True),
            "objective": st.objective.to(dt, copy=True),
            "rmse": st.rmse.to(dt, copy=True),
            "distance": st.budget_used.to(dt, copy=True),
            "time": st.time.to(dt, copy=True),
            "evidence_inside": (found & st.evidence_in_aoi).sum(-1),
            "evidence_outside": (found & ~st.evidence_in_aoi).sum(-1),
            "evidence_total": st.world.interest_valid.sum(-1),
            "traps": st.trapped.sum(-1),
            "measurements": st.meas_count.clone(),
        }
        bs = self.batch_size
        observation = TensorDict(
            node_features=feats,
            current_node=st.cur.clone(),
            budget=budget_left.view(e, 1, 1).expand(e, m, 1).clone(),
            neighbors=st.nbr.clone(),
            neighbor_dist=st.nbr_len.to(dt, copy=True),
            batch_size=(e, m),
        )
        agents = TensorDict(observation=observation, action_mask=st.mask.clone(),
                            deciding=st.deciding.clone(), batch_size=(e, m))
        if reward is not None:
            agents.set("reward", reward.to(dt).unsqueeze(-1))
        out = TensorDict(
            agents=agents,
            state=state,
            metrics=TensorDict(metrics, batch_size=bs),
            done=(terminated | truncated).unsqueeze(-1),
            terminated=terminated.unsqueeze(-1).clone(),
            truncated=truncated.unsqueeze(-1).clone(),
            batch_size=bs,
            device=self.device,  # transforms make their reset masks on the data's device
        )
        if cfg.node_encoding_dim:
            out.set("node_encoding", st.node_encoding.clone())
        # The action spec carries the live mask, so random actions (env.rand_action,
        # rollouts without a policy) respect it without any transform.
        self.full_action_spec[("agents", "action")].update_mask(st.mask.clone())
        return out

    # ================================================================== public views
    def _require_state(self) -> EpisodeState:
        if self._state is None:
            raise RuntimeError("MAIPPEnv: call reset() before using the environment")
        return self._state

    @property
    def episode(self) -> EpisodeState:
        """The live episode state (world, roadmap, beliefs, agents) of every env.

        ``episode.belief[:, g]`` is belief ``g``; agent ``a`` plans on
        ``agent_belief_index[a]`` and the last belief is the team's (all measurements).
        """
        return self._require_state()

    def agent_positions(self) -> torch.Tensor:
        """Positions of every agent now, ``[E, m, 2]`` (float64)."""
        return self._positions(self._require_state())

    def in_contact(self) -> torch.Tensor:
        """``[E, m, m]`` bool: agents in one communication component now (reflexive)."""
        return self._contact(self._require_state())

    @property
    def agent_belief_index(self) -> torch.Tensor:
        """``[m]``: which belief of ``state.belief[:, g]`` each agent plans on."""
        return self._agent_belief

    def episode_record(self, env_index: int) -> dict[str, Any]:
        """Everything needed to recompute env ``env_index``'s beliefs independently.

        Returns a dict of CPU tensors: ``points [n, 2]``, ``values [n, 2]`` (interest
        signal, risk; noisy as measured), ``agent [n]``, ``time [n]`` (the team log, in
        the order measurements were taken), ``known [m, n]`` (which of them each agent's
        belief holds; all of them with global communication), ``trajectories`` (a list of
        m node-index tensors, start node first), ``trajectory_points`` (their positions),
        ``nodes [N, 2]`` and ``query [Q, 2]`` (grid then nodes).
        """
        st = self._require_state()
        if not 0 <= env_index < self.n_envs:
            raise IndexError(f"env_index must be in [0, {self.n_envs}), got {env_index}")
        i, n = env_index, int(st.meas_count[env_index])
        # An agent's belief holds what it knew at its last decision event.
        known = st.in_belief[i, self._agent_belief, :n]
        trajs = [st.traj[i, a, : int(st.traj_len[i, a])].cpu() for a in range(self.n_agents)]
        nodes = st.roadmap.nodes[i].cpu()
        return {
            "points": st.meas_x[i, :n].cpu(),
            "values": st.meas_y[i, :n].cpu(),
            "agent": st.meas_agent[i, :n].cpu(),
            "time": st.meas_time[i, :n].cpu(),
            "known": known.cpu(),
            "trajectories": trajs,
            "trajectory_points": [nodes[t] for t in trajs],
            "nodes": nodes,
            "query": st.query[i].cpu(),
        }
