"""The incremental GP belief against an independent dense float64 GP (PROTOCOL "Beliefs")."""

from __future__ import annotations

import math

import pytest
import torch
from gp_reference import dense_gp, trace_in_region

from maipp_bench.envs import GPBelief, GPPrior, MAIPPConfig, MAIPPEnv
from maipp_bench.envs.belief import _gathered_product, interest_trace
from maipp_bench.envs.world import grid_points

F64 = torch.float64
PRIOR = GPPrior("matern32", 0.25, 1.0, 1e-4)


def _rel_mean_err(mu, ref):
    """Max error of each channel relative to that channel's largest |mean|."""
    return float(((mu.to(F64) - ref).abs().amax(-2) / ref.abs().amax(-2)).max())


def _field(x):
    """A smooth two-channel test field with values in [0, 1]."""
    return torch.stack([0.5 + 0.5 * torch.sin(5 * x[..., 0]) * torch.cos(3 * x[..., 1]),
                        torch.exp(-8 * ((x - 0.6) ** 2).sum(-1))], -1)


def _random_batches(gen, batch, rounds, p, values, n_pool=12):
    """Measurement batches drawn from a small pool, so points repeat within and across
    rounds (duplicates), with random masks (some beliefs take nothing in a round).

    ``values="field"``: a smooth field plus N(0, 0.01^2) noise, as the env measures;
    ``values="arbitrary"``: unrelated N(0.3, 0.5^2) values even at duplicate points (a
    badly conditioned stress case for the float64 path)."""
    pool = torch.rand(*batch, n_pool, 2, generator=gen, dtype=F64)
    out = []
    for _ in range(rounds):
        pick = torch.randint(0, n_pool, (*batch, p), generator=gen)
        x = pool.gather(-2, pick.unsqueeze(-1).expand(*batch, p, 2))
        if values == "field":
            y = _field(x) + 0.01 * torch.randn(*batch, p, 2, generator=gen, dtype=F64)
        else:
            y = torch.randn(*batch, p, 2, generator=gen, dtype=F64) * 0.5 + 0.3
        mask = torch.rand(*batch, p, generator=gen) < 0.6
        out.append((x, y, mask))
    out[0][2][0, 0] = False  # a belief that takes nothing in the first round
    return out


@pytest.mark.parametrize(
    ("dtype", "values"),
    [(torch.float64, "field"), (torch.float64, "arbitrary"), (torch.float32, "field")],
)
def test_add_matches_dense_gp(dtype, values):
    gen = torch.Generator().manual_seed(0)
    batch, nq, rounds, p = (3, 2), 70, 5, 6
    query = torch.rand(*batch, nq, 2, generator=gen, dtype=F64)
    gp = GPBelief.empty(batch, capacity=rounds * p, n_query=nq, n_channels=2, dtype=dtype)
    xs, ys = [[[] for _ in range(batch[1])] for _ in range(batch[0])], None
    ys = [[[] for _ in range(batch[1])] for _ in range(batch[0])]
    n_dup = 0
    for x, y, mask in _random_batches(gen, batch, rounds, p, values):
        before = gp.clone()
        gp.add(PRIOR, query, x, y, mask)
        for i in range(batch[0]):
            for j in range(batch[1]):
                sel = mask[i, j]
                if not sel.any():  # untouched beliefs are bit-identical
                    assert torch.equal(gp.sigma2[i, j], before.sigma2[i, j])
                    assert torch.equal(gp.mu[i, j], before.mu[i, j])
                xs[i][j].append(x[i, j][sel])
                ys[i][j].append(y[i, j][sel])
                xx, yy = torch.cat(xs[i][j]), torch.cat(ys[i][j])
                n_dup += len(xx) - len(torch.unique(xx, dim=0))
                assert int(gp.count[i, j]) == len(xx)
                mu, var = dense_gp(xx, yy, query[i, j])
                if len(xx) == 0:
                    assert torch.all(gp.sigma2[i, j] == 1.0) and torch.all(gp.mu[i, j] == 0)
                    continue
                if dtype == F64:
                    assert _rel_mean_err(gp.mu[i, j], mu) < 1e-9
                    assert float((gp.sigma2[i, j] - var).abs().max()) < 1e-9
                else:
                    assert gp.mu.dtype == torch.float32
                    assert _rel_mean_err(gp.mu[i, j], mu) < 1e-3
                    assert float((gp.sigma2[i, j].to(F64) - var).abs().max()) < 1e-3
    assert n_dup > 0  # the data really contained duplicate points


