"""PPO pieces of the learned methods, registered by name: critics and losses.

An algorithm config (``conf/algo/<name>.yaml``) names its ``feature_set`` (what the
network sees), its ``critic`` and its ``loss``; this module turns those names into
TorchRL objects. Adding a variant is one entry here and one YAML.

* ``critic: shared``: the paper's network, one encoder pass for both heads.
* ``critic: state``: MAPPO's centralised critic on the team ``state``.
* ``loss: ppo``: :class:`torchrl.objectives.ClipPPOLoss` (paper: clip 0.2, value 0.5,
  no entropy); ``loss: mappo``: :class:`torchrl.objectives.MAPPOLoss`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from torchrl.modules import ProbabilisticActor
from torchrl.objectives import ClipPPOLoss, MAPPOLoss

from maipp_bench.algos.attention import AttentionConfig
from maipp_bench.algos.modules import (
    LOG_PROB_KEY,
    PRECISIONS,
    AttentionCore,
    StateCritic,
    decision_actor,
    shared_value,
    state_value,
)
from maipp_bench.envs.maipp_env import STATE_FEATURES


@dataclass
class NetConfig:
    """Network sizes (reference code: 128 dims, 4 heads, feed-forward 512). The encoding's
    size is the env's ``node_encoding_dim`` (paper: 32)."""

    embed_dim: int = 128
    heads: int = 4
    ff_dim: int = 512
    encoder_layers: int = 1


@dataclass
class AlgoConfig:
    """A learned method's algorithm (Hydra group ``algo``). Defaults: the paper's PPO."""

    name: str = "ours"
    feature_set: str = "ours"  # paper: ours adds risk UCB and intent to CAtNIPP's inputs
    critic: str = "shared"
    loss: str = "ppo"
    lr: float = 1e-4  # paper: Adam 1e-4
    lr_decay: float = 0.96  # paper: x 0.96 every 32 updates
    lr_decay_every: int = 32
    minibatch: int = 256  # paper
    epochs: int = 8  # paper
    # > 0: end an update's epochs at the first minibatch whose approximate KL to the
    # collecting policy exceeds 1.5 x this (as Stable-Baselines3); 0: never (paper)
    target_kl: float = 0.0
    clip_epsilon: float = 0.2  # ref
    critic_coef: float = 0.5  # ref: loss = policy + 0.5 value
    entropy_coef: float = 0.0  # ref: no entropy bonus
    grad_clip: float = 10.0  # ref
    gamma: float = 1.0  # ref (single agent); per decision
    lmbda: float = 0.95  # ref (multi-agent)
    normalize_advantage: bool = False
    # > 0: while collecting, deciding agents broadcast trajectory intents TI(a, j) with
    # a = intent_rollouts, j = intent_depth (the paper's agents always do; without them the
    # network never sees a non-zero intent feature in training). 0: no intents.
    intent_rollouts: int = 0
    intent_depth: int = 5
    # float32 (paper), or bf16: the networks' matrix products under autocast while
    # training (collection, intents and the loss); weights, optimiser, checkpoints and
    # every evaluation stay float32 (docs/training.md, "Precision")
    precision: str = "float32"
    net: NetConfig = field(default_factory=NetConfig)


def net_config(algo: Any, pe_dim: int) -> AttentionConfig:
    """The network config of an algo config (anything with ``feature_set`` and ``net``)."""
    from maipp_bench.algos.attention import FEATURE_SETS

    if algo.feature_set not in FEATURE_SETS:
        raise ValueError(f"algo.feature_set={algo.feature_set!r}; valid: {sorted(FEATURE_SETS)}")
    net = algo.net
    return AttentionConfig(n_features=len(FEATURE_SETS[algo.feature_set]),
                           embed_dim=net.embed_dim, heads=net.heads, ff_dim=net.ff_dim,
                           encoder_layers=net.encoder_layers, pe_dim=pe_dim)


def _shared(algo: Any, core: AttentionCore) -> TensorDictModule | None:
    return None


def _state(algo: Any, core: AttentionCore) -> TensorDictModule:
    return state_value(StateCritic(len(STATE_FEATURES), core.net.cfg, core.autocast))


