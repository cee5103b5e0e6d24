"""Every registered method plays whole episodes on a small task: masks respected (the env
refuses masked actions), budgets kept, seeds reproduce, bad parameters are refused."""

from __future__ import annotations

import pytest
import torch

from maipp_bench import algos
from maipp_bench.envs import MAIPPConfig
from maipp_bench.protocol.runner import run_chunk, task_config

SMALL = dict(n_agents=2, budget=1.0, n_nodes=40, k_neighbors=8)


@pytest.mark.parametrize("name", algos.method_names())
@pytest.mark.parametrize("comm_range", [float("inf"), 0.3])
def test_method_plays_valid_episodes(name, comm_range, tiny_checkpoint):
    cfg = MAIPPConfig(**SMALL, comm_range=comm_range)
    spec = algos.get_method(name)
    # Learned methods play a tiny trained network (the shipped ones are for the protocol).
    kwargs = {"checkpoint": str(tiny_checkpoint)} if spec.learned else {}
    rows = run_chunk(spec, cfg, [11, 12], trial_seed=5, **kwargs)
    assert len(rows) == 2
    for r in rows:
        assert r["distance"] <= cfg.team_budget + 1e-9
        assert 0 < r["trace"] <= 900
        assert r["steps"] >= 1
    again = run_chunk(spec, cfg, [11, 12], trial_seed=5, **kwargs)
    strip = [{k: v for k, v in r.items() if k != "planning_s"} for r in rows]
    assert strip == [{k: v for k, v in r.items() if k != "planning_s"} for r in again]


def test_risk_unaware_methods_get_the_pruned_roadmap():
    cfg = MAIPPConfig(**SMALL)
    assert task_config(algos.get_method("greedy"), cfg).prune_risky_nodes
    assert not task_config(algos.get_method("greedy"), cfg.replace(risk_enabled=False)) \
        .prune_risky_nodes


def test_planner_parameters_are_checked():
    from maipp_bench.envs import MAIPPEnv

    env = MAIPPEnv(MAIPPConfig(**SMALL), batch_size=[1])
    env.reset()
    with pytest.raises(ValueError, match="min_length <= max_length"):
        algos.POLICIES["sga_rrt"](env, torch.zeros(1, dtype=torch.int64), 0.5, 0.3)
    with pytest.raises(ValueError, match="depth"):
        algos.POLICIES["oracle"](env, torch.zeros(1, dtype=torch.int64), depth=0)
