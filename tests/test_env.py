"""MAIPPEnv: TorchRL contract, budget and termination rules, seeding, resets, communication,
intents, risk, evidence and AOI (PROTOCOL v1)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from gp_reference import dense_gp, trace_in_region
from tensordict import TensorDict
from torchrl.envs import ActionMask, EnvBase, TransformedEnv
from torchrl.envs.utils import check_env_specs

from maipp_bench.envs import NODE_FEATURES, MAIPPConfig, MAIPPEnv

F64 = torch.float64
# Small roadmaps and a 10 x 10 evaluation grid keep the suite fast; the 30 x 30 grid of
# PROTOCOL is exercised by test_belief.py.
SMALL = dict(budget=1.0, n_nodes=40, k_neighbors=8, grid_size=10)
EPS = 1e-9


def make_env(n_envs=2, seed=0, **overrides):
    cfg = MAIPPConfig(**{**SMALL, **overrides})
    env = MAIPPEnv(cfg, batch_size=[n_envs])
    env.set_seed(seed)
    return env


def first_allowed(td):
    """Deterministic policy: the first allowed slot of every agent."""
    td.set(("agents", "action"), td.get(("agents", "action_mask")).to(torch.int64).argmax(-1))
    return td


def run_to_end(env, policy=None, max_steps=400, seed=0):
    """Step all envs (no auto-reset) until every env is done; returns the list of
    ``next`` tensordicts, the first one being the reset output."""
    torch.manual_seed(seed)
    td = env.reset()
    out = [td]
    for _ in range(max_steps):
        td = policy(td) if policy is not None else env.rand_action(td)
        td = env.step(td)["next"]
        out.append(td)
        if td["done"].all():
            return out
    raise AssertionError("episodes did not end")


def state_leaves(env):
    return env.episode.to_tensordict().clone()


def assert_td_equal(a, b, what=""):
    """Same keys and bit-identical leaves; the message lists every differing key."""
    keys_a = set(a.keys(True, True))
    assert keys_a == set(b.keys(True, True)), what
    differ = sorted(str(k) for k in keys_a if not torch.equal(a[k], b[k]))
    assert not differ, f"{what}: leaves differ: {differ}"


def knn(nodes, k):
    """Independent k-nearest-neighbour graph: ``(index [N, k], dist [N, k])`` (numpy)."""
    x = nodes.numpy()
    d = np.sqrt(((x[:, None, :] - x[None, :, :]) ** 2).sum(-1))
    np.fill_diagonal(d, np.inf)
    idx = np.argsort(d, axis=1, kind="stable")[:, :k]
    return idx, np.take_along_axis(d, idx, 1)


def true_field(points, centres, stds, valid, grid_size=30):
    """Independent mixture of axis-aligned Gaussians normalised to max 1 on the grid."""

    def raw(p):
        z = (p[:, None, :] - centres[None]) / stds[None]
        dens = np.exp(-0.5 * (z**2).sum(-1)) / (2 * np.pi * stds.prod(-1))[None]
        return (dens * valid[None]).sum(-1)

    lin = np.linspace(0, 1, grid_size)
    gx, gy = np.meshgrid(lin, lin)
    grid = np.stack([gx.ravel(), gy.ravel()], -1)
    norm = raw(grid).max()
    return raw(points) / (norm if norm > 0 else 1.0)


def true_risk(env, i, points):
    w = env.episode.world
    return true_field(points.numpy(), w.risk_centres[i].numpy(), w.risk_stds[i].numpy(),
                      w.risk_valid[i].numpy(), env.config.grid_size)


# ====================================================================== TorchRL contract
SPEC_SETTINGS = [
    dict(comm_range=math.inf, risk_enabled=True),
    dict(comm_range=0.3, risk_enabled=True),
    dict(comm_range=math.inf, risk_enabled=False),
    dict(comm_range=0.3, risk_enabled=False, aoi_enabled=True),
    dict(comm_range=math.inf, risk_enabled=True, aoi_enabled=True, aoi_bias=0.5),
]


@pytest.mark.parametrize("wrapped", [False, True], ids=["bare", "action_mask"])
@pytest.mark.parametrize("setting", SPEC_SETTINGS, ids=[str(s) for s in SPEC_SETTINGS])
def test_check_env_specs(setting, wrapped):
    env = make_env(3, seed=1, n_nodes=30, k_neighbors=6, **setting)
    if wrapped:  # the mask transform outermost, as a policy-facing stack would have it
        env = TransformedEnv(env, ActionMask(action_key=("agents", "action"),
                                             mask_key=("agents", "action_mask")))
    torch.manual_seed(0)
    check_env_specs(env, seed=1)
    td = env.rollout(8, break_when_any_done=False)
    _assert_actions_allowed(td)


def _assert_actions_allowed(td):
    action = td["agents", "action"]
    mask = td["agents", "action_mask"]
    deciding = td["agents", "deciding"]
    allowed = mask.gather(-1, action.unsqueeze(-1)).squeeze(-1)
    assert torch.all(allowed[deciding])
    # Agents that do not decide have an all-True mask (their action is ignored).
    assert torch.all(mask[~deciding])


def test_done_keys_in_specs_and_rollout():
    env = make_env(3)
    assert set(env.full_done_spec.keys()) == {"done", "terminated", "truncated"}
    for key in ("done", "terminated", "truncated"):
        spec = env.full_done_spec[key]
        assert spec.shape == (3, 1) and spec.dtype == torch.bool
    td = env.rollout(6, break_when_any_done=False)
    for prefix in ((), ("next",)):
        done = td[(*prefix, "done")]
        term, trunc = td[(*prefix, "terminated")], td[(*prefix, "truncated")]
        assert done.shape == (3, 6, 1) and done.dtype == torch.bool
        assert torch.equal(done, term | trunc)


def test_truncation_at_max_steps():
    env = make_env(3, budget=2.0, max_steps=3)
    td = env.rollout(10)  # stops at the first done
    assert td.shape == (3, 3)
    nxt = td["next"]
    assert torch.all(nxt["truncated"][:, -1]) and not torch.any(nxt["terminated"])
    assert torch.all(nxt["done"][:, -1]) and not torch.any(nxt["done"][:, :-1])
    assert torch.equal(env.episode.steps, torch.full((3,), 3))
    # With auto-reset the envs are truncated every 3 steps.
    td = make_env(3, budget=2.0, max_steps=3).rollout(7, break_when_any_done=False)
    trunc = td["next", "truncated"].squeeze(-1)
    expected = torch.tensor([False, False, True, False, False, True, False]).expand(3, 7)
    assert torch.equal(trunc, expected)


def test_rollout_without_policy_respects_masks():
    env = make_env(4, seed=2)
    td = env.rollout(5)
    assert td["agents", "action"].shape[-1] == 3
    _assert_actions_allowed(td)
    td = env.rollout(60, break_when_any_done=False)
    _assert_actions_allowed(td)
    deciding = td["agents", "deciding"]
    # Non-vacuous: some deciding agent had a forbidden slot.
    assert (~td["agents", "action_mask"][deciding]).any()


def test_team_budget_never_exceeded():
    env = make_env(24, seed=3)
    cfg = env.config
    torch.manual_seed(3)
    td = env.rollout(130, break_when_any_done=False)  # 3120 env steps, auto-reset
    assert int(td["next", "done"].sum()) > 48  # many complete episodes
    for prefix in ((), ("next",)):
        dist = td[(*prefix, "metrics", "distance")]
        assert float(dist.max()) <= cfg.team_budget + 1e-9
        assert float(dist.min()) >= 0.0
        budget = td[(*prefix, "agents", "observation", "budget")]
        assert float(budget.min()) >= 0.0 and float(budget.max()) <= 1.0
    # Episodes end close to the budget: random walks use most of it.
    left = td["next", "agents", "observation", "budget"][..., 0, 0]
    final = left[td["next", "done"].squeeze(-1)]
    assert float(final.mean()) < 0.2


def test_terminal_metrics_survive_auto_reset():
    """At a terminal step of a rollout with auto-reset, ("next", ...) must describe the end
    of the finished episode (as a plain step loop reports it), not the fresh episode."""
    env = make_env(4, seed=3, budget=0.6)
    td = env.rollout(80, policy=first_allowed, break_when_any_done=False)
    done = td["next", "done"].squeeze(-1)
    assert torch.all(done.any(-1))
    ref = make_env(4, seed=3, budget=0.6)
    out = ref.reset()
    steps = []
    while not all(bool(s["done"][i]) for i in range(4) for s in steps[-1:]) or not steps:
        out = ref.step(first_allowed(out))["next"].clone()
        steps.append(out)
        if len(steps) > 80:
            break
    for i in range(4):
        t = int(done[i].nonzero()[0])
        assert bool(steps[t]["done"][i])
        got = td["next"][i, t].select("metrics", ("agents", "observation"))
        want = steps[t][i].select("metrics", ("agents", "observation"))
        assert float(got["metrics", "distance"]) > 0, f"env {i}: terminal distance reads 0"
        assert_td_equal(got, want, f"env {i} terminal step {t}")


class _TorchRLMerge(MAIPPEnv):
    """MAIPPEnv with TorchRL's own partial-reset merge (a masked ``where`` per key)."""

    _reset_proc_data = EnvBase._reset_proc_data


