"""MAIPPParallelEnv: the PettingZoo API and seed tests, the rule for non-deciding agents,
agreement with MAIPPEnv, and the round trip through TorchRL's PettingZooWrapper."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import data_equivalence
from pettingzoo.test import parallel_api_test, parallel_seed_test
from tensordict import TensorDict
from torchrl.envs import PettingZooWrapper
from torchrl.envs.utils import check_env_specs

from maipp_bench.envs import METRICS, MAIPPConfig, MAIPPEnv
from maipp_bench.envs.pettingzoo import MAIPPParallelEnv

SMALL = dict(n_agents=2, budget=1.0, n_nodes=30, k_neighbors=6, grid_size=10)


def small(**overrides):
    return MAIPPConfig(**{**SMALL, **overrides})


def first_allowed(obs):
    return {a: int(np.argmax(o["action_mask"])) for a, o in obs.items()}


def step_until(env, obs, infos, predicate, max_steps=50):
    """Step with the first allowed slot until ``predicate(obs, infos)`` holds."""
    for _ in range(max_steps):
        if predicate(obs, infos):
            return obs, infos
        obs, _, _, _, infos = env.step(first_allowed(obs))
        assert env.agents, "episode ended before the predicate held"
    raise AssertionError("predicate never held")


def mixed(obs, infos):
    flags = [i["deciding"] for i in infos.values()]
    return any(flags) and not all(flags)


# ====================================================================== PettingZoo tests
@pytest.mark.parametrize("overrides", [{}, dict(comm_range=0.3, n_agents=3)],
                         ids=["global-comm", "range-0.3"])
def test_parallel_api_test(overrides):
    env = MAIPPParallelEnv(small(**overrides))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the API test reports problems as warnings
        parallel_api_test(env, num_cycles=200)


def test_parallel_seed_test():
    # parallel_seed_test samples actions *without* the mask and (since `any(dict)` is true)
    # takes one step after reset: at reset every agent rests at the start node and, with
    # risk off, every slot is feasible, so unmasked samples are valid actions.
    cfg = small(risk_enabled=False)
    env = MAIPPParallelEnv(cfg)
    obs, infos = env.reset(seed=42)
    assert all(i["deciding"] for i in infos.values())
    assert all(o["action_mask"].all() for o in obs.values())
    parallel_seed_test(lambda: MAIPPParallelEnv(cfg))


def test_same_seed_same_episode_to_the_end():
    envs = [MAIPPParallelEnv(small()) for _ in range(2)]
    outs = [env.reset(seed=7) for env in envs]
    assert data_equivalence(outs[0], outs[1])
    for env in envs:
        for j, agent in enumerate(env.possible_agents):
            env.action_space(agent).seed(100 + j)
    while envs[0].agents:
        acts = [{a: env.action_space(a).sample(mask=out[0][a]["action_mask"])
                 for a in env.agents} for env, out in zip(envs, outs)]
        assert data_equivalence(acts[0], acts[1])
        outs = [env.step(act) for env, act in zip(envs, acts)]
        assert data_equivalence(outs[0], outs[1])
        assert data_equivalence(envs[0].state(), envs[1].state())
    assert envs[1].agents == []


# ====================================================================== spaces and API
@pytest.mark.parametrize("overrides", [{}, dict(dtype="float32", prune_risky_nodes=True,
                                                aoi_enabled=True)], ids=["default", "f32"])
def test_spaces_contain_observations_and_state(overrides):
    cfg = small(**overrides)
    env = MAIPPParallelEnv(cfg)
    n, k = cfg.n_roadmap_nodes, cfg.k_neighbors
    assert env.possible_agents == ["agent_0", "agent_1"]
    assert env.metadata["name"] == "maipp_v1" and env.metadata["is_parallelizable"]
    for agent in env.possible_agents:
        assert env.observation_space(agent) is env.observation_space(agent)
        assert env.action_space(agent) is env.action_space(agent)
        assert env.action_space(agent).n == k
        space = env.observation_space(agent)
        assert space["action_mask"].dtype == np.int8 and space["action_mask"].shape == (k,)
        assert space["observation"]["node_features"].shape == (n, 7)
    assert env.observation_space("agent_0") is not env.observation_space("agent_1")
    with pytest.raises(ValueError, match="unknown agent"):
        env.action_space("agent_9")
    with pytest.raises(RuntimeError, match="reset"):
        env.state()

    obs, infos = env.reset(seed=3)
    assert env.agents == env.possible_agents
    steps = 0
    while True:
        state = env.state()
        assert state.shape == env.state_space.shape == (n, 8)
        assert env.state_space.contains(state)
        for agent, o in obs.items():
            assert env.observation_space(agent).contains(o), agent
            assert o["action_mask"].dtype == np.int8
            assert set(infos[agent]) == {"deciding", *METRICS}
        if not env.agents:
            break
        obs, rewards, term, trunc, infos = env.step(first_allowed(obs))
        steps += 1
        assert set(obs) == set(rewards) == set(term) == set(trunc) == set(infos)
        assert all(isinstance(r, float) for r in rewards.values())
    assert all(term.values()) or all(trunc.values())
    with pytest.raises(RuntimeError, match="episode is over"):
        env.step({})
    env.render_mode = "ansi"
    assert "agent_1: node" in env.render()
    assert steps > 1
    with pytest.raises(ValueError, match="render_mode"):
        MAIPPParallelEnv(small(), render_mode="human")


def test_overrides_and_reset_options():
    env = MAIPPParallelEnv(small(), n_agents=3, budget=0.5)
    assert env.config.n_agents == 3 and env.config.budget == 0.5
    assert len(env.possible_agents) == 3

    env = MAIPPParallelEnv(small())
    pin = {"instance_seed": 11, "trial_seed": 12}
    a, _ = env.reset(seed=0, options=pin)
    b, _ = env.reset(seed=5, options=pin)
    c, _ = env.reset(seed=5)
    d, _ = env.reset()
    assert data_equivalence(a, b)  # explicit seeds pin the world and roadmap
    assert not data_equivalence(b, c)
    assert not data_equivalence(c, d)  # reset() without a seed draws the next episode
    env.reset(seed=0, options={"unrelated": 1})  # unknown option keys are ignored
    with pytest.raises(ValueError, match="instance_seed"):
        env.reset(options={"instance_seed": 1.5})


# ====================================================================== the rule
def test_non_deciding_agents_may_omit_their_action():
    envs = [MAIPPParallelEnv(small()) for _ in range(3)]
    outs = [env.reset(seed=1) for env in envs]
    obs, infos = step_until(envs[0], *outs[0], mixed)
    for env in envs[1:]:
        step_until(env, *env.reset(seed=1), mixed)
    deciding = [a for a in obs if infos[a]["deciding"]]
    idle = [a for a in obs if not infos[a]["deciding"]]
    for a in idle:
        assert obs[a]["action_mask"].all()  # non-deciding agents' masks are all ones
    acts = {a: int(np.argmax(obs[a]["action_mask"])) for a in deciding}
    out_omit = envs[0].step(acts)  # idle agents left out
    out_zero = envs[1].step({**acts, **dict.fromkeys(idle, 0)})
    out_junk = envs[2].step({**acts, **dict.fromkeys(idle, 999)})  # ignored, not checked
    assert data_equivalence(out_omit, out_zero)
    assert data_equivalence(out_omit, out_junk)
    assert set(out_omit[0]) == set(obs)  # every live agent still gets its outputs


def test_deciding_agent_must_act():
    env = MAIPPParallelEnv(small())
    obs, infos = step_until(env, *env.reset(seed=1), mixed)
    deciding = [a for a in obs if infos[a]["deciding"]]
    state_before = env.state()
    with pytest.raises(ValueError, match="no action for deciding"):
        env.step({})
    with pytest.raises(ValueError, match="no action for deciding"):
        env.step({a: 0 for a in obs if a not in deciding})
    np.testing.assert_array_equal(env.state(), state_before)  # refused, nothing changed
    env.step(first_allowed(obs))  # the env is still usable


def test_masked_or_bad_actions_raise():
    env = MAIPPParallelEnv(small())
    obs, infos = env.reset(seed=2)
    assert infos["agent_0"]["deciding"] and infos["agent_1"]["deciding"]
    # Both pick slot 0 of the shared start node: agent_1 loses the collision, stays and
    # decides again, and slot 0 (now agent_0's target) is masked for it.
    obs, rewards, _, _, infos = env.step({"agent_0": 0, "agent_1": 0})
    assert rewards["agent_1"] <= -env.config.collision_penalty + 1e-12
    assert infos["agent_1"]["deciding"] and obs["agent_1"]["action_mask"][0] == 0
    good = first_allowed(obs)
    for bad in (0, -1, env.config.k_neighbors):  # masked, out of range (both ends)
        with pytest.raises(ValueError, match="masked or out-of-range"):
            env.step({**good, "agent_1": bad})
    for bad in (1.0, "1", True, np.array([0.0]), None):
        with pytest.raises(ValueError, match="integer slot"):
            env.step({**good, "agent_1": bad})
    with pytest.raises(ValueError, match="not live agents"):
        env.step({**good, "agent_7": 0})
    # integer scalars of any kind are accepted
    env.step({a: np.int64(v) if a == "agent_0" else torch.tensor(v) for a, v in good.items()})


# ====================================================================== vs MAIPPEnv
@pytest.mark.parametrize("pinned", [False, True], ids=["seed", "instance+trial seeds"])
def test_matches_torchrl_env(pinned):
    cfg = small(comm_range=0.4)
    pz = MAIPPParallelEnv(cfg)
    rl = MAIPPEnv(cfg, batch_size=[1])
    rl.set_seed(4)
    td_in = TensorDict(batch_size=[1])
    options = None
    if pinned:
        options = {"instance_seed": 21, "trial_seed": 22}
        td_in = TensorDict({k: torch.tensor([v]) for k, v in options.items()}, batch_size=[1])
    obs, infos = pz.reset(seed=4, options=options)
    td = rl.reset(td_in)
    agents = pz.possible_agents
    steps = 0
    while True:
        np.testing.assert_array_equal(pz.state(), td["state"][0].numpy())
        for name in METRICS:
            want = td["metrics", name][0].item()
            for a in obs:
                assert infos[a][name] == want, name
                assert type(infos[a][name]) is type(want)
        for i, a in enumerate(agents):
            assert infos[a]["deciding"] == bool(td["agents", "deciding"][0, i])
            np.testing.assert_array_equal(obs[a]["action_mask"],
                                          td["agents", "action_mask"][0, i].numpy())
            for key, value in obs[a]["observation"].items():
                np.testing.assert_array_equal(value, td["agents", "observation", key][0, i])
        if not pz.agents:
            assert bool(td["done"].all())
            break
        actions = first_allowed(obs)
        obs, rewards, term, trunc, infos = pz.step(actions)
        td.set(("agents", "action"), torch.tensor([[actions[a] for a in agents]]))
        td = rl.step(td)["next"]
        steps += 1
        for i, a in enumerate(agents):
            assert rewards[a] == td["agents", "reward"][0, i, 0].item()
            assert term[a] == bool(td["terminated"]) and trunc[a] == bool(td["truncated"])
    assert steps > 1


def test_episode_equals_env_zero_of_a_batch():
    pz = MAIPPParallelEnv(small())
    rl = MAIPPEnv(small(), batch_size=[2])
    rl.set_seed(9)
    pz.reset(seed=9)
    td = rl.reset()
    np.testing.assert_array_equal(pz.state(), td["state"][0].numpy())


# ====================================================================== TorchRL round trip
@pytest.mark.parametrize("use_mask", [False, True])
def test_torchrl_pettingzoo_wrapper(use_mask):
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="PettingZoo in TorchRL is tested")
        env = PettingZooWrapper(env=MAIPPParallelEnv(small()), use_mask=use_mask,
                                return_state=True, seed=0)
    assert list(env.group_map) == ["agent"]
    assert env.group_map["agent"] == ["agent_0", "agent_1"]
    check_env_specs(env, seed=0)
    torch.manual_seed(0)
    td = env.rollout(100, break_when_any_done=True)  # random actions respect the mask
    assert bool(td["next", "done"][-1])
    mask = td["agent", "action_mask"]
    chosen = mask.gather(-1, td["agent", "action"].unsqueeze(-1))
    assert bool(chosen.all())
    assert td["state"].shape[-2:] == (31, 8)
    assert td["next", "agent", "info", "trace"].shape == (td.shape[0], 2)
    if use_mask:
        assert not bool(td["next", "agent", "mask"][-1].any())  # all agents finished
