"""PettingZoo view of the MAIPP task: one episode of :class:`MAIPPEnv` as a ``ParallelEnv``.

``pettingzoo`` and ``gymnasium`` are imported here only, so ``import maipp_bench.envs``
never pulls them in::

    from maipp_bench.envs.pettingzoo import MAIPPParallelEnv

    env = MAIPPParallelEnv(n_agents=2, budget=1.0)
    obs, infos = env.reset(seed=0)
    while env.agents:
        actions = {a: env.action_space(a).sample(mask=obs[a]["action_mask"])
                   for a in env.agents}
        obs, rewards, terminations, truncations, infos = env.step(actions)
"""

from __future__ import annotations

from collections.abc import Mapping
from numbers import Integral
from typing import Any

import numpy as np
import torch
from gymnasium import spaces
from pettingzoo import ParallelEnv
from tensordict import TensorDict, TensorDictBase

from maipp_bench.envs.config import MAIPPConfig
from maipp_bench.envs.maipp_env import METRICS, NODE_FEATURES, STATE_FEATURES, MAIPPEnv

_RESET_OPTIONS = ("instance_seed", "trial_seed")


class MAIPPParallelEnv(ParallelEnv):
    """One MAIPP episode (PROTOCOL v1) as a PettingZoo ``ParallelEnv``.

    Wraps a :class:`~maipp_bench.envs.MAIPPEnv` with ``batch_size=[1]`` (``self.env``);
    every rule of the task is that env's (docs/environment.md). Agents are
    ``"agent_0" .. "agent_{m-1}"``; all of them live until the episode ends, and then all
    of them are terminated (or truncated) together and ``agents`` becomes ``[]``.

    Observation of each agent (``N = n_nodes + 1`` roadmap nodes, ``k = k_neighbors``
    slots, float arrays in the config's ``dtype``), a ``spaces.Dict``:

    * ``"observation"``, a ``spaces.Dict`` mirroring ``("agents", "observation")``:

      - ``"node_features"``: ``Box(-inf, inf, (N, 7))``, per node the agent's own view
        ``x, y, interest_mean, interest_std, risk_ucb, intent, in_aoi``
        (``NODE_FEATURES``);
      - ``"current_node"``: ``Discrete(N)``, the node the agent last reached;
      - ``"budget"``: ``Box(0, 1, (1,))``, remaining team budget / ``B_team``;
      - ``"neighbors"``: ``Box(0, N - 1, (k,), int64)``, node index of each action slot;
      - ``"neighbor_dist"``: ``Box(0, inf, (k,))``, edge length of each slot (``inf``
        for a slot that does not exist, only with ``prune_risky_nodes``);

    * ``"action_mask"``: ``Box(0, 1, (k,), int8)``, the feasibility mask.

    (Through ``torchrl.envs.PettingZooWrapper`` the observation lands under
    ``("agent", "observation", "observation", ...)``, ``current_node`` as a one-hot
    ``[N]`` (TorchRL's encoding of a ``Discrete`` observation), the mask under
    ``("agent", "action_mask")`` and the infos as float32 under ``("agent", "info")``.)

    Actions are ``Discrete(k)``: the neighbour slot to move to. ``state()`` is the
    env's root ``"state"`` ``[N, 8]`` (``STATE_FEATURES``, team view for centralised
    critics), described by ``state_space``.

    **Deciding and non-deciding agents.** Decisions are event-driven: at a step only the
    agents flagged ``infos[agent]["deciding"]`` act (they rest at a node, are not trapped
    and have a feasible slot); the others are travelling, waiting or trapped. The rule:

    * a deciding agent's action must be given, must be an int in ``[0, k)`` and allowed by
      its ``action_mask``: a missing action raises ``ValueError`` here, a masked or
      out-of-range one ``ValueError`` from ``MAIPPEnv``;
    * a non-deciding agent's ``action_mask`` is all ones and its action is ignored: it may
      be omitted (it is then taken as 0) and any integer is accepted (not range-checked);
    * every given action must be an integer scalar, and only live agents may act:
      anything else raises ``ValueError``.

    So a policy that submits a masked action for every live agent, as PettingZoo users
    do, never fails; each step every live agent gets an observation, a reward (rewards of
    steps at which it did not decide are still paid to it), a termination, a truncation
    and an info.

    ``infos[agent]`` holds ``"deciding"`` (bool) and the env's metrics (``METRICS``:
    ``trace``, ``objective``, ``rmse``, ``distance``, ``time`` as floats;
    ``evidence_inside``, ``evidence_outside``, ``evidence_total``, ``traps``,
    ``measurements`` as ints); the metrics are the team's, the same for every agent.

    ``reset(seed=s)`` calls ``env.set_seed(s)`` (episode ``j`` after it is keyed by
    ``(s, 0, j)``, exactly as env 0 of a batched ``MAIPPEnv`` seeded ``s``);
    ``reset()`` without a seed draws the next episode. ``options`` may carry
    ``"instance_seed"`` and ``"trial_seed"`` (ints) to pin the world and the roadmap as
    the evaluation protocol does; other option keys are ignored.

    Render modes: ``"ansi"`` (``render()`` returns a text summary) or ``None``.
    """

    metadata = {"name": "maipp_v1", "render_modes": ["ansi"], "is_parallelizable": True}

    def __init__(
        self,
        config: MAIPPConfig | None = None,
        device: torch.device | str = "cpu",
        render_mode: str | None = None,
        **overrides: Any,
    ) -> None:
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(
                f"MAIPPParallelEnv: render_mode must be None or one of "
                f"{self.metadata['render_modes']}, got {render_mode!r}"
            )
        self.env = MAIPPEnv(config, batch_size=[1], device=device, **overrides)
        self.config: MAIPPConfig = self.env.config
        self.render_mode = render_mode
        cfg = self.config
        self.n_nodes, self.k = cfg.n_roadmap_nodes, cfg.k_neighbors
        self._np_dtype = np.dtype(cfg.dtype)
        self.possible_agents = [f"agent_{i}" for i in range(cfg.n_agents)]
        self._index = {a: i for i, a in enumerate(self.possible_agents)}
        self.agents: list[str] = []
        # One space object per agent, built once (PettingZoo requires the same object).
        self._observation_spaces = {a: self._make_observation_space()
                                    for a in self.possible_agents}
        self._action_spaces = {a: spaces.Discrete(self.k) for a in self.possible_agents}
        self._state_space = spaces.Box(-np.inf, np.inf, (self.n_nodes, len(STATE_FEATURES)),
                                       self._np_dtype)
        self._td: TensorDictBase | None = None  # latest root output of self.env
        self._deciding = np.zeros(cfg.n_agents, dtype=bool)

    # ================================================================== spaces
    def _make_observation_space(self) -> spaces.Dict:
        n, k, dt = self.n_nodes, self.k, self._np_dtype
        observation = spaces.Dict({
            "node_features": spaces.Box(-np.inf, np.inf, (n, len(NODE_FEATURES)), dt),
            "current_node": spaces.Discrete(n),
            "budget": spaces.Box(0.0, 1.0, (1,), dt),
            "neighbors": spaces.Box(0, n - 1, (k,), np.int64),
            "neighbor_dist": spaces.Box(0.0, np.inf, (k,), dt),
        })
        return spaces.Dict({
            "observation": observation,
            "action_mask": spaces.Box(0, 1, (k,), np.int8),
        })

    def observation_space(self, agent: str) -> spaces.Dict:
        return self._observation_spaces[self._check_agent(agent)]

    def action_space(self, agent: str) -> spaces.Discrete:
        return self._action_spaces[self._check_agent(agent)]

    @property
    def state_space(self) -> spaces.Box:
        return self._state_space

    def _check_agent(self, agent: str) -> str:
        if agent not in self._index:
            raise ValueError(
                f"MAIPPParallelEnv: unknown agent {agent!r}; agents are {self.possible_agents}"
            )
        return agent

    # ================================================================== API
    def reset(
        self, seed: int | None = None, options: dict | None = None
    ) -> tuple[dict[str, dict], dict[str, dict]]:
        if seed is not None:
            self.env.set_seed(int(seed))
        td_in = TensorDict(batch_size=[1], device=self.env.device)
        for name in _RESET_OPTIONS:
            value = (options or {}).get(name)
            if value is None:
                continue
            if isinstance(value, bool) or not isinstance(value, Integral):
                raise ValueError(f"MAIPPParallelEnv.reset: options[{name!r}] must be an int, "
                                 f"got {value!r}")
            td_in.set(name, torch.tensor([int(value)], dtype=torch.int64,
                                         device=self.env.device))
        td = self.env.reset(td_in)
        self.agents = list(self.possible_agents)
        self._td = td
        obs, infos = self._convert(td)
        return obs, infos

    def step(
        self, actions: Mapping[str, Any]
    ) -> tuple[dict, dict, dict, dict, dict]:
        if self._td is None:
            raise RuntimeError("MAIPPParallelEnv: call reset() before step()")
        if not self.agents:
            raise RuntimeError("MAIPPParallelEnv: the episode is over; call reset()")
        unknown = sorted(set(actions) - set(self.agents))
        if unknown:
            raise ValueError(
                f"MAIPPParallelEnv.step: actions for {unknown}, which are not live agents "
                f"{self.agents}"
            )
        m = self.config.n_agents
        action = torch.zeros(1, m, dtype=torch.int64)
        missing = []
        for agent in self.agents:
            i = self._index[agent]
            if agent not in actions:
                if self._deciding[i]:
                    missing.append(agent)
                continue
            value = _as_int(actions[agent], agent)
            if self._deciding[i]:  # others' actions are ignored, never range-checked
                action[0, i] = value
        if missing:
            raise ValueError(
                f"MAIPPParallelEnv.step: no action for deciding agent(s) {missing}; a "
                f"deciding agent must act (only non-deciding agents may be left out)"
            )
        td_in = TensorDict(
            agents=TensorDict(action=action.to(self.env.device), batch_size=[1, m]),
            batch_size=[1], device=self.env.device,
        )
        nxt = self.env.step(td_in).get("next")
        self._td = nxt
        obs, infos = self._convert(nxt)
        reward = nxt.get(("agents", "reward")).reshape(m).tolist()
        terminated = bool(nxt.get("terminated").reshape(()))
        truncated = bool(nxt.get("truncated").reshape(()))
        live = self.agents
        rewards = {a: float(reward[self._index[a]]) for a in live}
        terminations = dict.fromkeys(live, terminated)
        truncations = dict.fromkeys(live, truncated)
        obs = {a: obs[a] for a in live}
        infos = {a: infos[a] for a in live}
        if terminated or truncated:
            self.agents = []
        return obs, rewards, terminations, truncations, infos

    def state(self) -> np.ndarray:
        if self._td is None:
            raise RuntimeError("MAIPPParallelEnv: call reset() before state()")
        return _numpy(self._td.get("state")[0]).astype(self._np_dtype, copy=False)

    def render(self) -> str | None:
        if self.render_mode is None:
            return None
        if self._td is None:
            return "MAIPPParallelEnv: not reset"
        td = self._td
        obs = td.get(("agents", "observation"))
        budget = float(obs.get("budget")[0, 0, 0])
        nodes = obs.get("current_node")[0].tolist()
        lines = [
            f"MAIPP step {int(self.env.episode.steps[0])}  time "
            f"{float(td.get(('metrics', 'time'))[0]):.3f}  budget left {budget:.3f}  "
            f"trace {float(td.get(('metrics', 'trace'))[0]):.2f}  "
            f"rmse {float(td.get(('metrics', 'rmse'))[0]):.4f}"
        ]
        for agent in self.possible_agents:
            i = self._index[agent]
            lines.append(f"  {agent}: node {nodes[i]}"
                         f"{'  deciding' if self._deciding[i] else ''}")
        return "\n".join(lines)

    def close(self) -> None:
        self.env.close(raise_if_closed=False)

    # ================================================================== conversion
    def _convert(self, td: TensorDictBase) -> tuple[dict[str, dict], dict[str, dict]]:
        """Per-agent observations and infos of a root output of ``self.env`` (env 0)."""
        ag = td.get("agents")
        ob = ag.get("observation")
        dt = self._np_dtype
        feats = _numpy(ob.get("node_features")[0]).astype(dt, copy=False)
        cur = _numpy(ob.get("current_node")[0]).astype(np.int64, copy=False)
        budget = _numpy(ob.get("budget")[0]).astype(dt, copy=False)
        nbrs = _numpy(ob.get("neighbors")[0]).astype(np.int64, copy=False)
        ndist = _numpy(ob.get("neighbor_dist")[0]).astype(dt, copy=False)
        mask = _numpy(ag.get("action_mask")[0]).astype(np.int8)
        self._deciding = _numpy(ag.get("deciding")[0]).astype(bool)
        # .item(): python int for the count metrics (int64), float for the others
        metrics = {name: td.get(("metrics", name))[0].item() for name in METRICS}
        obs, infos = {}, {}
        for agent in self.possible_agents:
            i = self._index[agent]
            obs[agent] = {
                "observation": {
                    "node_features": feats[i].copy(),
                    "current_node": np.int64(cur[i]),
                    "budget": budget[i].copy(),
                    "neighbors": nbrs[i].copy(),
                    "neighbor_dist": ndist[i].copy(),
                },
                "action_mask": mask[i].copy(),
            }
            infos[agent] = {"deciding": bool(self._deciding[i]), **metrics}
        return obs, infos


def _numpy(t: torch.Tensor) -> np.ndarray:
    return t.detach().cpu().numpy()


def _as_int(value: Any, agent: str) -> int:
    """An integer scalar (python or numpy int, 0-d or 1-element integer array/tensor)."""
    if isinstance(value, torch.Tensor):
        if value.numel() == 1 and not value.dtype.is_floating_point and \
                value.dtype != torch.bool and not value.dtype.is_complex:
            return int(value.reshape(()))
    elif isinstance(value, np.ndarray):
        if value.size == 1 and np.issubdtype(value.dtype, np.integer):
            return int(value.reshape(()))
    elif isinstance(value, Integral) and not isinstance(value, bool):
        if -(2**63) <= int(value) < 2**63:  # fits the env's int64 action
            return int(value)
    raise ValueError(
        f"MAIPPParallelEnv.step: the action of {agent} must be an integer slot, got {value!r}"
    )
