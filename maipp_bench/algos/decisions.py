"""From collected env steps to per-agent decisions with GAE advantages (a semi-MDP).

Agents act asynchronously: agent a's transition runs from one of its decisions to the
next one (or to the episode's end), while the env steps for everyone in between. Each
decision's reward is the sum of the rewards agent a received over that span (team gain
and its own penalties), its next value is the value at its next decision, and the
sequence of an agent's decisions is what GAE runs along. Only deciding agents' steps
enter the loss; nothing is learnt from steps at which an agent was travelling.

``torchrl.objectives.value.GAE`` does the estimation, on a ``[E * m, D]`` layout (D =
most decisions of one agent in the batch) padded with terminal zero-reward steps that
are dropped afterwards. An agent's last decision of the batch is bootstrapped with the
value of its state at the batch's end (the ``bootstrap`` argument).
"""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.objectives.value import GAE

from maipp_bench.algos.modules import HIDDEN_KEY, LOG_PROB_KEY, decision_rows


def _next_index(flags: torch.Tensor, strict: bool) -> torch.Tensor:
    """``[..., T]``: the first index t' >= t (or > t when ``strict``) with ``flags[t']``,
    T where there is none."""
    t = flags.shape[-1]
    idx = torch.where(flags, torch.arange(t, device=flags.device), t)
    if strict:
        idx = torch.cat([idx[..., 1:], torch.full_like(idx[..., :1], t)], -1)
    return idx.flip(-1).cummin(-1).values.flip(-1)


def decision_batch(batch: TensorDictBase, bootstrap: torch.Tensor, gamma: float,
                   lmbda: float) -> TensorDict:
    """Decision rows of a collected batch with ``advantage`` and ``value_target``.

    Args:
        batch: collector output ``[E, T]`` (policy :class:`~maipp_bench.algos.modules.TeamPolicy`).
        bootstrap: ``[E, m]`` value of each agent's state after the batch's last step.
        gamma, lmbda: GAE discount (per decision) and lambda.

    Returns:
        A ``[S]`` tensordict of the flat decision layout plus ``action``,
        ``action_log_prob``, ``state_value``, ``reward``, ``advantage``, ``value_target``.
    """
    e, t = batch.batch_size
    agents = batch.get("agents")
    deciding = agents.get("deciding").transpose(1, 2)  # [E, m, T]
    m = deciding.shape[1]
    done = batch.get(("next", "done")).reshape(e, 1, t).expand(e, m, t)
    reward = batch.get(("next", "agents", "reward")).squeeze(-1).transpose(1, 2).double()
    value = agents.get("state_value").squeeze(-1).transpose(1, 2)

    # A decision's span ends before the agent's next decision, at the episode's end, or
    # at the batch's end.
    next_dec = _next_index(deciding, strict=True)
    end = torch.minimum(next_dec - 1, _next_index(done, strict=False)).clamp_max(t - 1)
    csum = reward.cumsum(-1)
    span_reward = csum.gather(-1, end) - csum + reward
    episode_over = done.gather(-1, end)  # terminal for this agent (max-steps cuts included)
    has_next = (next_dec < t) & ~episode_over
    next_value = torch.where(has_next, value.gather(-1, next_dec.clamp_max(t - 1)),
                             bootstrap.unsqueeze(-1).to(value.dtype))

    # Flat rows in (env, agent, time) order, then the padded [E*m, D] layout for GAE.
    e_idx, a_idx, t_idx = deciding.nonzero(as_tuple=True)
    rank = (deciding.cumsum(-1) - 1)[e_idx, a_idx, t_idx]
    seq = e_idx * m + a_idx
    n_dec = deciding.sum(-1).reshape(-1)
    d = int(n_dec.max()) if e_idx.numel() else 0
    last = rank == n_dec[seq] - 1

    def padded(values: torch.Tensor, fill: float | bool) -> torch.Tensor:
        out = torch.full((e * m, d, 1), fill, dtype=values.dtype, device=values.device)
        out[seq, rank, 0] = values
        return out

    term = episode_over[e_idx, a_idx, t_idx]
    gae_td = TensorDict(
        state_value=padded(value[e_idx, a_idx, t_idx].float(), 0.0),
        next=TensorDict(
            state_value=padded(next_value[e_idx, a_idx, t_idx].float(), 0.0),
            reward=padded(span_reward[e_idx, a_idx, t_idx].float(), 0.0),
            done=padded(term | last, True),
            terminated=padded(term, True),
            batch_size=[e * m, d],
        ),
        batch_size=[e * m, d],
    )
    GAE(gamma=gamma, lmbda=lmbda, value_network=None)(gae_td)

    # Gather each decision's own agent straight from the [E * T] steps (no per-step copy of
    # every agent's features).
    steps = batch.exclude("next").reshape(-1)
    step = e_idx * t + t_idx
    rows = decision_rows(steps, step, a_idx, steps.get(HIDDEN_KEY))
    rows.update({
        "action": steps.get(("agents", "action"))[step, a_idx],
        LOG_PROB_KEY: steps.get(("agents", LOG_PROB_KEY))[step, a_idx],
        "state_value": gae_td.get("state_value")[seq, rank],
        "reward": gae_td.get(("next", "reward"))[seq, rank],
        "advantage": gae_td.get("advantage")[seq, rank],
        "value_target": gae_td.get("value_target")[seq, rank],
    })
    return rows