def test_add_in_one_call_equals_one_by_one():
    gen = torch.Generator().manual_seed(1)
    query = torch.rand(40, 2, generator=gen, dtype=F64)
    x = torch.rand(2, 5, 2, generator=gen, dtype=F64)
    x[:, 3] = x[:, 1]  # a duplicate inside the batch
    y = torch.randn(2, 5, 1, generator=gen, dtype=F64)
    mask = torch.tensor([[True, False, True, True, True], [True, True, True, False, False]])
    a = GPBelief.empty((2,), 8, 40, 1)
    a.add(PRIOR, query, x, y, mask)
    b = GPBelief.empty((2,), 8, 40, 1)
    for t in range(5):
        b.add(PRIOR, query, x[:, t : t + 1], y[:, t : t + 1], mask[:, t : t + 1])
    assert torch.allclose(a.mu, b.mu, rtol=0, atol=1e-12)
    assert torch.allclose(a.sigma2, b.sigma2, rtol=0, atol=1e-12)


def test_add_after_inference_mode_use_works_outside_it():
    # The gather buffers are reused across calls: an evaluation under inference_mode and a
    # training run in the same process must not share them (inference tensors are
    # read-only outside inference mode).
    query = torch.rand(30, 2, dtype=F64)
    x, y = torch.rand(4, 2, 2, dtype=F64), torch.randn(4, 2, 1, dtype=F64)
    mask = torch.zeros(4, 2, dtype=torch.bool)
    mask[1] = True  # one belief of four takes points: the gather path
    with torch.inference_mode():
        inside = GPBelief.empty((4,), 6, 30, 1)
        inside.add(PRIOR, query, x, y, mask)
    outside = GPBelief.empty((4,), 6, 30, 1)
    outside.add(PRIOR, query, x, y, mask)
    assert torch.equal(outside.mu, inside.mu) and torch.equal(outside.sigma2, inside.sigma2)


def test_capacity_overflow_raises():
    gp = GPBelief.empty((1,), 3, 10, 1)
    query = torch.rand(10, 2, dtype=F64)
    with pytest.raises(RuntimeError, match="capacity"):
        gp.add(PRIOR, query, torch.rand(1, 4, 2, dtype=F64), torch.zeros(1, 4, 1, dtype=F64),
               torch.ones(1, 4, dtype=torch.bool))


def test_fantasy_variance_matches_dense_gp():
    gen = torch.Generator().manual_seed(2)
    batch, nq, n_cand, p = (2,), 50, 4, 5
    query = torch.rand(*batch, nq, 2, generator=gen, dtype=F64)
    gp = GPBelief.empty(batch, 10, nq, 1)
    x0 = torch.rand(*batch, 6, 2, generator=gen, dtype=F64)
    m0 = torch.tensor([[True] * 6, [True, True, False, True, False, False]])
    gp.add(PRIOR, query, x0, torch.randn(*batch, 6, 1, generator=gen, dtype=F64), m0)
    cand = torch.rand(*batch, n_cand, p, 2, generator=gen, dtype=F64)
    cand[0, 1, 2] = x0[0, 0]  # a candidate point already measured (duplicate)
    cand[1, 2, 4] = cand[1, 2, 0]  # a duplicate inside a candidate set
    cmask = torch.rand(*batch, n_cand, p, generator=gen) < 0.7
    cmask[0, 1, 2] = cmask[1, 2, 4] = cmask[1, 2, 0] = True
    cmask[1, 3] = False  # a candidate set that is all padding
    # Garbage in the padding must not matter.
    cand = torch.where(cmask.unsqueeze(-1), cand, torch.full_like(cand, 7.0))
    fv = gp.fantasy_variance(PRIOR, query, cand, cmask)
    assert fv.shape == (*batch, n_cand, nq)
    fv_grid = gp.fantasy_variance(PRIOR, query, cand, cmask, n_query=20)
    assert fv_grid.shape == (*batch, n_cand, 20)
    for i in range(batch[0]):
        for c in range(n_cand):
            pts = torch.cat([x0[i][m0[i]], cand[i, c][cmask[i, c]]])
            _, var = dense_gp(pts, torch.zeros(len(pts)), query[i])
            assert float((fv[i, c] - var).abs().max()) < 1e-9
            assert float((fv_grid[i, c] - var[:20]).abs().max()) < 1e-9
    # The all-padding candidate leaves the current variance unchanged.
    assert torch.allclose(fv[1, 3], gp.sigma2[1], rtol=0, atol=1e-12)
    # Fantasies do not modify the belief.
    _, var_now = dense_gp(x0[0], torch.zeros(6), query[0])
    assert float((gp.sigma2[0] - var_now).abs().max()) < 1e-9


