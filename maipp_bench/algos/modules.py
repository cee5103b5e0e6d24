"""TorchRL modules of the learned methods: one row per decision, and the team policy.

The env is event-driven: at a step only *deciding* agents act (usually one). Learning
therefore works on **decisions**, one row per (env, agent, step) where the agent decided,
in this flat layout (``B`` decisions, ``N`` nodes, ``k`` slots)::

    node_features [B, N, 7]   current_node [B]   budget [B, 1]   neighbors [B, k]
    action_mask [B, k]        hidden [B, 2, d]   node_encoding [B, N, D]   state [B, N, 8]

:func:`decision_actor` maps such rows to a masked categorical over the slots (and, for
the paper's network, the value of the shared encoder pass); :class:`TeamPolicy` is the
env-facing policy a collector runs: it gathers the deciding agents' rows from the env's
``("agents", ...)`` keys, runs the actor on them only, and scatters actions, log-probs,
values and the agents' new LSTM states back. Non-deciding agents get slot 0 (ignored by
the env) and keep their LSTM state.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager, nullcontext
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictModuleBase
from torch import nn
from torchrl.modules import MaskedCategorical, ProbabilisticActor

from maipp_bench.algos.attention import AttentionConfig, AttentionPolicyNet, feature_columns

HIDDEN_KEY = ("agents", "hidden")  # [E, m, 2, d]: LSTM (h, c) of each agent's trajectory
LOG_PROB_KEY = "action_log_prob"
CORE_IN_KEYS = ["node_features", "node_encoding", "current_node", "budget", "neighbors",
                "action_mask", "hidden"]


# algo.precision -> the dtype the networks' matrix products run in under autocast while
# training (None: float32 throughout). Weights, optimiser and evaluation stay float32.
PRECISIONS: dict[str, torch.dtype | None] = {"float32": None, "bf16": torch.bfloat16}


def autocast_to(dtype: torch.dtype | None, device: torch.device) -> Any:
    """Autocast to ``dtype`` on ``device``'s type, or nothing for None."""
    return nullcontext() if dtype is None else torch.autocast(device.type, dtype=dtype)


@contextmanager
def full_precision(*modules: nn.Module) -> Iterator[None]:
    """Run ``modules`` (with an ``autocast`` attribute) in float32 inside the block: a
    held-out evaluation during mixed-precision training scores what the saved float32
    network will play."""
    saved = [m.autocast for m in modules]
    for m in modules:
        m.autocast = None
    try:
        yield
    finally:
        for m, dtype in zip(modules, saved):
            m.autocast = dtype


class AttentionCore(nn.Module):
    """The paper's network on decision rows: a feature set's columns, float32 inside
    (``autocast``: the matrix products in that dtype, the outputs float32).

    Returns masked logits ``[B, k]``, the value ``[B, 1]`` of the same encoder pass and
    the new LSTM state ``[B, 2, d]``.
    """

    def __init__(self, feature_set: str, net: AttentionConfig, threshold: float,
                 autocast: torch.dtype | None = None) -> None:
        super().__init__()
        self.autocast = autocast
        self.feature_set = feature_set
        self.register_buffer("columns", torch.tensor(feature_columns(feature_set)),
                             persistent=False)
        self.net = AttentionPolicyNet(net, threshold)

    @property
    def hidden_dim(self) -> int:
        return self.net.cfg.embed_dim

    def forward(self, node_features, node_encoding, current_node, budget, neighbors,
                action_mask, hidden, positions=None):
        """The network on decision rows; ``positions``: see :class:`AttentionPolicyNet`
        (given, ``node_encoding`` may be None)."""
        x = node_features.index_select(-1, self.columns).float()
        h, c = hidden.float().unbind(-2)
        enc = None if positions is not None else node_encoding.float()
        with autocast_to(self.autocast, x.device):
            logits, value, (h, c) = self.net(x, enc, current_node, budget.float(), neighbors,
                                             action_mask, (h, c), positions)
        # .float() is the identity on float32 outputs: full precision keeps its bits.
        return logits.float(), value.float(), torch.stack([h, c], -2).float()


class StateCritic(nn.Module):
    """MAPPO's centralised critic: the team ``state`` (plus a one-hot of the deciding
    agent's node, so the value is the agent's) through one attention layer, mean-pooled."""

    def __init__(self, state_features: int, net: AttentionConfig,
                 autocast: torch.dtype | None = None) -> None:
        super().__init__()
        self.autocast = autocast  # as AttentionCore's
        d = net.embed_dim
        self.embed = nn.Linear(state_features + 1, d)
        self.pos = nn.Linear(net.pe_dim, d)
        layer = nn.TransformerEncoderLayer(d, net.heads, net.ff_dim, dropout=0.0,
                                           batch_first=True, norm_first=True)
        self.encoder = nn.TransformerEncoder(layer, 1, enable_nested_tensor=False)
        self.head = nn.Sequential(nn.Linear(2 * d, d), nn.Tanh(), nn.Linear(d, 1))

    def forward(self, state: torch.Tensor, node_encoding: torch.Tensor,
                current_node: torch.Tensor) -> torch.Tensor:
        here = nn.functional.one_hot(current_node, state.shape[-2]).unsqueeze(-1)
        with autocast_to(self.autocast, state.device):
            h = self.encoder(self.embed(torch.cat([state.float(), here.float()], -1))
                             + self.pos(node_encoding.float()))
            mine = h[torch.arange(h.shape[0], device=h.device), current_node]
            return self.head(torch.cat([h.mean(-2), mine], -1)).float()


