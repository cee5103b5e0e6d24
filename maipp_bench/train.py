"""``python -m maipp_bench.train algo=ours``: PPO on the batched MAIPP env (Hydra CLI).

Reads top to bottom: one update = collect a batch with TorchRL's ``Collector`` (every
env reset from a seed of (seed, update) every ``reset_every`` updates, by default every
one, so a run resumed from a checkpoint replays exactly what an uninterrupted one
would), turn env steps into per-agent decisions with GAE
(:mod:`maipp_bench.algos.decisions`), then ``epochs`` passes of minibatches from a
TorchRL replay buffer through ``ClipPPOLoss`` / ``MAPPOLoss``. Every
``checkpoint_every`` updates the whole training state is written atomically to
``<run>/checkpoint.pt``; ``resume=<path>`` continues it (same curve, same run folder).

Config groups (``maipp_bench/conf``): ``algo`` (ours, catnipp, mappo), ``env``
(risk_aware, risk_unaware, tiny), ``logger`` (csv, wandb, tensorboard); any field can be overridden,
e.g. ``python -m maipp_bench.train algo=catnipp n_envs=16 algo.lr=5e-5 env.budget=4``.
"""

from __future__ import annotations

import dataclasses
import json
import math
import shlex
import sys
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import hydra
import torch
from hydra.core.config_store import ConfigStore
from hydra.core.hydra_config import HydraConfig
from omegaconf import OmegaConf, ValidationError
from tensordict import TensorDict, TensorDictBase
from torchrl.collectors import Collector
from torchrl.data import Composite, LazyTensorStorage, ReplayBuffer, Unbounded
from torchrl.data.replay_buffers import SamplerWithoutReplacement
from torchrl.envs import Compose, TensorDictPrimer, Transform, TransformedEnv
from tqdm import tqdm

from maipp_bench.algos.checkpoint import (
    FORMAT,
    atomic_save,
    average_policies,
    export_policy,
    load_core,
    resolve,
    slim,
)
from maipp_bench.algos.decisions import decision_batch
from maipp_bench.algos.learned import LearnedPolicy
from maipp_bench.algos.modules import HIDDEN_KEY, TeamPolicy, decision_rows, full_precision
from maipp_bench.algos.ppo import AlgoConfig, Learner, build_learner
from maipp_bench.algos.registry import MethodSpec, get_method
from maipp_bench.algos.rollouts import IntentBroadcast, check_training_intents
from maipp_bench.allocator import keep_freed_memory
from maipp_bench.envs import rng
from maipp_bench.envs.config import MAIPPConfig, check_device
from maipp_bench.envs.maipp_env import MAIPPEnv
from maipp_bench.hardware import cpu_model, machine_name, native_bf16
from maipp_bench.heldout import HELDOUT_SETS, check_heldout, heldout_seeds
from maipp_bench.protocol.leaderboard import git_commit
from maipp_bench.protocol.protocol import file_sha256, load_protocol
from maipp_bench.protocol.runner import run_chunk, trial_seeds

_PY_TYPES = {"int": int, "float": float, "bool": bool, "str": str}
# The env group's schema: every MAIPPConfig field, typed (MAIPPConfig validates ranges).
EnvSchema = dataclasses.make_dataclass("EnvSchema", [
    (f.name, _PY_TYPES[f.type] if isinstance(f.type, str) else f.type, f.default)
    for f in dataclasses.fields(MAIPPConfig)
])


@dataclass
class LoggerConfig:
    """Where scalars go besides ``<run>/curve.jsonl`` (always written)."""

    backend: str = "csv"  # csv | wandb | tensorboard
    project: str = "maipp_bench"
    offline: bool = True  # wandb: never needs the network unless asked