def _merge_pair(n_envs, **overrides):
    envs = [cls(MAIPPConfig(**{**SMALL, "budget": 0.6, **overrides}), batch_size=[n_envs])
            for cls in (MAIPPEnv, _TorchRLMerge)]
    for env in envs:
        env.set_seed(4)
    return envs


@pytest.mark.parametrize("n_envs", [1, 5])
def test_auto_reset_merge_equals_torchrl_merge(n_envs):
    """MAIPPEnv merges a reset by a plain update (its _reset returns every env's data):
    step after step with auto-reset the same data as TorchRL's masked merge, a carried
    entry the env does not produce zeroed in the reset envs only when some envs go on
    (TorchRL's full reset keeps it). E = 1: every reset is full; E = 5: partial ones."""
    envs = _merge_pair(n_envs)
    tds = [env.reset() for env in envs]
    partial = full = 0
    for t in range(40):
        outs = []
        for i, env in enumerate(envs):
            td = first_allowed(tds[i])
            td.set("carry", torch.full((n_envs, 2), float(t + 1), dtype=F64))
            outs.append(env.step_and_maybe_reset(td))
            tds[i] = outs[-1][1]
        assert_td_equal(outs[0][0], outs[1][0], f"step {t}: stepped data")
        assert_td_equal(tds[0], tds[1], f"step {t}: data after the reset")
        done = outs[0][0]["next", "done"].squeeze(-1)
        partial += bool(done.any() and not done.all())
        full += bool(done.all())
        zeroed = done.unsqueeze(-1) & ~done.all()
        assert torch.all((tds[0]["carry"] == 0) == zeroed), f"step {t}"
    assert full if n_envs == 1 else partial


def test_explicit_partial_reset_merge_equals_torchrl_merge():
    """A hand-written partial reset, a finished env left alone (it stays done), and an
    input holding only ``_reset`` (TorchRL pads the other envs with zeros): as TorchRL."""
    envs = _merge_pair(3)
    finals = [run_to_end(env)[-1] for env in envs]  # every env finished, none reset
    chosen = torch.tensor([[True], [False], [False]])
    out = [env.reset(finals[i].clone().set("_reset", chosen)) for i, env in enumerate(envs)]
    assert_td_equal(out[0], out[1], "full input")
    assert out[0]["done"].squeeze(-1).tolist() == [False, True, True]
    with pytest.warns(UserWarning, match="partial `'_reset'`"):  # TorchRL's, on both
        sparse = [env.reset(TensorDict({"_reset": chosen.roll(1, 0)}, batch_size=[3]))
                  for env in envs]
    assert_td_equal(sparse[0], sparse[1], "input holding only _reset")