def test_fantasy_posterior_and_grown_match_dense_gp():
    gen = torch.Generator().manual_seed(5)
    nq, n_cand, p = 40, 3, 4
    query = torch.rand(2, nq, 2, generator=gen, dtype=F64)
    gp = GPBelief.empty((2,), 8, nq, 2)
    x0 = torch.rand(2, 8, 2, generator=gen, dtype=F64)
    y0 = torch.randn(2, 8, 2, generator=gen, dtype=F64)
    gp.add(PRIOR, query, x0, y0, torch.ones(2, 8, dtype=torch.bool))  # full capacity
    big = gp.grown(3)  # room for three more (e.g. teammates' committed points)
    x1 = torch.rand(2, 3, 2, generator=gen, dtype=F64)
    y1 = torch.randn(2, 3, 2, generator=gen, dtype=F64)
    big.add(PRIOR, query, x1, y1, torch.ones(2, 3, dtype=torch.bool))
    assert int(gp.count.max()) == 8  # the original is untouched
    cand = torch.rand(2, n_cand, p, 2, generator=gen, dtype=F64)
    vals = torch.randn(2, n_cand, p, generator=gen, dtype=F64)
    cmask = torch.rand(2, n_cand, p, generator=gen) < 0.75
    mean, var = big.fantasy_posterior(PRIOR, query, cand, vals, cmask)
    for i in range(2):
        for c in range(n_cand):
            pts = torch.cat([x0[i], x1[i], cand[i, c][cmask[i, c]]])
            ys = torch.cat([y0[i, :, 0], y1[i, :, 0], vals[i, c][cmask[i, c]]])
            ref_mean, ref_var = dense_gp(pts, ys, query[i])
            assert float((mean[i, c] - ref_mean.squeeze(-1)).abs().max()) < 1e-9
            assert float((var[i, c] - ref_var).abs().max()) < 1e-9