@dataclass
class TrainConfig:
    """``python -m maipp_bench.train``'s config (defaults: conf/train.yaml)."""

    algo: AlgoConfig = field(default_factory=AlgoConfig)
    env: Any = field(default_factory=EnvSchema)
    logger: LoggerConfig = field(default_factory=LoggerConfig)
    seed: int = 0
    device: str = "cpu"
    # torch threads: 1 per run when runs share the cores (the most work per core); one
    # run alone on the 2-core box updates 1.6x faster with 2 (docs/performance.md)
    threads: int = 1
    n_envs: int = 8  # envs stepped together
    steps_per_batch: int = 160  # env steps per env per update (> one episode at B = 5)
    # Updates per fresh start of every env from a seed of (seed, update). 1: each update
    # collects from new episodes, so steps_per_batch must cover one. N > 1: episodes run on
    # across the N updates in between, so a wide, short batch (n_envs=128
    # steps_per_batch=20 reset_every=8) still sees whole episodes: on a GPU, where an env
    # step costs about the same at any width, its update is 4.4x faster than 16 envs x 160
    # steps (docs/performance.md). The intervals (and checkpoint_every's) count from the
    # update a process starts at, and checkpoint_every must be a multiple of it, so every
    # checkpoint falls on a fresh start and a resumed run continues the same curve (a
    # resume from a max_minutes stop starts fresh episodes there and counts from it).
    reset_every: int = 1
    total_updates: int = 200
    max_minutes: float = 0.0  # > 0: stop (after a checkpoint) once this much wall time is used
    checkpoint_every: int = 5
    eval_every: int = 10  # evaluation on held-out seeds (0: never); it selects best.pt
    eval_episodes: int = 16
    eval_budget: float = 3.0
    # What the held-out evaluation runs: "greedy" (the network's argmax, cheap) or a
    # registered learned method with this network, e.g. "ours_ti" (what the leaderboard
    # ranks); at eval_budgets if given (score: geometric mean of Tr(P_f) over them, so
    # every budget counts by its relative change), else at eval_budget.
    eval_method: str = "greedy"
    eval_budgets: list[float] = field(default_factory=list)
    eval_heldout: int = 2  # the held-out episode set (maipp_bench/heldout.py: 1 = one roadmap)
    # Keep the weights of every evaluated update in <run>/snapshots/update_<N>.pt (slim
    # policy files): best.pt is chosen by the held-out score, which may not rank candidates
    # as the leaderboard's method would; snapshots let them be compared afterwards
    # (benchmarks/paired_subset.py --heldout <run>/snapshots/*.pt --heldout-method ours_ti)
    # or averaged (export_from=N-M).
    keep_snapshots: bool = False
    # Keep them every this many updates instead (implies keep_snapshots; 0: at each
    # held-out evaluation): a run that averages its snapshots needs no evaluation to choose
    # them (eval_every=0).
    snapshot_every: int = 0
    resume: str | None = None
    # Start from this network's weights (a checkpoint or an exported policy, e.g. "ours"):
    # fine-tuning, with a fresh optimizer and update count. Ignored when resuming.
    init: str | None = None
    export: str | None = None  # at the end: write the policy file + JSON card here
    # best (lowest held-out eval Tr(P); else last) | last | N: the snapshot of update N
    # (keep_snapshots=true), e.g. one chosen afterwards with benchmarks/paired_subset.py;
    # resume=<run>/checkpoint.pt total_updates=0 exports from a finished run.
    export_from: str = "best"
    export_note: str = ""  # how the exported update was chosen (written into the card)
    progress: bool = True


ConfigStore.instance().store(name="train_schema", node=TrainConfig)


def _logger(cfg: Any, run_dir: Path) -> Any:
    from torchrl.record.loggers import CSVLogger, TensorboardLogger, WandbLogger

    name = f"{cfg.algo.name}"
    loggers = {
        "csv": lambda: CSVLogger(name, log_dir=str(run_dir / "logs")),
        "tensorboard": lambda: TensorboardLogger(name, log_dir=str(run_dir / "logs")),
        "wandb": lambda: WandbLogger(name, offline=cfg.logger.offline, save_dir=str(run_dir),
                                     project=cfg.logger.project),
    }
    if cfg.logger.backend not in loggers:
        raise ValueError(f"logger.backend={cfg.logger.backend!r}; valid: {sorted(loggers)}")
    return loggers[cfg.logger.backend]()


class Materialise(Transform):
    """Give the agents' node features their own memory: with one shared belief the env
    returns an expanded view (one copy for all agents), which collectors cannot update
    in place."""

    KEY = ("agents", "observation", "node_features")

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        next_tensordict.set(self.KEY, next_tensordict.get(self.KEY).contiguous())
        return next_tensordict

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase
               ) -> TensorDictBase:
        return self._call(tensordict_reset)


def make_env(env_cfg: MAIPPConfig, n_envs: int, hidden_dim: int, device: str) -> TransformedEnv:
    """The training env: MAIPPEnv with the Laplacian encoding and zeroed LSTM states at
    every (partial) reset, held under ``("agents", "hidden")``."""
    base = MAIPPEnv(env_cfg, batch_size=[n_envs], device=device)
    m = env_cfg.n_agents
    spec = Composite(agents=Composite(hidden=Unbounded((n_envs, m, 2, hidden_dim),
                                                       device=device), shape=(n_envs, m)),
                     shape=(n_envs,), device=device)
    return TransformedEnv(base, Compose(Materialise(), TensorDictPrimer(spec, expand_specs=False)))


def _bootstrap(learner: Learner, last: TensorDict) -> torch.Tensor:
    """``[E, m]``: every agent's value after the batch's last step."""
    e, m = last.get(("agents", "deciding")).shape
    e_idx = torch.arange(e, device=last.device).repeat_interleave(m)
    a_idx = torch.arange(m, device=last.device).repeat(e)
    rows = decision_rows(last, e_idx, a_idx, last.get(HIDDEN_KEY))
    with torch.no_grad():
        if learner.critic is not None:
            value = learner.critic(rows).get("state_value")
        else:
            value = learner.actor.module[0](rows).get("live_value")
    return value.view(e, m)


def make_collection(cfg: Any, env_cfg: MAIPPConfig, learner: Learner
                    ) -> tuple[TransformedEnv, Collector, ReplayBuffer]:
    """The training env, its TorchRL collector (policy: the learner's TeamPolicy) and the
    replay buffer an update's decisions are sampled from."""
    env = make_env(env_cfg, cfg.n_envs, learner.core.hidden_dim, cfg.device)
    algo = cfg.algo
    intent = (IntentBroadcast(env.base_env, learner.core, algo.intent_rollouts,
                              algo.intent_depth) if algo.intent_rollouts != 0 else None)
    policy = TeamPolicy(learner.actor, learner.critic, learner.core.hidden_dim, intent)
    collector = Collector(env, policy, frames_per_batch=cfg.n_envs * cfg.steps_per_batch,
                          total_frames=-1, auto_register_policy_transforms=False,
                          # each batch is read within its update only (decision rows and
                          # metrics are indexed copies): no clone of the whole rollout. On
                          # CPU only: on CUDA TorchRL then runs the collector, and the
                          # caller's work after it, on a side stream
                          return_same_td=torch.device(cfg.device).type == "cpu")
    buffer = ReplayBuffer(storage=LazyTensorStorage(cfg.n_envs * cfg.steps_per_batch
                                                    * env_cfg.n_agents, device=cfg.device),
                          sampler=SamplerWithoutReplacement(), batch_size=cfg.algo.minibatch)
    return env, collector, buffer