def test_step_output_does_not_alias_env_state():
    env = make_env(2, seed=3)
    torch.manual_seed(3)
    td = env.reset()
    for _ in range(4):
        td = env.step(env.rand_action(td))["next"]
    snapshot = td.clone()
    env.reset(TensorDict({"_reset": torch.tensor([[True], [False]])}, batch_size=[2]))
    assert_td_equal(td, snapshot, "returned observation changed by a later reset")


def test_episode_ends_only_when_no_move_is_feasible_single_agent():
    env = make_env(6, seed=4, n_agents=1, risk_enabled=False)
    cfg = env.config
    tds = run_to_end(env)
    done_at = [None] * 6
    for t, td in enumerate(tds):
        for i in range(6):
            if done_at[i] is not None:
                continue
            if bool(td["done"][i]):
                done_at[i] = t
                continue
            # Not done: the single agent decides, and its mask is exactly the budget rule
            # over its k nearest neighbours (recomputed independently).
            assert bool(td["agents", "deciding"][i, 0])
            cur = int(td["agents", "observation", "current_node"][i, 0])
            idx, dist = knn(env.episode.roadmap.nodes[i], cfg.k_neighbors)
            nbrs = td["agents", "observation", "neighbors"][i, 0].numpy()
            assert set(nbrs.tolist()) == set(idx[cur].tolist())
            left = cfg.team_budget - float(td["metrics", "distance"][i])
            ndist = td["agents", "observation", "neighbor_dist"][i, 0].numpy()
            np.testing.assert_allclose(np.sort(ndist), dist[cur], rtol=0, atol=1e-12)
            assert np.array_equal(td["agents", "action_mask"][i, 0].numpy(), ndist <= left + EPS)
    assert all(t is not None for t in done_at)
    for i in range(6):
        final = tds[done_at[i]]
        assert bool(final["terminated"][i]) and not bool(final["truncated"][i])
        cur = int(env.episode.cur[i, 0])
        assert cur == int(final["agents", "observation", "current_node"][i, 0])
        left = cfg.team_budget - float(env.episode.budget_used[i])
        _, dist = knn(env.episode.roadmap.nodes[i], cfg.k_neighbors)
        assert left >= -1e-12
        assert np.all(dist[cur] > left + EPS), (i, left, dist[cur].min())


def test_someone_decides_while_not_done():
    env = make_env(4, seed=5, comm_range=0.3)
    torch.manual_seed(5)
    td = env.rollout(60, break_when_any_done=False)
    assert int(td["next", "done"].sum()) >= 2
    for prefix in ((), ("next",)):
        not_done = ~td[(*prefix, "done")].squeeze(-1)
        deciding = td[(*prefix, "agents", "deciding")].any(-1)
        assert torch.all(deciding[not_done])
        # Done envs have nobody deciding.
        assert not torch.any(td[(*prefix, "agents", "deciding")][~not_done])


@pytest.mark.parametrize("max_steps", [1000, 4], ids=["terminated", "truncated"])
def test_stepping_a_finished_env_changes_nothing_and_pays_nothing(max_steps):
    env = make_env(6, seed=6, max_steps=max_steps)
    tds = run_to_end(env)  # envs that finish early keep being stepped
    ended = [next(t for t, td in enumerate(tds) if td["done"][i]) for i in range(6)]
    if max_steps == 1000:
        assert len(set(ended)) > 1
    else:  # some truncated with agents still on an edge
        assert any(bool(tds[t]["truncated"][i]) for i, t in enumerate(ended))
        tds = tds + [env.step(env.rand_action(tds[-1]))["next"] for _ in range(3)]
    for i, t_end in enumerate(ended):
        at_end = tds[t_end]
        assert float(at_end["agents", "reward"][i].abs().sum()) > 0  # the terminal term
        for td in tds[t_end + 1:]:
            for key in ("done", "terminated", "truncated", ("metrics", "trace"),
                        ("metrics", "time"), ("metrics", "measurements")):
                assert torch.equal(td[key][i], at_end[key][i]), key
            assert not td["agents", "reward"][i].any()


def _find_masked_decider(env, seed):
    torch.manual_seed(seed)
    td = env.reset()
    for _ in range(200):
        mask, deciding = td["agents", "action_mask"], td["agents", "deciding"]
        hit = (deciding.unsqueeze(-1) & ~mask).nonzero()
        if len(hit):
            return td, tuple(int(v) for v in hit[0])
        td = env.step(env.rand_action(td))["next"]
        if td["done"].any():
            td = env.reset()
    raise AssertionError("no deciding agent with a masked slot found")


def test_masked_and_out_of_range_actions_raise_without_changing_state():
    env = make_env(2, seed=6)
    k = env.config.k_neighbors
    td, (e, a, slot) = _find_masked_decider(env, 6)
    before = state_leaves(env)
    spec_mask = env.full_action_spec["agents", "action"].mask.clone()
    bad_values = [slot, k, -1, k + 5]
    for value in bad_values:
        bad = first_allowed(td.clone())
        action = bad["agents", "action"].clone()
        action[e, a] = value
        bad["agents", "action"] = action
        with pytest.raises(ValueError, match="masked or out-of-range") as info:
            env.step(bad)
        msg = str(info.value)
        assert f"env {e} agent {a}" in msg and f"chose slot {value}" in msg
        allowed = td["agents", "action_mask"][e, a].nonzero().squeeze(-1).tolist()
        assert f"allowed slots are {allowed}" in msg
        assert_td_equal(state_leaves(env), before, f"after action {value}")
        assert torch.equal(env.full_action_spec["agents", "action"].mask, spec_mask)
    wrong = first_allowed(td.clone())
    wrong["agents", "action"] = wrong["agents", "action"].to(F64)
    with pytest.raises(ValueError, match="integer"):
        env.step(wrong)
    assert_td_equal(state_leaves(env), before, "after float action")
    # The env is still usable with a legal action.
    out = env.step(first_allowed(td.clone()))["next"]
    assert int(env.episode.steps[e]) == int(before["steps"][e]) + 1
    assert out["agents", "action_mask"].shape == (2, 3, k)


