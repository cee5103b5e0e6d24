"""Run a method on a batch of protocol episodes and return one result row per episode.

One call runs one *chunk*: a fixed (method, setting, trial) over the suite's instances,
all batched in one env. Chunks are the unit of storage and resumption, and their
composition never changes, so a resumed run computes exactly what an uninterrupted one does.
"""

from __future__ import annotations

import operator
import time
from collections.abc import Callable, Sequence
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase

from maipp_bench.algos.registry import MethodSpec
from maipp_bench.envs import rng
from maipp_bench.envs.config import MAIPPConfig
from maipp_bench.envs.maipp_env import COUNT_METRICS, METRICS, MAIPPEnv

# Every row carries all env metrics ("metrics", name) at the episode's first done.
ROW_METRICS = METRICS


def trial_seeds(instance_seeds: list[int], trial_seed: int | Sequence[int]) -> list[int]:
    """One trial seed per episode: ``trial_seed`` (an integer) for all, or one integer per
    instance (a sequence, tensor or array); anything else is a TypeError saying so."""
    seeds = trial_seed.tolist() if getattr(trial_seed, "ndim", 0) >= 1 else trial_seed
    try:
        if not isinstance(seeds, Sequence) or isinstance(seeds, (str, bytes)):
            return [operator.index(seeds)] * len(instance_seeds)  # numpy integers too
        trials = [operator.index(t) for t in seeds]
    except TypeError:
        raise TypeError(f"trial_seed: an int or one int per instance, got {trial_seed!r}"
                        ) from None
    if len(trials) != len(instance_seeds):
        raise ValueError(f"{len(trials)} trial seeds for {len(instance_seeds)} instances")
    return trials


def method_seeds(instance_seeds: list[int], trial_seed: int | Sequence[int]) -> torch.Tensor:
    """Per-episode method seeds, a fixed function of (instance, trial)."""
    inst = torch.tensor(instance_seeds, dtype=torch.int64)
    trials = torch.tensor(trial_seeds(instance_seeds, trial_seed), dtype=torch.int64)
    return rng.derive(rng.mix(trials), inst)  # rng.seed_key of each trial seed


def task_config(method: MethodSpec, cfg: MAIPPConfig) -> MAIPPConfig:
    """Risk-unaware methods plan on the roadmap without nodes of true risk > 0.7 (paper)."""
    if cfg.risk_enabled and method.prunes_roadmap:
        return cfg.replace(prune_risky_nodes=True)
    return cfg


def run_chunk(
    method: MethodSpec,
    cfg: MAIPPConfig,
    instance_seeds: list[int],
    trial_seed: int | Sequence[int],
    device: str | torch.device = "cpu",
    on_action: Callable[[MAIPPEnv, TensorDictBase], None] | None = None,
    **policy_kwargs: Any,
) -> list[dict[str, Any]]:
    """Play one episode per instance to the end; return the rows. ``trial_seed``: one for
    every episode (a protocol chunk) or one per instance. ``on_action(env, td)``, if
    given, sees every step's actions before the env applies them (diagnostics; not timed
    as planning)."""
    e = len(instance_seeds)
    trials = trial_seeds(instance_seeds, trial_seed)
    env = MAIPPEnv(task_config(method, cfg), batch_size=[e], device=device)
    td = env.reset(TensorDict(
        instance_seed=torch.tensor(instance_seeds, dtype=torch.int64, device=env.device),
        trial_seed=torch.tensor(trials, dtype=torch.int64, device=env.device),
        batch_size=[e], device=env.device,
    ))
    policy = method.build(env, method_seeds(instance_seeds, trials), **policy_kwargs)
    finished = torch.zeros(e, dtype=torch.bool, device=env.device)
    final = {name: torch.zeros(e, dtype=torch.float64) for name in ROW_METRICS}
    steps = torch.zeros(e, dtype=torch.int64)
    planning = 0.0
    while not bool(finished.all()):
        t0 = time.perf_counter()
        td = policy(td)
        planning += time.perf_counter() - t0
        if on_action is not None:
            on_action(env, td)
        td = env.step(td)
        nxt = td.get("next")
        done = nxt.get("done").reshape(e)
        new = (done & ~finished).cpu()
        if bool(new.any()):
            for name in ROW_METRICS:
                final[name][new] = nxt.get(("metrics", name)).cpu().to(torch.float64)[new]
            steps[new] = env.episode.steps.cpu()[new]
        finished |= done
        td = nxt
    rows = []
    for i, (inst, trial) in enumerate(zip(instance_seeds, trials)):
        row = {"instance": int(inst), "trial": trial, "steps": int(steps[i])}
        for name in ROW_METRICS:
            v = float(final[name][i])
            row[name] = int(v) if name in COUNT_METRICS else v
        row["planning_s"] = planning / e  # batched planning time shared equally
        rows.append(row)
    return rows