def collected_decisions(learner: Learner, batch: TensorDict, algo: Any) -> TensorDict:
    """A collected batch's decision rows with GAE advantages and value targets."""
    return decision_batch(batch, _bootstrap(learner, batch[:, -1].get("next")),
                          algo.gamma, algo.lmbda)


def learn(learner: Learner, optim: torch.optim.Optimizer, buffer: ReplayBuffer,
          rows: TensorDict, algo: Any) -> dict[str, list[float]]:
    """``epochs`` passes of minibatches of ``rows`` through the loss; the loss terms and
    diagnostics of every minibatch, and ``minibatches``: how many were stepped (fewer than
    all when ``algo.target_kl`` ended the update early)."""
    learner.core.train()
    buffer.empty()
    buffer.extend(rows)
    kept: dict[str, list[torch.Tensor]] = {}
    steps = 0
    for minibatch in (mb for _ in range(algo.epochs) for mb in buffer):
        out = learner.loss(minibatch)
        if algo.target_kl > 0 and float(out["kl_approx"]) > 1.5 * algo.target_kl:
            break  # the policy moved far enough from the one that collected
        total = sum(v for k, v in out.items() if k.startswith("loss_"))
        optim.zero_grad()
        total.backward()
        torch.nn.utils.clip_grad_norm_(learner.parameters(), algo.grad_clip)
        optim.step()
        steps += 1
        for k, v in out.items():
            kept.setdefault(k, []).append(v.detach().mean())
    # Read back once per update, not once per term and minibatch: on a GPU each read
    # waits for the device, so the host could not queue the next minibatch meanwhile.
    stats = {k: torch.stack(v).tolist() for k, v in kept.items()}
    stats["minibatches"] = [float(steps)]
    return stats


def greedy_method(name: str) -> MethodSpec:
    """Greedy decoding of an in-memory network: training's model-selection method."""
    return MethodSpec(name=f"{name}_greedy", policy="attention", models_risk=True,
                      params={"mode": "greedy"}, learned=True)


def heldout_rows(core: Any, env_cfg: MAIPPConfig, episodes: int, budget: float,
                 method: MethodSpec, first: int = 0,
                 on_action: Callable[[MAIPPEnv, TensorDictBase], None] | None = None,
                 heldout: int = 2) -> list[dict[str, Any]]:
    """``method`` with the network ``core`` on ``episodes`` held-out seeds (never the
    protocol's) from the ``first``-th on, at a fixed ``budget``: one result row per episode
    (each episode's row depends on its own seeds only, so ranges can be scored apart).
    ``heldout``: the episode set (:data:`HELDOUT_SETS`). ``on_action``: see
    :func:`~maipp_bench.protocol.runner.run_chunk`."""
    seeds, trials = heldout_seeds(first, episodes, heldout)
    eval_cfg = env_cfg.replace(budget=budget, budget_min=0.0, node_encoding_dim=0)
    device = next(core.parameters()).device  # where the network is, the episodes run
    return run_chunk(method, eval_cfg, seeds, trial_seed=trials, device=device,
                     on_action=on_action, core=core)


def init_weights(learner: Learner, checkpoint: str, algo: Any, threshold: float) -> None:
    """Load the policy network of ``checkpoint`` (path or shipped name) into ``learner``
    (a separate critic, MAPPO's, starts fresh); a network of another feature set, size or
    interest threshold (an input of the network) is a ValueError naming both."""
    core, payload = load_core(checkpoint, next(learner.core.parameters()).device)
    theirs = (payload["algo"]["feature_set"], core.net.cfg, core.net.threshold)
    ours = (algo.feature_set, learner.core.net.cfg, threshold)
    if theirs != ours:
        raise ValueError(f"init={checkpoint}: its network {theirs} is not this run's {ours}")
    learner.core.load_state_dict(core.state_dict())


def eval_spec(cfg: Any) -> tuple[MethodSpec, list[float]]:
    """The held-out evaluation's method and budgets (clear errors for bad values)."""
    budgets = sorted({float(b) for b in (cfg.eval_budgets or [cfg.eval_budget])})
    if any(not math.isfinite(b) or b <= 0 for b in budgets):
        raise ValueError(f"eval_budgets={budgets}: budgets must be finite and > 0")
    check_heldout(cfg.eval_heldout)
    if cfg.eval_method == "greedy":
        return greedy_method(cfg.algo.name), budgets
    spec = get_method(cfg.eval_method)  # ValueError listing the registered methods
    # The method must play this network as the leaderboard does (same features, roadmap).
    if not (spec.learned and spec.policy == "attention"
            and cfg.eval_method.startswith(f"{cfg.algo.name}_")):
        raise ValueError(f"eval_method={cfg.eval_method!r}: 'greedy' or a method of the "
                         f"{cfg.algo.name!r} network (e.g. {cfg.algo.name}_ti)")
    return spec, budgets


