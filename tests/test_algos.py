"""Every registered method plays whole episodes on a small task: masks respected (the env
refuses masked actions), budgets kept, seeds reproduce, bad parameters are refused."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from maipp_bench import algos
from maipp_bench.envs import MAIPPConfig
from maipp_bench.protocol.runner import run_chunk, task_config, trial_seeds

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
    assert _strip(rows) == _strip(again)


def _strip(rows: list[dict]) -> list[dict]:
    return [{k: v for k, v in r.items() if k != "planning_s"} for r in rows]


@pytest.mark.parametrize("name", ["random", "ours_ti"])
def test_a_trial_seed_per_episode_plays_each_episode_as_its_own_chunk(name, tiny_checkpoint):
    """Training's held-out episodes give each episode its own trial seed (its own roadmap,
    start and method randomness): a batch of them plays exactly what one chunk per
    (instance, trial) plays, and each row records its trial."""
    cfg = MAIPPConfig(**SMALL)
    spec = algos.get_method(name)
    kwargs = {"checkpoint": str(tiny_checkpoint)} if spec.learned else {}
    rows = run_chunk(spec, cfg, [11, 12], trial_seed=[5, 7], **kwargs)
    alone = [run_chunk(spec, cfg, [inst], trial_seed=trial, **kwargs)[0]
             for inst, trial in ((11, 5), (12, 7))]
    assert [r["trial"] for r in rows] == [5, 7]
    assert _strip(rows) == _strip(alone)
    assert trial_seeds([11, 12], torch.tensor([5, 7])) == trial_seeds([11, 12], (5, 7))
    assert trial_seeds([11, 12], np.int64(5)) == [5, 5]
    with pytest.raises(ValueError, match="1 trial seeds for 2 instances"):
        run_chunk(spec, cfg, [11, 12], trial_seed=[5], **kwargs)
    for bad in ("57", 5.0, [5, 7.0]):
        with pytest.raises(TypeError, match="an int or one int per instance"):
            trial_seeds([11, 12], bad)


@pytest.mark.cuda
@pytest.mark.parametrize("name", algos.method_names())
def test_method_plays_the_same_episodes_on_cuda(name, tiny_checkpoint):
    """``eval --device cuda``: every method runs there and plays the CPU's episodes (same
    decisions; floating-point results to rounding). SGA-RRT only plays valid ones: its
    tree search ranks paths by float gains, and CUDA's rounding flips near ties (its
    protocol rows differ on CUDA: docs/performance.md)."""
    if not torch.cuda.is_available():
        pytest.skip("CUDA is not available")
    cfg = MAIPPConfig(**SMALL, comm_range=0.3)
    spec = algos.get_method(name)
    kwargs = {"checkpoint": str(tiny_checkpoint)} if spec.learned else {}
    cpu, gpu = (run_chunk(spec, cfg, [11, 12], trial_seed=5, device=d, **kwargs)
                for d in ("cpu", "cuda"))
    for a, b in zip(cpu, gpu):
        assert b["distance"] <= cfg.team_budget + 1e-9 and 0 < b["trace"] <= 900
        if spec.policy != "sga_rrt":
            assert a["steps"] == b["steps"] and a["measurements"] == b["measurements"], (a, b)
            assert b["trace"] == pytest.approx(a["trace"], rel=1e-6)


def test_risk_unaware_methods_get_the_pruned_roadmap_unless_their_yaml_says_otherwise():
    cfg = MAIPPConfig(**SMALL)
    pruned = {name: task_config(algos.get_method(name), cfg).prune_risky_nodes
              for name in ("greedy", "catnipp_greedy", "ours_greedy",
                           "catnipp_greedy_full_roadmap", "catnipp_ti_full_roadmap")}
    assert pruned == {"greedy": True, "catnipp_greedy": True, "ours_greedy": False,
                      "catnipp_greedy_full_roadmap": False, "catnipp_ti_full_roadmap": False}
    assert not task_config(algos.get_method("greedy"), cfg.replace(risk_enabled=False)) \
        .prune_risky_nodes
    assert (algos.get_method("catnipp_greedy").fingerprint()
            != algos.get_method("catnipp_greedy_full_roadmap").fingerprint())


def test_sga_rrt_grows_its_next_tree_from_the_rest_of_its_last_best_path():
    from maipp_bench.algos.paths import polyline_lengths
    from maipp_bench.envs import MAIPPEnv, rng

    env = MAIPPEnv(MAIPPConfig(**SMALL), batch_size=[2])
    td = env.reset()
    policy = algos.get_method("sga_rrt_0.9_1.0").build(env, torch.arange(2))
    ar, agent = torch.arange(2), torch.zeros(2, dtype=torch.int64)
    assert not policy._remainder(env.episode, ar, agent)[1].any()  # nothing before a plan
    td = env.step(policy(td))["next"]
    rest, mask = policy._remainder(env.episode, ar, agent)
    path, real = policy.path[ar, agent], policy.path_mask[ar, agent]
    beyond = real & (polyline_lengths(path, real) > policy.execute + 1e-9)
    assert mask.any(-1).all() and torch.equal(mask.sum(-1), beyond.sum(-1))
    assert torch.equal(rest[mask], path[beyond])  # the unexecuted vertices, in order
    root = env.episode.roadmap.nodes[ar, env.episode.cur[ar, agent]]
    nodes, parent, cost, depth = policy._grow(root, rng.derive(rng.seed_key(1), ar), rest, mask)
    r = rest.shape[1]
    chain = torch.arange(1, r + 1)
    assert torch.equal(nodes[:, 1 : r + 1][mask], rest[mask])
    assert torch.equal(parent[:, 1 : r + 1][mask], (chain - 1).expand(2, r)[mask])
    assert bool((cost[:, 1 : r + 1].diff(dim=-1)[mask[:, 1:]] > 0).all())
    assert torch.equal(depth[:, 1 : r + 1][mask], chain.expand(2, r)[mask])


def test_planner_parameters_are_checked():
    from maipp_bench.envs import MAIPPEnv

    env = MAIPPEnv(MAIPPConfig(**SMALL), batch_size=[1])
    env.reset()
    with pytest.raises(ValueError, match="min_length <= max_length"):
        algos.POLICIES["sga_rrt"](env, torch.zeros(1, dtype=torch.int64), 0.5, 0.3)
    with pytest.raises(ValueError, match="depth"):
        algos.POLICIES["oracle"](env, torch.zeros(1, dtype=torch.int64), depth=0)