@pytest.mark.parametrize("dense", [True, False])
def test_gathered_gives_the_bits_of_index_then_grown(dense):
    """TI's planning copy (used prefix only, each belief once, then repeated) evolves
    bit-identically to the full-capacity copy it replaces, whether the adds update every
    belief in place (dense) or gather the few that take points."""
    gen = torch.Generator().manual_seed(11)
    nq, cap, extra, reps = 30, 16, 6, 3
    query = torch.rand(4, 3, nq, 2, generator=gen, dtype=F64)
    gp = GPBelief.empty((4, 3), cap, nq, 2)
    for x, y, mask in _random_batches(gen, (4, 3), 3, 3, "field"):
        gp.add(PRIOR, query, x, y, mask)
    e_idx, g_idx = torch.tensor([2, 0, 2]), torch.tensor([1, 1, 0])
    new = gp.gathered((e_idx, g_idx), extra, torch.float32, repeats=reps)
    old = gp[e_idx.repeat_interleave(reps), g_idx.repeat_interleave(reps)].grown(
        extra, torch.float32)
    assert new.capacity == int(gp.count[e_idx, g_idx].max()) + extra < old.capacity
    q = query[e_idx, g_idx].repeat_interleave(reps, 0).float()
    for _ in range(2):  # two rounds of at most 3 points: within the extra room
        x = torch.rand(9, 3, 2, generator=gen)
        mask = torch.rand(9, 3, generator=gen) < (0.9 if dense else 0.2)
        for b in (new, old):
            b.add(PRIOR, q, x, torch.zeros(9, 3, 2), mask)
    assert torch.equal(new.mu, old.mu) and torch.equal(new.sigma2, old.sigma2)
    assert torch.equal(new.count, old.count)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_gathered_product_gives_the_bits_of_gather_then_bmm(dtype):
    """The blocked product in GPBelief.add reads only used rows (unused slots read the
    belief's zero last row) and must equal gathering the whole prefix then one bmm, bit
    for bit, whatever the block boundaries: ragged counts, a full belief, an empty one."""
    gen = torch.Generator().manual_seed(5)
    n_beliefs, cap, nq, p = 40, 12, 37, 3
    count = torch.randint(0, cap - 1, (n_beliefs,), generator=gen)
    count[3], count[7] = cap, 0  # only belief 3 is full
    table = torch.randn(n_beliefs, cap, nq, generator=gen, dtype=dtype)
    table *= (torch.arange(cap) < count.unsqueeze(-1)).unsqueeze(-1)  # unused rows are zero
    with_full = torch.tensor([0, 3, 4, 7, 9, 10, 11, 13, 17, 18, 20, 25, 26, 31, 33, 38, 39])
    for idx in (with_full, with_full[with_full != 3]):  # h == cap, then h < cap
        h = int(count[idx].max())
        assert h == cap or h < cap - 1
        # add passes B^T, a transposed view
        left = torch.randn(len(idx), h, p, generator=gen, dtype=dtype).transpose(1, 2)
        left = left * (torch.arange(h) < count[idx].unsqueeze(-1)).unsqueeze(1)
        got = _gathered_product(left, table, idx, count[idx])
        assert torch.equal(got, left @ table[idx, :h])


def test_fantasy_trace_equals_trace_of_fantasy_variance():
    gen = torch.Generator().manual_seed(9)
    nq, ng = 120, 100
    query = torch.rand(3, nq, 2, generator=gen, dtype=F64)
    gp = GPBelief.empty((3,), 30, nq, 2)
    x = torch.rand(3, 15, 2, generator=gen, dtype=F64)
    gp.add(PRIOR, query, x, torch.rand(3, 15, 2, generator=gen, dtype=F64),
           torch.ones(3, 15, dtype=torch.bool))
    pts = torch.rand(3, 6, 4, 2, generator=gen, dtype=F64)
    pmask = torch.rand(3, 6, 4, generator=gen) < 0.7
    mean = gp.mu[:, :ng, 0]
    full = gp.fantasy_variance(PRIOR, query, pts, pmask, n_query=ng)
    expected = interest_trace(mean.unsqueeze(1), full, 1.0, 0.4)
    got = gp.fantasy_trace(PRIOR, query, pts, pmask, mean, 1.0, 0.4, ng)
    assert float((got - expected).abs().max()) < 1e-9


def test_empty_belief_trace_is_900():
    grid = grid_points(30, F64, "cpu")
    assert grid.shape == (900, 2)
    gp = GPBelief.empty((2,), 4, 900, 2)
    tr = interest_trace(gp.mu[..., 0], gp.sigma2, 1.0, 0.4)
    assert torch.equal(tr, torch.full((2,), 900.0, dtype=F64))