def warn_unseen_intents(cfg: Any, spec: MethodSpec) -> None:
    """Warn when a network trained with intents is selected by a method that sends none:
    its held-out score (and so ``best.pt``) then sees the intent feature at zero, which
    the network never saw in training."""
    sends = LearnedPolicy.sends_intents(spec.params)
    if cfg.algo.intent_rollouts > 0 and cfg.eval_every > 0 and not sends:
        warnings.warn(f"algo.intent_rollouts={cfg.algo.intent_rollouts} trains with "
                      f"teammates' intents, but eval_method={cfg.eval_method!r} sends none: "
                      f"best.pt is chosen without the input the network learnt from; use "
                      f"eval_method={cfg.algo.name}_ti, or keep_snapshots=true and compare "
                      f"the snapshots under TI afterwards", stacklevel=2)


def warn_emulated_bf16(precision: str, device: str) -> None:
    """Warn when ``algo.precision=bf16`` trains on a CPU that emulates bfloat16: there an
    update ran at about half float32's speed (docs/performance.md, "bf16 where it is
    emulated"), so the choice costs time instead of saving it."""
    if precision == "bf16" and torch.device(device).type == "cpu" and not native_bf16():
        warnings.warn(f"algo.precision=bf16 on a CPU without native bfloat16 ({cpu_model()}: "
                      f"no AVX512-BF16 or AMX): autocast emulates it, and an update runs "
                      f"about 1.7-1.9x slower than with algo.precision=float32", stacklevel=2)


def _tag(method: str, budgets: list[float], heldout: int) -> str:
    tag = f"{method}@{','.join(f'{b:g}' for b in budgets)}"
    return tag if heldout == 1 else f"{tag}/h{heldout}"  # set 1's rows predate the suffix


def eval_tag(cfg: Any) -> str:
    """What an ``eval/trace`` value measures: only values of one tag are compared."""
    return _tag(cfg.eval_method, eval_spec(cfg)[1], cfg.eval_heldout)


def row_tag(row: dict[str, Any], state: dict[str, Any]) -> str:
    """A curve row's eval tag; rows written before tags existed were greedy decoding at
    the ``eval_budget`` of the run that wrote them."""
    budget = state.get("config", {}).get("eval_budget", TrainConfig.eval_budget)
    return row.get("eval/tag", _tag("greedy", [float(budget)], 1))


def trace_score(per_budget: list[float]) -> float:
    """The held-out selection score: one budget's mean Tr(P_f), or the geometric mean of
    several budgets' means (so that no budget's scale outweighs another's)."""
    if len(per_budget) == 1:
        return per_budget[0]
    if min(per_budget) <= 0:
        return 0.0
    return math.exp(sum(math.log(v) for v in per_budget) / len(per_budget))


def evaluate(learner: Learner, env_cfg: MAIPPConfig, cfg: Any) -> dict[str, Any]:
    """``eval_method`` on held-out seeds (never the protocol's) at each evaluation budget.

    ``eval/trace`` is the selection score (:func:`trace_score`) of the budgets' mean
    Tr(P_f); ``eval/trace_B<b>`` each budget's mean at several."""
    spec, budgets = eval_spec(cfg)
    out: dict[str, Any] = {}
    per_budget, rows = [], []
    for budget in budgets:
        with full_precision(learner.core):  # what the saved float32 network plays
            chunk = heldout_rows(learner.core, env_cfg, cfg.eval_episodes, budget, spec,
                                 heldout=cfg.eval_heldout)
        per_budget.append(sum(r["trace"] for r in chunk) / len(chunk))
        rows += chunk
        if len(budgets) > 1:
            out[f"eval/trace_B{budget:g}"] = per_budget[-1]
    out["eval/trace"] = trace_score(per_budget)
    out.update({f"eval/{k}": sum(r[k] for r in rows) / len(rows) for k in ("rmse", "traps")})
    out["eval/tag"] = _tag(cfg.eval_method, budgets, cfg.eval_heldout)
    return out


def _command() -> str:
    return "python -m maipp_bench.train " + " ".join(sys.argv[1:])


def _hydra_command(run_dir: Path) -> list[str]:
    """The command of a run from Hydra's record of its overrides (checkpoints written
    before commands were stored in them)."""
    path = run_dir / ".hydra" / "overrides.yaml"
    if not path.exists():
        return []
    return ["python -m maipp_bench.train " + " ".join(OmegaConf.load(path))]


def recorded_init(state: dict[str, Any]) -> str | None:
    """The ``init`` a checkpoint's run started from: stored since 2026-11-25, else the
    ``init=`` of its first command."""
    return state.get("init") or _command_init((state.get("commands") or [""])[0])


def _command_init(command: str) -> str | None:
    """The ``init=`` of a training command, as typed (a quote may be unbalanced)."""
    try:
        tokens = shlex.split(command)
    except ValueError:
        tokens = command.split()
    return next((t[len("init="):] for t in tokens if t.startswith("init=")), None)


def init_lineage(init: str | None) -> dict[str, Any] | None:
    """What a run's ``init`` network was: its file's sha256, update, frames, wall time and
    commands, and, if it was itself fine-tuned, its own ``init`` (nested), so a card
    accounts for all the training behind a network. None without init."""
    if not init:
        return None
    try:
        path = resolve(init)
    except FileNotFoundError:
        return {"path": init, "found": False}
    payload = torch.load(path, map_location="cpu", weights_only=False)
    commands = payload.get("commands") or [""]
    lineage = {"path": init, "sha256": file_sha256(path), "update": payload["update"],
               "frames": payload["frames"], "wall_s": payload["wall_s"],
               "command": commands[0], "resumed_with": commands[1:]}
    parent = init_lineage(recorded_init(payload))
    card = path.with_suffix(".json")
    if parent is not None and parent.get("found") is False and card.exists():
        # A shipped file whose own init is gone (kept outside the repo): its card has the
        # lineage, written when that init still existed.
        parent = json.loads(card.read_text()).get("init", parent)
    return lineage | {"init": parent} if parent else lineage