def decision_actor(core: AttentionCore) -> ProbabilisticActor:
    """Masked categorical policy over the slots of decision rows.

    Writes ``action``, ``action_log_prob``, ``logits``, ``live_value`` (the value head of
    the same forward pass) and ``next_hidden``.
    """
    module = TensorDictModule(core, in_keys=CORE_IN_KEYS,
                              out_keys=["logits", "live_value", "next_hidden"])
    return ProbabilisticActor(
        module, in_keys={"logits": "logits", "mask": "action_mask"}, out_keys=["action"],
        distribution_class=MaskedCategorical, return_log_prob=True,
        log_prob_key=LOG_PROB_KEY,
    )


def shared_value() -> TensorDictModule:
    """The critic of the paper's network: the value the actor's pass already computed
    (one encoder pass per row for both heads, as the paper's shared network does)."""
    return TensorDictModule(lambda v: v, in_keys=["live_value"], out_keys=["state_value"])


def state_value(critic: StateCritic) -> TensorDictModule:
    """MAPPO's centralised critic on decision rows."""
    return TensorDictModule(critic, in_keys=["state", "node_encoding", "current_node"],
                            out_keys=["state_value"])


def decision_rows(td: TensorDictBase, e_idx: torch.Tensor, a_idx: torch.Tensor,
                  hidden: torch.Tensor) -> TensorDict:
    """The flat decision rows of agents ``a_idx`` in envs ``e_idx`` of an env tensordict."""
    obs = td.get(("agents", "observation"))
    enc = td.get("node_encoding")
    return TensorDict(
        node_features=obs.get("node_features")[e_idx, a_idx],
        current_node=obs.get("current_node")[e_idx, a_idx],
        budget=obs.get("budget")[e_idx, a_idx],
        neighbors=obs.get("neighbors")[e_idx, a_idx],
        action_mask=td.get(("agents", "action_mask"))[e_idx, a_idx],
        hidden=hidden[e_idx, a_idx],
        node_encoding=enc[e_idx],
        state=td.get("state")[e_idx],
        batch_size=[e_idx.shape[0]],
    )


class TeamPolicy(TensorDictModuleBase):
    """Env-facing policy: the actor on the deciding agents' rows only.

    Reads the env's ``("agents", ...)`` keys, ``node_encoding``, ``state`` and the agents'
    LSTM states ``("agents", "hidden")`` (zeros when absent, e.g. right after a reset);
    writes ``("agents", "action")``, ``("agents", "action_log_prob")``,
    ``("agents", "state_value")`` (zeros for agents that do not decide) and the new LSTM
    states under ``("next", "agents", "hidden")``.

    Args:
        actor: a :func:`decision_actor`.
        critic: optional separate critic on decision rows (MAPPO); by default the actor's
            own ``live_value``.
        intent: optional ``intent(td, rows, e_idx, a_idx)`` that writes the deciding
            agents' broadcast intents into ``td`` (its ``KEYS`` join ``out_keys``)
            (:class:`~maipp_bench.algos.rollouts.IntentBroadcast`).
    """

    in_keys = [("agents", "observation"), ("agents", "action_mask"), ("agents", "deciding"),
               "node_encoding", "state"]
    OUT_KEYS = [("agents", "action"), ("agents", LOG_PROB_KEY), ("agents", "state_value"),
                ("next", *HIDDEN_KEY)]
    out_keys = OUT_KEYS

    def __init__(self, actor: ProbabilisticActor, critic: TensorDictModule | None = None,
                 hidden_dim: int = 128, intent: Any = None) -> None:
        super().__init__()
        self.actor, self.critic, self.hidden_dim = actor, critic, hidden_dim
        self.intent = intent
        if intent is not None:
            self.out_keys = [*self.OUT_KEYS, *intent.KEYS]

    def forward(self, td: TensorDictBase, **kwargs: Any) -> TensorDictBase:
        deciding = td.get(("agents", "deciding"))
        e, m = deciding.shape
        hidden = td.get(HIDDEN_KEY, None)
        if hidden is None:
            hidden = torch.zeros(e, m, 2, self.hidden_dim, device=deciding.device)
        e_idx, a_idx = deciding.nonzero(as_tuple=True)
        action = torch.zeros(e, m, dtype=torch.int64, device=deciding.device)
        log_prob = torch.zeros(e, m, device=deciding.device)
        value = torch.zeros(e, m, 1, device=deciding.device)
        new_hidden = hidden.clone()
        if e_idx.numel():
            rows = self.actor(decision_rows(td, e_idx, a_idx, hidden))
            if self.critic is not None:
                rows = self.critic(rows)
            else:
                rows.set("state_value", rows.get("live_value"))
            action[e_idx, a_idx] = rows.get("action")
            log_prob[e_idx, a_idx] = rows.get(LOG_PROB_KEY).detach()
            value[e_idx, a_idx] = rows.get("state_value").detach()
            new_hidden[e_idx, a_idx] = rows.get("next_hidden").detach()
        if self.intent is not None:
            self.intent(td, rows if e_idx.numel() else None, e_idx, a_idx)
        td.set(("agents", "action"), action)
        td.set(("agents", LOG_PROB_KEY), log_prob)
        td.set(("agents", "state_value"), value)
        td.set(("next", *HIDDEN_KEY), new_hidden)
        return td