def test_in_range_actions_of_non_deciding_agents_are_ignored():
    results = []
    for fill in (0, 5):
        env = make_env(3, seed=7, comm_range=0.3)
        torch.manual_seed(7)
        td = env.reset()
        outs = []
        for _ in range(25):
            td = env.rand_action(td)
            action = td["agents", "action"].clone()
            action[~td["agents", "deciding"]] = fill
            td["agents", "action"] = action
            td = env.step(td)["next"]
            outs.append(td.exclude(("agents", "action")))
        results.append(torch.stack(outs))
    assert_td_equal(results[0], results[1])


def test_out_of_range_actions_of_non_deciding_agents_are_ignored():
    """The env documents that non-deciding agents' actions are ignored; a placeholder
    such as -1 for them must give the same step as any in-range value."""
    envs = [make_env(1, seed=8), make_env(1, seed=8)]
    tds = [e.reset() for e in envs]
    torch.manual_seed(8)
    for _ in range(50):
        action = envs[0].rand_action(tds[0])["agents", "action"]
        for t in tds:
            t["agents", "action"] = action.clone()
        if not tds[0]["agents", "deciding"].all():
            break
        tds = [e.step(t)["next"] for e, t in zip(envs, tds)]
    deciding = tds[0]["agents", "deciding"]
    assert deciding.any() and not deciding.all()
    action = tds[1]["agents", "action"].clone()
    action[~deciding] = -1
    tds[1]["agents", "action"] = action
    expected = envs[0].step(tds[0])["next"]
    out = envs[1].step(tds[1])["next"]
    assert_td_equal(out, expected)


# ====================================================================== determinism
def test_same_seed_gives_bit_identical_rollout():
    tds = []
    for env_seed in (11, 11, 12):
        env = make_env(3, seed=env_seed, comm_range=0.3)
        torch.manual_seed(0)
        tds.append(env.rollout(20, break_when_any_done=False))
    assert_td_equal(tds[0], tds[1])
    # A different env seed gives other worlds (the test above can fail).
    assert not torch.equal(tds[0]["state"], tds[2]["state"])


def test_episodes_do_not_depend_on_batch_size():
    tds = []
    for n_envs in (2, 5):
        env = make_env(n_envs, seed=4, budget=0.6)
        tds.append(env.rollout(60, policy=first_allowed, break_when_any_done=False))
    small, big = tds[0], tds[1][:2]
    assert int(small["next", "done"].sum()) >= 2  # auto-resets happened in envs 0 and 1
    for key in (("agents", "observation"), ("agents", "action"), ("agents", "action_mask"),
                "state", "metrics", ("next", "agents", "reward"), ("next", "metrics"),
                ("next", "agents", "observation"), ("next", "done")):
        a, b = small[key], big[key]
        if isinstance(a, torch.Tensor):
            assert torch.equal(a, b), key
        else:
            assert_td_equal(a, b, key)


def test_partial_reset_reinitialises_only_chosen_envs():
    cfg_kw = dict(seed=2, comm_range=0.3)
    env = make_env(4, **cfg_kw)
    torch.manual_seed(2)
    td = env.reset()
    for _ in range(6):
        td = env.step(env.rand_action(td))["next"]
    before = state_leaves(env)
    assert torch.all(before["steps"] == 6) and torch.all(before["budget_used"] > 0)
    chosen = torch.tensor([True, False, True, False])
    out = env.reset(TensorDict({"_reset": chosen.unsqueeze(-1)}, batch_size=[4]))
    after = state_leaves(env)
    m = env.config.n_agents
    for i in (1, 3):  # untouched
        assert_td_equal(after[i], before[i], f"env {i}")
    for i in (0, 2):
        assert int(after["steps"][i]) == 0 and float(after["budget_used"][i]) == 0.0
        assert float(after["time"][i]) == 0.0 and int(after["meas_count"][i]) == m
        assert torch.all(after["cur"][i] == 0)
        assert not torch.equal(after["world", "interest_centres"][i],
                               before["world", "interest_centres"][i])  # a new episode
        assert not bool(out["done"][i])
        assert float(out["metrics", "distance"][i]) == 0.0
        # Trace at the start: m duplicate measurements at the start node.
        rec = env.episode_record(i)
        assert torch.all(rec["points"] == rec["nodes"][0])
        mu, var = dense_gp(rec["points"], rec["values"], rec["query"])
        g2 = env.config.n_grid
        start_trace = float(trace_in_region(mu[:g2, 0], var[:g2]))
        assert math.isclose(float(out["metrics", "trace"][i]), start_trace, rel_tol=1e-9)
        assert start_trace < 900.0
    # The reset envs drew their second episode: the same as a fresh env's second episode.
    fresh = make_env(4, **cfg_kw)
    fresh.reset()
    fresh.reset()
    ref = state_leaves(fresh)
    for i in (0, 2):
        assert_td_equal(after[i], ref[i], f"env {i} vs fresh")