def test_interest_trace_matches_definition():
    gen = torch.Generator().manual_seed(3)
    mean = torch.rand(3, 900, generator=gen, dtype=F64)
    var = torch.rand(3, 900, generator=gen, dtype=F64) * 0.2
    weight = torch.rand(3, 900, generator=gen, dtype=F64)
    tr = interest_trace(mean, var, 1.0, 0.4)
    trw = interest_trace(mean, var, 1.0, 0.4, weight)
    for i in range(3):
        region = mean[i] + var[i].sqrt() >= 0.4
        assert 0 < int(region.sum()) < 900
        assert math.isclose(float(tr[i]), float(var[i][region].sum()), rel_tol=1e-12)
        assert math.isclose(float(trw[i]), float((var[i] * weight[i])[region].sum()),
                            rel_tol=1e-12)


# ------------------------------------------------------------------ beliefs inside the env
def _field_err(mu, ref):
    """Mean error per channel relative to the field scale: fields are normalised to max 1
    and the prior std is 1, so the scale is max(1, max |mu_ref|). (Relative to max |mu_ref|
    alone is ill-posed: at the start the interest mean can be ~1e-6.)"""
    scale = ref.abs().amax(-2).clamp_min(1.0)
    return float(((mu.to(F64) - ref).abs().amax(-2) / scale).max())


def _check_env_beliefs(env, td, tol):
    cfg, st = env.config, env.episode
    g2 = cfg.n_grid
    m = cfg.n_agents
    for i in range(env.n_envs):
        rec = env.episode_record(i)
        n = len(rec["points"])
        known = rec["known"]
        assert known.shape == (m, n)
        # Every agent holds its own measurements (all agents measure the start node).
        own = rec["agent"].unsqueeze(0) == torch.arange(m).unsqueeze(1)
        assert torch.all(known[own])
        assert int(own[:, :m].sum()) == m and torch.all(rec["points"][:m] == rec["nodes"][0])
        for a in range(m):
            g = int(env.agent_belief_index[a])
            mu, var = dense_gp(rec["points"][known[a]], rec["values"][known[a]], rec["query"])
            b = st.belief[i, g]
            assert int(b.count) == int(known[a].sum())
            assert _field_err(b.mu, mu) < tol
            assert float((b.sigma2.to(F64) - var).abs().max()) < tol
        # The team belief (last) holds every measurement; the trace metric uses it.
        mu, var = dense_gp(rec["points"], rec["values"], rec["query"])
        team = st.belief[i, -1]
        assert int(team.count) == n
        assert _field_err(team.mu, mu) < tol
        assert float((team.sigma2.to(F64) - var).abs().max()) < tol
        trace = float(td["metrics", "trace"][i])
        ref = float(trace_in_region(mu[:g2, 0], var[:g2]))
        if cfg.dtype == "float64":
            assert math.isclose(trace, ref, rel_tol=1e-9, abs_tol=1e-9)
        else:  # cells within float32 error of the X_I threshold may flip
            sd = var[:g2].clamp_min(0).sqrt()
            edge = ((mu[:g2, 0] + sd) - 0.4).abs() < 1e-3
            assert abs(trace - ref) <= 1e-3 * g2 * tol + float(var[:g2][edge].sum()) + 1e-3


@pytest.mark.parametrize("dtype", ["float64", "float32"])
@pytest.mark.parametrize("comm_range", [math.inf, 0.3])
def test_env_beliefs_equal_dense_gp_on_held_measurements(comm_range, dtype):
    cfg = MAIPPConfig(budget=2.0, n_nodes=50, k_neighbors=8, comm_range=comm_range,
                      dtype=dtype)
    tol = 1e-9 if dtype == "float64" else 1e-3
    env = MAIPPEnv(cfg, batch_size=[3])
    env.set_seed(3)
    torch.manual_seed(0)
    td = env.reset()
    _check_env_beliefs(env, td, tol)
    steps = 0
    for _ in range(200):
        td = env.step(env.rand_action(td))["next"]
        steps += 1
        if steps % 2 == 0 or td["done"].all():
            _check_env_beliefs(env, td, tol)
        if td["done"].all():
            break
    assert td["done"].all() and steps > 10
    # Long episodes: many measurements were taken.
    assert int(env.episode.meas_count.min()) > 20