# critic name -> the critic on decision rows (None: the actor's own value head)
CRITICS: dict[str, Callable[[Any, AttentionCore], TensorDictModule | None]] = {
    "shared": _shared,
    "state": _state,
}


def _ppo(algo: Any, actor: ProbabilisticActor, critic: TensorDictModule | None) -> ClipPPOLoss:
    return ClipPPOLoss(actor, critic if critic is not None else shared_value(),
                       clip_epsilon=algo.clip_epsilon, entropy_bonus=algo.entropy_coef > 0,
                       entropy_coeff=algo.entropy_coef or None, critic_coeff=algo.critic_coef,
                       loss_critic_type="l2", normalize_advantage=algo.normalize_advantage)


def _mappo(algo: Any, actor: ProbabilisticActor, critic: TensorDictModule | None) -> MAPPOLoss:
    if critic is None:
        raise ValueError("loss 'mappo' needs a centralised critic: set algo.critic=state")
    # Decision rows are flat [B]: no agent dim to exclude from advantage normalisation.
    return MAPPOLoss(actor, critic, clip_epsilon=algo.clip_epsilon,
                     entropy_coeff=algo.entropy_coef, critic_coeff=algo.critic_coef,
                     loss_critic_type="l2", normalize_advantage=algo.normalize_advantage,
                     normalize_advantage_exclude_dims=())


LOSSES: dict[str, Callable[..., ClipPPOLoss]] = {"ppo": _ppo, "mappo": _mappo}


@dataclass
class Learner:
    """Everything a learned method trains: network, actor, critic and loss."""

    core: AttentionCore
    actor: ProbabilisticActor
    critic: TensorDictModule | None
    loss: ClipPPOLoss

    def parameters(self) -> list[torch.nn.Parameter]:
        return list(self.loss.parameters())

    def precision_modules(self) -> list[torch.nn.Module]:
        """The networks that carry a precision (their own ``autocast`` attribute: the
        TensorDictModules around them only forward it): the core and, with a centralised
        critic, that critic (the loss's ``modules()`` holds neither). Set them together,
        or run them in float32 with :func:`full_precision`."""
        nets = [self.actor] if self.critic is None else [self.actor, self.critic]
        return [m for net in nets for m in net.modules() if "autocast" in vars(m)]

    def action_log_prob(self, rows: TensorDictBase, minibatch: int,
                        generator: torch.Generator | None = None) -> torch.Tensor:
        """Each decision row's log-probability of its ``action`` as the loss computes it
        (train mode, no gradient, ``minibatch`` rows at a time in a random order), in the
        rows' order: what PPO's first ratio sets against the collector's stored one."""
        self.core.train()
        order = torch.randperm(rows.numel(), generator=generator).to(rows.device)
        out = torch.empty(rows.numel(), device=rows.device)
        with torch.no_grad():
            for chunk in order.split(minibatch):
                mb = rows[chunk].clone()
                out[chunk] = self.actor.get_dist(mb).log_prob(mb.get("action"))
        return out


def build_learner(algo: Any, pe_dim: int, threshold: float,
                  device: str | torch.device = "cpu") -> Learner:
    """Network, actor, critic and loss of an algo config (errors list the valid names), with
    the network on ``device`` before the loss takes its parameters."""
    for kind, name, table in (("critic", algo.critic, CRITICS), ("loss", algo.loss, LOSSES),
                              ("precision", algo.precision, PRECISIONS)):
        if name not in table:
            raise ValueError(f"algo.{kind}={name!r}; valid: {sorted(table)}")
    core = AttentionCore(algo.feature_set, net_config(algo, pe_dim), threshold,
                         PRECISIONS[algo.precision]).to(device)
    actor = decision_actor(core)
    critic = CRITICS[algo.critic](algo, core)
    if critic is not None:
        critic = critic.to(device)
    loss = LOSSES[algo.loss](algo, actor, critic)
    loss.set_keys(sample_log_prob=LOG_PROB_KEY)
    return Learner(core, actor, critic, loss)