def _seeded_reset(env, instance, trial):
    n = env.n_envs
    return env.reset(TensorDict({"instance_seed": torch.tensor(instance, dtype=torch.int64),
                                 "trial_seed": torch.tensor(trial, dtype=torch.int64)},
                                batch_size=[n]))


def test_explicit_seeds_pin_world_and_roadmap():
    a = make_env(3, seed=0)
    b = make_env(2, seed=99)
    _seeded_reset(a, [5, 6, 7], [1, 2, 3])
    _seeded_reset(b, [7, 5], [3, 1])
    sa, sb = state_leaves(a), state_leaves(b)
    for ia, ib in ((2, 0), (0, 1)):
        assert_td_equal(sa[ia]["world"], sb[ib]["world"])
        assert_td_equal(sa[ia]["roadmap"], sb[ib]["roadmap"])
        assert torch.equal(sa[ia]["belief", "mu"], sb[ib]["belief", "mu"])
    assert not torch.equal(sa["world", "interest_centres"][0], sa["world", "interest_centres"][1])
    # Same instance, other trials: one world, other roadmaps; and seeds beat the counter.
    _seeded_reset(a, [5, 5, 5], [1, 2, 3])
    sc = state_leaves(a)
    for i in (1, 2):
        assert_td_equal(sc[i]["world"], sc[0]["world"])
        assert not torch.equal(sc[i]["roadmap", "nodes"], sc[0]["roadmap", "nodes"])
    assert_td_equal(sc[0]["roadmap"], sa[0]["roadmap"])
    assert_td_equal(sc[0]["world"], sa[0]["world"])


# ====================================================================== communication
def test_infinite_range_equals_one_shared_belief():
    runs = []
    for comm in (math.inf, 10.0):
        env = make_env(2, seed=9, comm_range=comm, budget=1.5)
        assert env.n_beliefs == (1 if math.isinf(comm) else 4)
        runs.append(env.rollout(40, policy=first_allowed, break_when_any_done=False))
    a, b = runs
    for key in (("agents", "action"), ("agents", "observation", "current_node"),
                ("next", "agents", "observation", "current_node"), ("next", "done"),
                ("agents", "action_mask"), ("next", "metrics", "measurements")):
        assert torch.equal(a[key], b[key]), key
    for key in (("agents", "observation", "node_features"),
                ("next", "agents", "observation", "node_features"),
                ("next", "agents", "reward"), ("next", "metrics", "trace"), ("next", "state")):
        assert torch.allclose(a[key], b[key], rtol=0, atol=1e-9), key


def test_finite_range_restricts_shared_knowledge():
    env = make_env(4, seed=10, comm_range=0.3, budget=2.0)
    tds = run_to_end(env, seed=10)
    assert len(tds) > 5
    # Replay to inspect the held sets at every step.
    env = make_env(4, seed=10, comm_range=0.3, budget=2.0)
    torch.manual_seed(10)
    td = env.reset()
    restricted = False
    m = env.config.n_agents
    while not td["done"].all():
        td = env.step(env.rand_action(td))["next"]
        for i in range(4):
            rec = env.episode_record(i)
            teammate = rec["agent"].unsqueeze(0) != torch.arange(m).unsqueeze(1)
            restricted |= bool((~rec["known"] & teammate).any())
            # The team belief always holds every measurement.
            assert int(env.episode.belief.count[i, -1]) == len(rec["points"])
    assert restricted
    # Global communication: every agent holds everything at every step.
    env = make_env(2, seed=10, comm_range=math.inf, budget=2.0)
    torch.manual_seed(10)
    td = env.reset()
    while not td["done"].all():
        td = env.step(env.rand_action(td))["next"]
        for i in range(2):
            assert torch.all(env.episode_record(i)["known"])


# ====================================================================== intents
def _gauss(x, mean, cov):
    d = x - mean
    q = np.einsum("ni,ij,nj->n", d, np.linalg.inv(cov), d)
    return np.exp(-0.5 * q) / (2 * np.pi * np.sqrt(np.linalg.det(cov)))


def test_intents_set_teammates_intent_feature():
    assert NODE_FEATURES[5] == "intent"
    env = make_env(2, seed=11, budget=2.0)
    td = env.reset()
    m = env.config.n_agents
    assert torch.all(td["agents", "deciding"])  # everyone decides at the start
    assert torch.all(td["agents", "observation", "node_features"][..., 5] == 0)
    gen = torch.Generator().manual_seed(0)
    mean = torch.rand(2, m, 2, generator=gen, dtype=F64)
    a = torch.randn(2, m, 2, 2, generator=gen, dtype=F64) * 0.2
    cov = a @ a.transpose(-1, -2) + (1 / 28) ** 2 * torch.eye(2, dtype=F64)
    td = first_allowed(td)
    td["agents", "intent", "mean"] = mean
    td["agents", "intent", "cov"] = cov
    out = env.step(td)["next"]
    feat = out["agents", "observation", "node_features"][..., 5]
    nodes = env.episode.roadmap.nodes
    for i in range(2):
        for r in range(m):
            total = sum(_gauss(nodes[i].numpy(), mean[i, s].numpy(), cov[i, s].numpy())
                        for s in range(m) if s != r)
            np.testing.assert_allclose(feat[i, r].numpy(), total / total.max(), rtol=1e-9,
                                       atol=1e-12)
            assert math.isclose(float(feat[i, r].max()), 1.0, rel_tol=1e-12)


def test_non_pd_intent_covariance_raises():
    env = make_env(1, seed=12)
    td = first_allowed(env.reset())
    before = state_leaves(env)
    cov = torch.eye(2, dtype=F64).expand(1, 3, 2, 2).clone()
    cov[0, 1] = torch.tensor([[1.0, 2.0], [2.0, 1.0]], dtype=F64)
    td["agents", "intent", "mean"] = torch.full((1, 3, 2), 0.5, dtype=F64)
    td["agents", "intent", "cov"] = cov
    with pytest.raises(ValueError, match="positive"):
        env.step(td)
    assert_td_equal(state_leaves(env), before)
    td2 = first_allowed(env.reset())
    td2["agents", "intent", "mean"] = torch.full((1, 3, 2), 0.5, dtype=F64)
    with pytest.raises(ValueError, match="cov"):
        env.step(td2)