def _with_init(card: dict[str, Any], lineage: dict[str, Any] | None, key: str) -> Any:
    """``card[key]`` plus the same of every init behind it (None if one is unknown)."""
    total = card[key]
    while lineage:
        if key not in lineage:
            return None
        total, lineage = total + lineage[key], lineage.get("init")
    return total


# Fields that say where and how this invocation runs, not what the run trains: a resumed run
# takes them from its own command line, never from the checkpoint.
INVOCATION_FIELDS = ("device", "threads", "progress", "resume", "init", "export", "export_from",
                     "export_note")
# Fields added after runs were saved, with what those runs did: a resumed old run keeps that.
SAVED_BEFORE = {"eval_heldout": 1}  # held-out set 2 came on 2026-11-27


_ABSENT = object()


def _leaves(tree: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in tree.items():
        path = f"{prefix}{key}"
        out |= _leaves(value, path + ".") if isinstance(value, dict) else {path: value}
    return out


def resumed_config(cfg: Any, overrides: list[str]) -> Any:
    """``cfg`` with the checkpoint's recipe (``cfg.resume``): every field that ``overrides``
    (this command line) does not set comes from the run's own config, so ``resume=<path>``
    alone continues the run as it was started (n_envs, intents, seed, ...); a field typed
    again takes the new value (how benchmarks/train_2h.sh changes stage 2's settings).

    ``algo=``/``env=`` typed again only name the run's groups: a different algo is an
    error (its network would not load), and the env's fields still come from the
    checkpoint; ``logger=`` switches where this command logs. What came from the checkpoint
    and differs from this command's own config is printed."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    saved = torch.load(cfg.resume, map_location="cpu", weights_only=False, mmap=True)
    saved = saved.get("config")
    if saved is None:  # checkpoints before configs were saved: this command's config
        return cfg
    typed = {o.key_or_group for o in OverridesParser.create().parse_overrides(overrides)}
    if "algo" in typed and cfg.algo.name != saved["algo"]["name"]:
        raise ValueError(f"resume={cfg.resume} continues a run of algo "
                         f"'{saved['algo']['name']}', not algo={cfg.algo.name}: start a new "
                         "run, or fine-tune its network with init=<path>")
    out, inherited = cfg.copy(), []
    leaves = _leaves(saved)
    for path, value in leaves.items():
        if (path.split(".")[0] in INVOCATION_FIELDS
                or any(path == t or path.startswith(t + ".") for t in typed
                       if t not in ("algo", "env"))  # logger=wandb: log there from now on
                or OmegaConf.select(out, path, default=_ABSENT) is _ABSENT):  # a retired field
            continue
        if OmegaConf.select(out, path) != value:
            inherited.append(f"{path}={value!r} (this command: {OmegaConf.select(out, path)!r})")
            try:
                OmegaConf.update(out, path, value, merge=False)
            except ValidationError as err:  # a field whose type changed since the checkpoint
                why = err.msg.splitlines()[0]
                raise ValueError(f"resume={cfg.resume}: its {path}={value!r} does not fit "
                                 f"this code's config ({why}); type {path}=...") from err
    for path, value in SAVED_BEFORE.items():
        if path not in typed and path not in leaves:
            inherited.append(f"{path}={value!r} (saved before the field existed)")
            OmegaConf.update(out, path, value, merge=False)
    if inherited:
        print("resume: the run's own settings, kept:\n  " + "\n  ".join(inherited))
    return out


def train(cfg: Any, run_dir: Path) -> Path:
    """Train the configured method into ``run_dir``; returns the checkpoint path."""
    torch.set_num_threads(cfg.threads)
    check_device(cfg.device)
    env_cfg = MAIPPConfig.from_dict(OmegaConf.to_container(cfg.env))
    if env_cfg.node_encoding_dim < 1:
        raise ValueError("env.node_encoding_dim must be >= 1: the network reads the "
                         "roadmap's Laplacian encoding (paper: 32)")
    spec, _ = eval_spec(cfg)  # a bad eval_method / eval_budgets fails now, not later
    check_snapshots(cfg)  # bad values fail now, not after training
    check_reset_every(cfg)
    if not cfg.export and (cfg.export_from != "best" or cfg.export_note):
        warnings.warn("export_from / export_note do nothing without export=<path>",
                      stacklevel=2)
    check_training_intents(cfg.algo)
    warn_unseen_intents(cfg, spec)
    warn_emulated_bf16(cfg.algo.precision, cfg.device)
    # Disjoint from every protocol seed, so training never sees the leaderboard's episodes.
    protocol_seeds = {s for suite in load_protocol(1).suites.values()
                      for s in (*suite.instance_seeds, *suite.trial_seeds)}
    for heldout in HELDOUT_SETS:
        seeds, trials = heldout_seeds(0, cfg.eval_episodes, heldout)
        assert not protocol_seeds & {*seeds, *trial_seeds(seeds, trials)}

    torch.manual_seed(cfg.seed)  # the network's initial weights
    learner = build_learner(cfg.algo, env_cfg.node_encoding_dim, env_cfg.interest_threshold,
                            cfg.device)
    if cfg.init and cfg.resume:
        warnings.warn(f"init={cfg.init} is ignored: resume={cfg.resume} continues its own "
                      "weights", stacklevel=2)
    if cfg.init and not cfg.resume:
        init_weights(learner, cfg.init, cfg.algo, env_cfg.interest_threshold)
    optim = torch.optim.Adam(learner.parameters(), lr=cfg.algo.lr)
    sched = torch.optim.lr_scheduler.StepLR(optim, cfg.algo.lr_decay_every, cfg.algo.lr_decay)
    ckpt_path = run_dir / "checkpoint.pt"
    start, frames, episodes, wall, curve = 0, 0, 0, 0.0, []
    best = math.inf  # lowest held-out eval Tr(P) so far (model selection never sees the protocol)
    commands = [_command()]  # every invocation that contributed, in order
    commit = git_commit()  # the code of the updates this invocation runs
    init = cfg.init  # the network the run started from (kept through resumes)
    if cfg.resume:
        state = torch.load(cfg.resume, map_location=cfg.device, weights_only=False)
        learner.loss.load_state_dict(state["loss"])
        optim.load_state_dict(state["optimizer"])
        sched.load_state_dict(state["scheduler"])
        start, frames, episodes = state["update"], state["frames"], state["episodes"]
        wall, curve = state["wall_s"], state["curve"]
        best_path = Path(cfg.resume).parent / "best.pt"
        if best_path.exists():  # the score of what best.pt holds, if it measured the same
            held = torch.load(best_path, map_location="cpu", weights_only=False,
                              mmap=True)["update"]  # mmap: only the header is read
            row = next((r for r in curve if r["update"] == held and "eval/trace" in r), None)
            if row is not None and row_tag(row, state) == eval_tag(cfg):
                best = row["eval/trace"]  # else a new evaluation: the selection restarts
        commands = state.get("commands", _hydra_command(Path(cfg.resume).parent)) + commands
        init = recorded_init(state)
        ckpt_path = Path(cfg.resume)
        run_dir = ckpt_path.parent
    if cfg.export:  # a snapshot that will not exist is an error now, not after training
        check_snapshot_export(cfg, start, ckpt_path)
        if start >= cfg.total_updates and ckpt_path.exists():  # nothing to train: export
            write_card(cfg, export_sources(cfg.export_from, ckpt_path), ckpt_path,
                       Path(cfg.export))
            return ckpt_path
    if start < cfg.total_updates and 0 < cfg.max_minutes <= wall / 60:  # else one update more
        raise ValueError(f"resume={cfg.resume} has used {wall / 60:.2f} minutes of update "
                         f"time, max_minutes={cfg.max_minutes}: type a higher max_minutes "
                         "to continue it (or total_updates=0 to export only)")
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "curve.jsonl").write_text("".join(json.dumps(r) + "\n" for r in curve))

    env, collector, buffer = make_collection(cfg, env_cfg, learner)
    logger = _logger(cfg, run_dir)
    bar = tqdm(total=cfg.total_updates, initial=start, desc=f"train {cfg.algo.name}",
               unit="upd", disable=not cfg.progress, dynamic_ncols=True)

    def save(update: int, path: Path = ckpt_path, policy_only: bool = False) -> None:
        """The whole training state, or (``policy_only``) a policy file's part of it."""
        state = {
            "format": FORMAT, "update": update, "frames": frames, "episodes": episodes,
            "wall_s": wall, "curve": curve, "core": learner.core.state_dict(),
            "loss": learner.loss.state_dict(), "optimizer": optim.state_dict(),
            "scheduler": sched.state_dict(), "algo": OmegaConf.to_container(cfg.algo),
            "env": env_cfg.to_dict(), "config": OmegaConf.to_container(cfg),
            "commands": commands, "commit": commit, "init": init,
        }
        atomic_save(slim(state) if policy_only else state, path)

    period = snapshot_period(cfg)  # 0: no snapshots
    since_reset, cut_warned = 0, False  # episodes ended since the envs' fresh start
    for update in range(start, cfg.total_updates):
        t0 = time.perf_counter()
        # --- collect: every reset_every updates counted from this process's start (a
        # checkpoint's update, or a max_minutes stop's), every env starts fresh episodes
        # from a seed of (seed, update); in between they run on. The policy's sampling is
        # seeded every update.
        useed = int(rng.derive(rng.seed_key(cfg.seed), update)) & (2**62 - 1)
        torch.manual_seed(useed)
        done_here = update + 1 - start  # updates this process will have made
        if (done_here - 1) % cfg.reset_every == 0:
            env.set_seed(useed)
            collector.reset()
            since_reset = 0
        learner.core.eval()
        batch = collector.next()
        rows = collected_decisions(learner, batch, cfg.algo)
        done = batch.get(("next", "done")).squeeze(-1)
        frames += batch.numel()
        ended = int(done.sum())
        episodes += ended
        since_reset += ended
        if done_here % cfg.reset_every == 0 and since_reset < cfg.n_envs and not cut_warned:
            cut_warned = True  # most envs never reached an episode's end before the reset
            warnings.warn(
                f"update {update + 1}: {since_reset} episodes ended in {cfg.n_envs} envs "
                f"since their fresh start: most episodes were cut before their end "
                f"(steps_per_batch={cfg.steps_per_batch} x reset_every={cfg.reset_every} "
                f"env steps per env between fresh starts); raise steps_per_batch or "
                f"reset_every", stacklevel=2)
        # --- learn: epochs x minibatches of decisions
        stats = learn(learner, optim, buffer, rows, cfg.algo)
        sched.step()
        wall += time.perf_counter() - t0
        # --- log
        final = batch.get(("next", "metrics"))[done]
        row = {"update": update + 1, "frames": frames, "episodes": episodes,
               "decisions": rows.numel(), "wall_s": round(wall, 2),
               "lr": sched.get_last_lr()[0],
               "reward_per_decision": float(rows.get("reward").mean()),
               "trace_final": float(final.get("trace").mean()) if final.numel() else math.nan,
               "traps": float(final.get("traps").float().mean()) if final.numel() else math.nan,
               **{k: sum(v) / len(v) for k, v in stats.items()}}
        if cfg.eval_every and (update + 1) % cfg.eval_every == 0:
            learner.core.eval()
            row.update(evaluate(learner, env_cfg, cfg))
        curve.append(row)
        if period and (update + 1) % period == 0:
            save(update + 1, run_dir / "snapshots" / f"update_{update + 1:04d}.pt",
                 policy_only=True)
        if row.get("eval/trace", math.inf) < best:
            best = row["eval/trace"]
            save(update + 1, run_dir / "best.pt")
        with open(run_dir / "curve.jsonl", "a") as f:
            f.write(json.dumps(row) + "\n")
        for k, v in row.items():
            if k != "update" and isinstance(v, float) and math.isfinite(v):
                logger.log_scalar(k, v, step=frames)
        bar.update(1)
        bar.set_postfix(frames=frames, episodes=episodes,
                        reward=f"{row['reward_per_decision']:.3f}",
                        trace=f"{row['trace_final']:.1f}")
        out_of_time = cfg.max_minutes > 0 and wall >= 60 * cfg.max_minutes
        if done_here % cfg.checkpoint_every == 0 or update + 1 == cfg.total_updates \
                or out_of_time:  # on a fresh start: counted from this process's start
            save(update + 1)
        if out_of_time:
            break
    bar.close()
    collector.shutdown()
    if cfg.export:
        write_card(cfg, export_sources(cfg.export_from, ckpt_path), ckpt_path,
                   Path(cfg.export))
    return ckpt_path


def check_snapshots(cfg: Any) -> None:
    """A clear error for snapshot settings that are invalid or would keep nothing."""
    snapshot_span(cfg.export_from)
    if cfg.snapshot_every < 0:
        raise ValueError(f"snapshot_every={cfg.snapshot_every}: must be >= 0 (0: at each "
                         f"held-out evaluation, eval_every)")
    if cfg.keep_snapshots and not snapshot_period(cfg):
        raise ValueError("keep_snapshots=true keeps nothing with eval_every=0 and "
                         "snapshot_every=0: set snapshot_every=N (every N updates) or "
                         "eval_every=N (at each held-out evaluation)")


def check_reset_every(cfg: Any) -> None:
    """A clear error for a reset_every that is not a positive divisor of checkpoint_every
    (a run resumed from a checkpoint between fresh starts would not continue its curve)."""
    if cfg.reset_every < 1:
        raise ValueError(f"reset_every={cfg.reset_every}: must be >= 1 (updates per fresh "
                         f"start of the envs; 1: every update)")
    if cfg.checkpoint_every % cfg.reset_every:
        raise ValueError(f"checkpoint_every={cfg.checkpoint_every} must be a multiple of "
                         f"reset_every={cfg.reset_every}, so that every checkpoint falls on a "
                         f"fresh start of the envs and a resumed run continues the same curve")


def snapshot_period(cfg: Any) -> int:
    """Every how many updates a snapshot is kept: snapshot_every, else (keep_snapshots)
    at each held-out evaluation (eval_every); 0: never."""
    return cfg.snapshot_every or (cfg.eval_every if cfg.keep_snapshots else 0)


def snapshot_span(export_from: Any) -> tuple[int, int] | None:
    """The updates ``(first, last)`` of the snapshots ``export_from`` names: ``N`` one
    snapshot, ``N-M`` the average of those kept from update N to M (None for best / last);
    a clear error for anything else."""
    text = str(export_from)
    if text in ("best", "last"):
        return None
    ends = text.split("-")
    if len(ends) > 2 or not all(e.isdigit() for e in ends) or int(ends[0]) > int(ends[-1]):
        raise ValueError(f"export_from={export_from!r}; valid: best, last, the update N of a "
                         f"kept snapshot (keep_snapshots=true), or N-M (N <= M): the average "
                         f"of the snapshots kept from update N to M")
    return int(ends[0]), int(ends[-1])


def check_snapshot_export(cfg: Any, start: int, last: Path) -> None:
    """``export_from=N`` (or ``N-M``) must name snapshots the run has kept (up to
    ``start``, the update it resumes from) or will keep (every snapshot_period-th update
    of this run)."""
    span, period = snapshot_span(cfg.export_from), snapshot_period(cfg)
    for n in sorted(set(span or ())):
        if n <= start:
            kept_snapshot(cfg.export_from, n, last)  # FileNotFoundError listing the kept
        elif not (period and n % period == 0 and n <= cfg.total_updates):
            raise ValueError(f"export_from={cfg.export_from}: this run keeps no snapshot of "
                             f"update {n} (snapshots are kept at every snapshot_every-th "
                             f"update, or with keep_snapshots=true every eval_every-th: here "
                             f"{period or 'never'}, up to "
                             f"total_updates={cfg.total_updates})")


def kept_snapshot(export_from: Any, n: int, last: Path) -> Path:
    """The kept snapshot of update ``n`` in the run of checkpoint ``last``; a
    FileNotFoundError listing the kept ones if there is none."""
    path = last.parent / "snapshots" / f"update_{n:04d}.pt"
    if not path.exists():
        kept = sorted(int(p.stem.split("_")[1]) for p in path.parent.glob("update_*.pt"))
        raise FileNotFoundError(f"export_from={export_from}: no {path}; snapshots kept "
                                f"(keep_snapshots=true) at updates {kept}")
    return path


def export_sources(export_from: Any, last: Path) -> list[Path]:
    """The files ``export_from`` names in the run of checkpoint ``last``: best.pt (if
    held-out evaluation made one) or the checkpoint itself; or the kept snapshots
    snapshots/update_N.pt of its span (both ends must have been kept)."""
    span = snapshot_span(export_from)
    if span is None:
        best = last.parent / "best.pt"
        return [best if str(export_from) == "best" and best.exists() else last]
    ends = [kept_snapshot(export_from, n, last) for n in span]
    kept = {int(p.stem.split("_")[1]): p for p in ends[0].parent.glob("update_*.pt")}
    return [kept[n] for n in sorted(kept) if span[0] <= n <= span[1]]


def _card_machine(run_config: dict, cfg: Any) -> str:
    """The machine line of a card: this CPU, with the torch threads and device the run's
    last session trained with (threads and device are per invocation, so an export typed
    with other ones does not describe the training)."""
    threads = run_config.get("threads", torch.get_num_threads())
    device = run_config.get("device", cfg.device)
    gpu = (f" ({torch.cuda.get_device_name(device)})"
           if "cuda" in device and torch.cuda.is_available() else "")
    return f"{machine_name()}, {threads} torch thread(s), device {device}{gpu}"


def write_card(cfg: Any, sources: list[Path], last: Path, out: Path) -> None:
    """The shipped policy file (weights of ``sources``: the best or the last checkpoint, a
    snapshot, or the average of several) and its JSON card: commands, seed, commit, wall
    time, machine and curve.

    A best or last checkpoint's card describes the whole run. A snapshot's describes the
    network it holds: the commands, frames, wall time and curve up to its update (the
    policy file keeps that curve too), plus how far the run went on and the command that
    exported it; an average's is that of its last snapshot, with the updates averaged."""
    chosen = average_policies(sources)
    state = torch.load(last, map_location="cpu", weights_only=False)
    snapshot = "curve" not in chosen  # snapshots are slim policy files
    run = chosen if snapshot else state  # what the card describes
    commands = run.get("commands") or _hydra_command(last.parent)
    if snapshot:
        curve = [r for r in state["curve"] if r["update"] <= chosen["update"]]
        atomic_save({**chosen, "curve": curve}, out)
        updates = chosen.get("averaged_updates", [chosen["update"]])
        how = (f"snapshot (keep_snapshots=true) of the run's update {chosen['update']}"
               if len(updates) == 1 else "uniform average of the weights of the run's "
               f"snapshots (keep_snapshots=true) at updates {updates}")
    else:
        export_policy(sources[0], out)
        curve = state["curve"]
        how = "lowest held-out Tr(P) (eval/trace) of " + row_tag(
            next(r for r in curve if r["update"] == chosen["update"]), state) \
            if chosen["update"] != state["update"] or sources[0] != last else "last update"
    card = {
        "algo": cfg.algo.name,
        "command": commands[0],
        "resumed_with": commands[1:],
        "seed": run["config"]["seed"],
        # The code of the network's last update where its file records it (checkpoints
        # since 2026-11-25), else the code writing the card.
        "commit": chosen.get("commit") or git_commit(),
        "updates": run["update"],
        "selected_update": chosen["update"],
        "selected_by": f"{how}, {cfg.export_note}" if cfg.export_note else how,
        "frames": run["frames"],
        "wall_s": run["wall_s"],
        "machine": _card_machine(run["config"], cfg),
    }
    if snapshot:
        card |= {"run_continued_to": state["update"], "exported_with": _command(),
                 "exported_at_commit": git_commit()}
        if "averaged_updates" in chosen:
            card["averaged_updates"] = chosen["averaged_updates"]
    lineage = init_lineage(recorded_init(run))
    if lineage:  # a fine-tune: what it started from, and the training behind it in all
        card |= {"init": lineage, "frames_with_init": _with_init(card, lineage, "frames"),
                 "wall_s_with_init": _with_init(card, lineage, "wall_s")}
    card["curve"] = curve
    out.with_suffix(".json").write_text(json.dumps(card, indent=1) + "\n")


@hydra.main(version_base=None, config_path="conf", config_name="train")
def main(cfg: Any) -> None:
    """Hydra entry point: the run folder is Hydra's output folder."""
    run_dir = Path(HydraConfig.get().runtime.output_dir)
    keep_freed_memory()
    if cfg.resume:
        cfg = resumed_config(cfg, list(HydraConfig.get().overrides.task))
    path = train(cfg, run_dir)
    print(f"checkpoint: {path}")


if __name__ == "__main__":
    main()