# ====================================================================== risk and safety
@pytest.mark.parametrize("comm_range", [math.inf, 0.3])
def test_risk_traps_and_risk_mask(comm_range):
    env = make_env(8, seed=0, budget=2.0, comm_range=comm_range)
    cfg = env.config
    g2, m = cfg.n_grid, cfg.n_agents
    torch.manual_seed(0)
    td = env.reset()
    risk_masked = 0
    steps = 0
    while not td["done"].all():
        st = env.episode
        # The mask is exactly budget & collision & (risk belief mean <= 0.7).
        nbr, nlen = st.nbr, st.nbr_len
        ok = st.roadmap.neighbor_valid.gather(1, st.cur.unsqueeze(-1).expand(-1, -1, nbr.shape[-1]))
        ok &= nlen <= (cfg.team_budget - st.budget_used)[:, None, None] + EPS
        for a in range(m):
            for b in range(m):
                if a != b:
                    ok[:, a] &= nbr[:, a] != st.tgt[:, b].unsqueeze(-1)
        risk_mean = st.belief.mu[:, env.agent_belief_index, g2:, 1].to(F64)  # [E, m, N]
        risky = risk_mean.gather(-1, nbr) > cfg.risk_mask_threshold
        deciding = td["agents", "deciding"]
        expected = ok & ~risky
        assert torch.equal(td["agents", "action_mask"][deciding], expected[deciding])
        resting = (st.edge_len == 0) & ~st.trapped
        assert torch.equal(deciding, resting & expected.any(-1) & ~td["done"])
        risk_masked += int((ok & risky)[deciding].sum())
        assert torch.equal(td["metrics", "traps"], st.trapped.sum(-1))
        td = env.step(env.rand_action(td))["next"]
        steps += 1
    assert torch.equal(td["metrics", "traps"], env.episode.trapped.sum(-1))
    assert risk_masked > 0  # the risk rule really hid neighbours
    assert int(env.episode.trapped.sum()) > 0  # traps happened
    # Independently: an agent is trapped iff it reached a node of true risk >= 0.9, and it
    # never moved after the first such node.
    for i in range(env.n_envs):
        rec = env.episode_record(i)
        for a in range(m):
            traj = rec["trajectories"][a]
            risk = true_risk(env, i, rec["nodes"][traj[1:]])
            hit = np.nonzero(risk >= cfg.trap_threshold)[0]
            assert bool(env.episode.trapped[i, a]) == (len(hit) > 0)
            if len(hit):
                assert hit[0] == len(traj) - 2  # the trap node is the last one


def test_world_fields_match_independent_formula():
    env = make_env(3, seed=13)
    env.reset()
    w = env.episode.world
    pts = torch.rand(3, 50, 2, dtype=F64)
    risk = w.risk(pts)
    interest = w.interest(pts)
    for i in range(3):
        ref_r = true_risk(env, i, pts[i])
        ref_i = true_field(pts[i].numpy(), w.interest_centres[i].numpy(),
                           w.interest_stds[i].numpy(), w.interest_valid[i].numpy(),
                           env.config.grid_size)
        np.testing.assert_allclose(risk[i].numpy(), ref_r, rtol=1e-10, atol=1e-13)
        np.testing.assert_allclose(interest[i].numpy(), ref_i, rtol=1e-10, atol=1e-13)
        assert 8 <= int(w.interest_valid[i].sum()) <= 12
        assert 4 <= int(w.risk_valid[i].sum()) <= 6
    # The measured signal is y_it (1 - 0.5 y_rk) with N(0, 0.01^2) noise.
    rec = None
    td = env.reset()
    for _ in range(10):
        td = env.step(env.rand_action(td))["next"]
    rec = env.episode_record(0)
    sig = (w.interest(rec["points"][None]) * (1 - 0.5 * w.risk(rec["points"][None])))[0]
    risk = w.risk(rec["points"][None])[0]
    noise = torch.cat([rec["values"][:, 0] - sig, rec["values"][:, 1] - risk])
    assert float(noise.abs().max()) < 0.06 and 0.003 < float(noise.std()) < 0.03


# ====================================================================== evidence and AOI
@pytest.mark.parametrize("aoi", [False, True])
def test_evidence_metrics(aoi):
    env = make_env(4, seed=14, budget=2.0, aoi_enabled=aoi, risk_enabled=False)
    tds = run_to_end(env, seed=14)
    w = env.episode.world
    for td in tds:
        ins, out = td["metrics", "evidence_inside"], td["metrics", "evidence_outside"]
        total = td["metrics", "evidence_total"]
        assert torch.all(ins + out <= total) and torch.all(ins >= 0) and torch.all(out >= 0)
        if not aoi:
            assert torch.all(out == 0)
    final = tds[-1]
    found_any = 0
    for i in range(4):
        rec = env.episode_record(i)
        centres = w.interest_centres[i][w.interest_valid[i]]
        d = torch.cdist(rec["points"], centres)
        found = (d <= env.config.detect_radius).any(0)
        lo, hi = w.aoi_low[i], w.aoi_high[i]
        inside = ((centres >= lo) & (centres <= hi)).all(-1)
        assert int(final["metrics", "evidence_total"][i]) == len(centres)
        assert int(final["metrics", "evidence_inside"][i]) == int((found & inside).sum())
        assert int(final["metrics", "evidence_outside"][i]) == int((found & ~inside).sum())
        found_any += int(found.sum())
    assert found_any > 0


def _outside_fraction(env):
    w = env.episode.world
    inside = ((w.interest_centres >= w.aoi_low.unsqueeze(1))
              & (w.interest_centres <= w.aoi_high.unsqueeze(1))).all(-1)
    valid = w.interest_valid
    return ((~inside & valid).sum(-1).double() / valid.sum(-1).double())


def test_aoi_bias_moves_evidence_outside():
    fracs = {}
    for bias in (0.0, 1.0):
        env = make_env(16, seed=15, aoi_enabled=True, aoi_bias=bias)
        env.reset()
        w = env.episode.world
        side = w.aoi_high - w.aoi_low
        assert torch.allclose(side, torch.full_like(side, 0.5))  # area fraction 0.25
        assert torch.all(w.aoi_low >= 0) and torch.all(w.aoi_high <= 1 + 1e-12)
        fracs[bias] = _outside_fraction(env)
    # Same worlds; the unbiased AOI holds the most evidence, the fully biased the least.
    assert torch.all(fracs[0.0] <= fracs[1.0])
    assert float(fracs[0.0].mean()) < float(fracs[1.0].mean()) - 0.2


# ====================================================================== dynamics
def _polyline_points(pts, spacing, count):
    seg = pts[1:] - pts[:-1]
    lens = np.sqrt((seg**2).sum(-1))
    cum = np.concatenate([[0.0], np.cumsum(lens)])
    out = []
    for j in range(count):
        s = j * spacing
        e = min(np.searchsorted(cum, s, side="right") - 1, len(lens) - 1)
        e = max(e, 0)
        frac = (s - cum[e]) / lens[e] if len(lens) and lens[e] > 0 else 0.0
        out.append(pts[e] + frac * seg[e] if len(lens) else pts[0])
    return np.array(out), cum[-1]


def test_measurements_every_spacing_along_each_path():
    env = make_env(3, seed=16, budget=1.5, risk_enabled=False)
    cfg = env.config
    tds = run_to_end(env, seed=16)
    for i in range(3):
        rec = env.episode_record(i)
        total = 0.0
        for a in range(cfg.n_agents):
            pts = rec["trajectory_points"][a].numpy()
            own = rec["points"][rec["agent"] == a].numpy()
            _, length = _polyline_points(pts, cfg.sample_spacing, 1)
            count = int(math.floor(length / cfg.sample_spacing + 1e-9)) + 1
            assert len(own) == count, (i, a)
            ref, _ = _polyline_points(pts, cfg.sample_spacing, count)
            np.testing.assert_allclose(own, ref, rtol=0, atol=1e-9)
            total += length
        assert math.isclose(total, float(tds[-1]["metrics", "distance"][i]), abs_tol=1e-9)
        assert int(tds[-1]["metrics", "measurements"][i]) == len(rec["points"])


def test_measurement_times_follow_unit_speed():
    """The log's ``time`` of a measurement taken 0.2 further along the same agent's path
    is at least 0.2 later (agents move at unit speed)."""
    env = make_env(2, seed=17, budget=1.5, risk_enabled=False)
    run_to_end(env, seed=17)
    for i in range(2):
        rec = env.episode_record(i)
        for a in range(env.config.n_agents):
            t = rec["time"][rec["agent"] == a]
            gaps = t[1:] - t[:-1]
            assert float(gaps.min()) >= env.config.sample_spacing - 1e-9, (i, a, t.tolist())


def _single_agent_rewards():
    """Rewards of random single-agent episodes (risk on) with the PROTOCOL value
    r_t = max(0, (Phi_{t-1} - Phi_t) / Phi_{t-1}) - 0.1 backtrack - true risk if > 0.7
    - done Phi_T / 900, recomputed from the trajectory and an independent risk field."""
    env = make_env(4, seed=18, n_agents=1, budget=2.0)
    cfg = env.config
    tds = run_to_end(env, seed=18)
    rows = []  # (reward, expected, backtracked, risk penalised)
    for i in range(4):
        visited = [int(tds[0]["agents", "observation", "current_node"][i, 0])]
        nodes = env.episode.roadmap.nodes[i]
        for t in range(1, len(tds)):
            prev, cur = tds[t - 1], tds[t]
            if bool(prev["done"][i]):
                break
            node = int(cur["agents", "observation", "current_node"][i, 0])
            # Backtracking: going to one of the last 2 nodes the agent left.
            back = node in visited[-cfg.backtrack_window - 1 : -1]
            phi0 = float(prev["metrics", "trace"][i])
            phi1 = float(cur["metrics", "trace"][i])
            expected = max(0.0, (phi0 - phi1) / phi0) - cfg.backtrack_penalty * back
            risk = float(true_risk(env, i, nodes[node : node + 1])[0])
            risky = risk > cfg.risk_penalty_threshold
            expected -= risk * risky
            if bool(cur["done"][i]):
                expected -= cfg.terminal_scale * phi1
            rows.append((float(cur["agents", "reward"][i, 0, 0]), expected, back, risky))
            visited.append(node)
    return rows


def test_reward_single_agent():
    rows = _single_agent_rewards()
    assert any(r[2] for r in rows)  # backtracking happened
    for reward, expected, _, _ in rows:
        assert math.isclose(reward, expected, rel_tol=0, abs_tol=1e-7)


def test_penalties_exact_in_float64():
    """In the float64 env a backtracking step is penalised exactly 0.1 (not 0.1 rounded
    to float32, 0.10000000149011612)."""
    rows = [r for r in _single_agent_rewards() if r[2]]
    assert rows
    worst = max(abs(reward - expected) for reward, expected, _, _ in rows)
    assert worst < 1e-12, worst


# ====================================================================== views and errors
def test_observation_is_consistent_with_state():
    env = make_env(2, seed=19, comm_range=0.3)
    torch.manual_seed(19)
    td = env.reset()
    for _ in range(5):
        td = env.step(env.rand_action(td))["next"]
    cfg, st = env.config, env.episode
    g2 = cfg.n_grid
    feats = td["agents", "observation", "node_features"]
    n = cfg.n_roadmap_nodes
    assert feats.shape == (2, 3, n, len(NODE_FEATURES))
    assert torch.equal(feats[..., 0], st.roadmap.nodes[..., 0].unsqueeze(1).expand(2, 3, n))
    for a in range(3):
        g = int(env.agent_belief_index[a])
        assert torch.equal(feats[:, a, :, 2], st.belief.mu[:, g, g2:, 0])
        sd = st.belief.sigma2[:, g, g2:].clamp_min(0).sqrt()
        assert torch.allclose(feats[:, a, :, 3], sd, rtol=0, atol=1e-15)
        ucb = st.belief.mu[:, g, g2:, 1] + sd
        assert torch.allclose(feats[:, a, :, 4], ucb, rtol=0, atol=1e-15)
    state = td["state"]
    assert torch.all(state[..., 5].sum(-1) == 3)  # every agent targets one node
    assert torch.equal(td["agents", "observation", "current_node"], st.cur)


def test_errors_before_reset_and_bad_record_index():
    env = make_env(2)
    with pytest.raises(RuntimeError, match="reset"):
        _ = env.episode
    env.reset()
    with pytest.raises(IndexError):
        env.episode_record(2)


# ====================================================================== CUDA
@pytest.mark.cuda
def test_cuda_rollout_matches_cpu():
    if not torch.cuda.is_available():
        pytest.skip("CUDA is not available")
    tds = []
    for device in ("cpu", "cuda"):
        cfg = MAIPPConfig(**SMALL, comm_range=0.3)
        env = MAIPPEnv(cfg, batch_size=[3], device=device)
        env.set_seed(20)
        tds.append(env.rollout(30, policy=first_allowed, break_when_any_done=False).to("cpu"))
    cpu, gpu = tds
    for key in (("agents", "action"), ("agents", "observation", "current_node"),
                ("next", "done"), ("next", "metrics", "measurements")):
        assert torch.equal(cpu[key], gpu[key]), key
    for key in (("next", "agents", "observation", "node_features"), ("next", "metrics", "trace"),
                ("next", "agents", "reward")):
        assert torch.allclose(cpu[key], gpu[key], rtol=1e-9, atol=1e-9), key


def test_budget_drawn_per_episode_is_respected():
    """budget_min > 0 (training across a suite's range): each episode draws its own pool,
    the distance never exceeds it, and the budget feature is relative to it."""
    env = make_env(16, seed=4, budget=3.0, budget_min=1.0)
    td = env.rollout(160, break_when_any_done=False)
    pools = env.episode.team_budget
    m = env.n_agents
    assert float(pools.min()) >= m * 1.0 and float(pools.max()) <= m * 3.0
    assert len(set(pools.tolist())) == 16  # drawn per env, not shared
    done = td["next", "done"].squeeze(-1)
    assert int(done.sum()) > 16
    # At an episode's end: distance <= its pool and the feature matches (pool - used) / pool.
    used = td["next", "metrics", "distance"]
    left = td["next", "agents", "observation", "budget"][..., 0, 0]
    pool_now = used / (1 - left).clamp_min(1e-12)
    ok = left < 1 - 1e-6
    assert float(pool_now[ok].max()) <= m * 3.0 + 1e-6
    assert float(pool_now[ok].min()) >= m * 1.0 - 1e-6
    # Draws are keyed by the episode, not the batch: same pools at E=16 and E=4.
    small = make_env(4, seed=4, budget=3.0, budget_min=1.0)
    small.reset()
    env2 = make_env(16, seed=4, budget=3.0, budget_min=1.0)
    env2.reset()
    assert torch.equal(small.episode.team_budget, env2.episode.team_budget[:4])
    with pytest.raises(ValueError, match="budget_min"):
        MAIPPConfig(budget=2.0, budget_min=2.5)


def test_node_encoding_key():
    env = make_env(3, seed=5, n_nodes=30, k_neighbors=6, node_encoding_dim=8)
    check_env_specs(env, seed=5)
    td = env.reset()
    rm = env.episode.roadmap
    from maipp_bench.envs.roadmap import laplacian_encoding

    assert torch.equal(td["node_encoding"], laplacian_encoding(rm.neighbors, rm.neighbor_valid, 8))
    assert "node_encoding" not in make_env(2, n_nodes=30, k_neighbors=6).reset().keys()


def test_masked_random_policy_drives_wrappers_and_collectors():
    from torchrl.collectors import Collector
    from torchrl.envs import SerialEnv

    from maipp_bench.envs import MaskedRandomPolicy

    cfg = MAIPPConfig(n_nodes=30, k_neighbors=6, budget=1.0)
    env = SerialEnv(2, lambda: MAIPPEnv(cfg, batch_size=[2]))  # copies the spec: no mask
    # torchrl 0.14 warns for any module policy on an env without "is_init" (a stateless
    # policy needs no InitTracker); opt out, as train.py does.
    collector = Collector(env, MaskedRandomPolicy(torch.Generator().manual_seed(0)),
                          frames_per_batch=60, total_frames=120,
                          auto_register_policy_transforms=False)
    done = 0
    for batch in collector:
        _assert_actions_allowed(batch.reshape(-1))
        done += int(batch["next", "done"].sum())
    collector.shutdown()
    assert done > 0  # finished envs were reset and played on
    with pytest.raises(ValueError, match="at least one allowed slot"):
        MaskedRandomPolicy()(TensorDict({("agents", "action_mask"): torch.zeros(1, 2, 3,
                                                                                dtype=bool)}))
