"""Learned methods: decisions and GAE, masks, training, checkpoints, resume, Hydra errors."""

from __future__ import annotations

import copy
import hashlib
import json
import math
import os
import shutil
import subprocess
import sys
import warnings
from datetime import datetime, timedelta, timezone
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import TINY_TRAIN, compose_train
from tensordict import TensorDict

from maipp_bench import algos
from maipp_bench.algos.attention import AttentionConfig
from maipp_bench.algos.checkpoint import average_policies, load_core
from maipp_bench.algos.decisions import decision_batch
from maipp_bench.algos.modules import AttentionCore, decision_actor
from maipp_bench.envs import MAIPPConfig
from maipp_bench.protocol.protocol import load_protocol
from maipp_bench.protocol.runner import run_chunk


def _fake_batch(deciding, reward, done, value):
    """A collector-shaped batch [E, T] with only what decision_batch reads."""
    e, t, m = deciding.shape
    n, k = 5, 3
    agents = TensorDict(
        deciding=deciding, state_value=value.unsqueeze(-1).float(),
        action=torch.zeros(e, t, m, dtype=torch.int64), action_log_prob=torch.zeros(e, t, m),
        action_mask=torch.ones(e, t, m, k, dtype=torch.bool),
        hidden=torch.zeros(e, t, m, 2, 4),
        observation=TensorDict(
            node_features=torch.zeros(e, t, m, n, 7), current_node=torch.zeros(e, t, m).long(),
            budget=torch.zeros(e, t, m, 1), neighbors=torch.zeros(e, t, m, k).long(),
            batch_size=[e, t, m]),
        batch_size=[e, t, m])
    nxt = TensorDict(done=done.unsqueeze(-1),
                     agents=TensorDict(reward=reward.unsqueeze(-1), batch_size=[e, t, m]),
                     batch_size=[e, t])
    return TensorDict(agents=agents, next=nxt, node_encoding=torch.zeros(e, t, n, 2),
                      state=torch.zeros(e, t, n, 8), batch_size=[e, t])


def _gae_reference(rewards, values, next_values, dones, terms, gamma, lmbda):
    adv, out = 0.0, []
    for r, v, nv, d, tm in reversed(list(zip(rewards, values, next_values, dones, terms))):
        delta = r + gamma * nv * (1 - tm) - v
        adv = delta + gamma * lmbda * (1 - d) * adv
        out.append(adv)
    return out[::-1]


def test_decision_batch_sums_spans_and_matches_reference_gae():
    gen = torch.Generator().manual_seed(0)
    e, t, m = 2, 12, 2
    deciding = torch.rand(e, t, m, generator=gen) < 0.4
    deciding[:, 0] = True  # every agent decides at the start
    done = torch.zeros(e, t, dtype=torch.bool)
    done[0, 6] = True  # env 0's episode ends at step 6, a new one starts at 7
    deciding[0, 7] = True
    reward = torch.randn(e, t, m, generator=gen)
    value = torch.randn(e, t, m, generator=gen) * deciding
    bootstrap = torch.randn(e, m, generator=gen)
    gamma, lmbda = 0.99, 0.9
    rows = decision_batch(_fake_batch(deciding, reward, done, value), bootstrap, gamma, lmbda)
    assert rows.shape[0] == int(deciding.sum())
    got = iter(zip(rows["reward"].squeeze(-1).tolist(), rows["advantage"].squeeze(-1).tolist()))
    for i in range(e):
        for a in range(m):
            ts = deciding[i, :, a].nonzero().squeeze(-1).tolist()
            spans, nexts, dones, terms, vals = [], [], [], [], []
            for n_, t0 in enumerate(ts):
                t1 = ts[n_ + 1] if n_ + 1 < len(ts) else t
                ends = [s for s in range(t0, t1) if done[i, s]]
                end = ends[0] if ends else t1 - 1
                spans.append(float(reward[i, t0:end + 1, a].sum()))
                over = bool(done[i, end])
                last = n_ + 1 == len(ts)
                nexts.append(0.0 if over else (float(bootstrap[i, a]) if last
                                               else float(value[i, t1, a])))
                dones.append(over or last)
                terms.append(over)
                vals.append(float(value[i, t0, a]))
            ref = _gae_reference(spans, vals, nexts, dones, terms, gamma, lmbda)
            for span, adv in zip(spans, ref):
                r, g = next(got)
                assert r == pytest.approx(span, abs=1e-5)
                assert g == pytest.approx(adv, abs=1e-5)


def test_sampled_and_greedy_actions_respect_masks():
    torch.manual_seed(0)
    core = AttentionCore("ours", AttentionConfig(n_features=6, embed_dim=32, heads=2,
                                                 ff_dim=64, pe_dim=4), 0.4)
    actor = decision_actor(core)
    b, n, k = 256, 20, 6
    mask = torch.rand(b, k) < 0.3
    mask[torch.arange(b), torch.randint(0, k, (b,))] = True
    rows = TensorDict(node_features=torch.rand(b, n, 7), node_encoding=torch.rand(b, n, 4),
                      current_node=torch.randint(0, n, (b,)), budget=torch.rand(b, 1),
                      neighbors=torch.randint(0, n, (b, k)), action_mask=mask,
                      hidden=torch.zeros(b, 2, 32), batch_size=[b])
    for _ in range(20):
        out = actor(rows.clone())
        assert mask.gather(1, out["action"].unsqueeze(-1)).all()
        assert torch.isfinite(out["action_log_prob"]).all()
    assert mask.gather(1, out["logits"].argmax(-1, keepdim=True)).all()


def test_training_runs_with_finite_losses_and_checkpoint_round_trip(tiny_checkpoint):
    state = torch.load(tiny_checkpoint, weights_only=False)
    assert state["update"] == 2 and len(state["curve"]) == 2
    for row in state["curve"]:
        for key in ("loss_objective", "loss_critic", "reward_per_decision"):
            assert np.isfinite(row[key]), key
    core, payload = load_core(tiny_checkpoint)
    # The saved network is the one the loss trained (its parameters, not a stale copy).
    trained = [v for k, v in payload["loss"].items() if k.startswith("actor_network_params")]
    for name, tensor in core.named_parameters():
        assert any(t.shape == tensor.shape and torch.equal(t, tensor) for t in trained), name
    # Training moved the weights away from their seeded initialisation.
    from maipp_bench.algos.ppo import build_learner

    torch.manual_seed(payload["config"]["seed"])
    fresh = build_learner(compose_train(*TINY_TRAIN).algo, payload["env"]["node_encoding_dim"],
                          payload["env"]["interest_threshold"]).core.state_dict()
    moved = [k for k, v in fresh.items() if not torch.equal(v, payload["core"][k])]
    assert len(moved) > len(fresh) // 2


def test_bf16_precision_autocasts_training_only(tmp_path, monkeypatch):
    """algo.precision=bf16: the networks' products in bfloat16 while training (outputs
    float32, masks kept, close to float32), but the held-out evaluation, the checkpoint
    and every later load play float32; a bad precision is a clear error."""
    from maipp_bench.algos.modules import full_precision
    from maipp_bench.algos.ppo import build_learner
    from maipp_bench.train import train

    torch.manual_seed(0)
    algo = compose_train(*TINY_TRAIN, "algo.precision=bf16").algo
    learner = build_learner(algo, 4, 0.4)
    assert learner.core.autocast == torch.bfloat16
    b, n, k = 64, 20, 6
    mask = torch.rand(b, k) < 0.5
    mask[:, 0] = True
    rows = (torch.rand(b, n, 7, dtype=torch.float64), torch.rand(b, n, 4),
            torch.randint(0, n, (b,)), torch.rand(b, 1), torch.randint(0, n, (b, k)), mask,
            torch.zeros(b, 2, 32))
    with torch.no_grad():
        logits, value, hidden = learner.core(*rows)
        with full_precision(learner.core):
            ref_logits, ref_value, ref_hidden = learner.core(*rows)
    assert learner.core.autocast == torch.bfloat16  # restored after the block
    assert logits.dtype == value.dtype == hidden.dtype == torch.float32
    assert torch.isneginf(logits[~mask]).all() and torch.isfinite(logits[mask]).all()
    rel = (logits[mask] - ref_logits[mask]).norm() / ref_logits[mask].norm()
    assert 0 < rel < 5e-2  # bf16 rounding moved the logits, a little
    assert ((value - ref_value).norm() / ref_value.norm()) < 5e-2
    float32 = build_learner(compose_train(*TINY_TRAIN).algo, 4, 0.4).core
    float32.load_state_dict(learner.core.state_dict())
    with torch.no_grad():
        assert torch.equal(float32(*rows)[0], ref_logits)  # full precision: float32's bits

    import maipp_bench.train as train_mod

    seen = []
    heldout = train_mod.heldout_rows

    def spy(core, *args, **kwargs):  # what training's held-out evaluation plays with
        seen.append(core.autocast)
        return heldout(core, *args, **kwargs)

    monkeypatch.setattr(train_mod, "heldout_rows", spy)
    run = [*TINY_TRAIN, "algo.precision=bf16", "total_updates=1", "eval_every=1",
           "eval_episodes=2", "eval_budget=1.0"]
    ckpt = train(compose_train(*run), tmp_path / "bf16")
    assert seen == [None]  # float32, though the run trains in bf16
    state = torch.load(ckpt, weights_only=False)
    assert state["config"]["algo"]["precision"] == "bf16"
    for key in ("loss_objective", "loss_critic", "eval/trace"):
        assert np.isfinite(state["curve"][-1][key]), key
    assert load_core(ckpt)[0].autocast is None  # evaluation loads play float32
    with pytest.raises(ValueError, match=r"algo.precision='fp8'; valid: \['bf16', 'float32'\]"):
        build_learner(compose_train(*TINY_TRAIN, "algo.precision=fp8").algo, 4, 0.4)


@pytest.mark.parametrize("precision", ["float32", "bf16"])
def test_loss_recomputes_the_collectors_log_probs(precision):
    """PPO's first ratio is 1 to float32 rounding in either precision: the loss (train
    mode, shuffled minibatches) recomputes the log-probability the collector stored for
    every decision row (each row is computed alone, so bf16 rounds both alike), though
    bf16's are far from float32's (benchmarks/logprob_mismatch.py, the paper's network)."""
    from maipp_bench.algos.modules import LOG_PROB_KEY, full_precision
    from maipp_bench.algos.ppo import build_learner
    from maipp_bench.train import collected_decisions, make_collection

    cfg = compose_train(*TINY_TRAIN, f"algo.precision={precision}")
    env_cfg = MAIPPConfig.from_dict(dict(cfg.env))
    torch.manual_seed(0)
    learner = build_learner(cfg.algo, env_cfg.node_encoding_dim, env_cfg.interest_threshold)
    env, collector, _ = make_collection(cfg, env_cfg, learner)
    env.set_seed(0)
    learner.core.eval()
    rows = collected_decisions(learner, next(iter(collector)), cfg.algo)
    collector.shutdown()
    stored = rows.get(LOG_PROB_KEY)
    assert rows.numel() > cfg.algo.minibatch  # more than one minibatch, in another order
    assert (learner.action_log_prob(rows, cfg.algo.minibatch) - stored).abs().max() < 1e-5
    with torch.no_grad():  # and the loss itself reads them as its behaviour log-probs
        first = learner.loss(rows[:cfg.algo.minibatch].clone())
    assert abs(float(first["kl_approx"])) < 1e-6 and float(first["clip_fraction"]) == 0
    with full_precision(learner.core):
        exact = learner.action_log_prob(rows, cfg.algo.minibatch)
    assert ((exact - stored).abs().max() > 1e-3) == (precision == "bf16")


@pytest.mark.parametrize("algo, nets", [("ours", ["AttentionCore"]),
                                         ("mappo", ["AttentionCore", "StateCritic"])])
def test_precision_modules_are_every_network_with_a_precision(algo, nets):
    """A benchmark that switches precision after build must reach MAPPO's critic too."""
    from maipp_bench.algos.ppo import build_learner

    learner = build_learner(compose_train(*TINY_TRAIN, f"algo={algo}",
                                          "algo.precision=bf16").algo, 4, 0.4)
    mods = learner.precision_modules()
    assert [type(m).__name__ for m in mods] == nets
    assert all(m.autocast == torch.bfloat16 for m in mods)


def assert_same_training(a: Path, b: Path) -> None:
    """Two checkpoints hold the same weights and the same curve (wall time aside)."""
    a, b = torch.load(a, weights_only=False), torch.load(b, weights_only=False)
    for name, tensor in a["core"].items():
        assert torch.equal(tensor, b["core"][name]), name
    strip = lambda curve: [{k: v for k, v in r.items() if k != "wall_s"} for r in curve]  # noqa: E731
    # as JSON, so that NaN (an update in which no episode ended) equals NaN
    assert json.dumps(strip(a["curve"])) == json.dumps(strip(b["curve"]))


@pytest.mark.parametrize("intents", [0, 2])
def test_killed_and_resumed_training_continues_the_same_curve(tmp_path, intents):
    from maipp_bench.train import train

    run = [*TINY_TRAIN, "checkpoint_every=1", f"algo.intent_rollouts={intents}",
           "algo.intent_depth=2"]  # intents: the rollouts' noise replays too
    full = train(compose_train(*run, "total_updates=3"), tmp_path / "full")
    part = train(compose_train(*run, "total_updates=2"), tmp_path / "part")
    resumed = train(compose_train(*run, "total_updates=3", f"resume={part}"),
                    tmp_path / "elsewhere")
    assert resumed == part  # the run continues in its own folder
    assert_same_training(full, resumed)
    lines = (part.parent / "curve.jsonl").read_text().splitlines()
    assert len(lines) == 3


def test_reset_every_runs_episodes_on_between_fresh_starts(tmp_path):
    """With reset_every=N the envs start fresh episodes every N updates and run on in
    between: short batches then still reach episodes' ends (more of them end than when
    every update restarts them), the first update is the default's, a run resumed from a
    checkpoint (which falls on a fresh start) continues the same curve, and cut episodes
    get a warning."""
    from maipp_bench.train import train

    short = [*TINY_TRAIN, "steps_per_batch=6", "checkpoint_every=2"]
    with pytest.warns(UserWarning, match="most episodes were cut before their end"):
        every = train(compose_train(*short, "total_updates=4"), tmp_path / "every")
    run = [*short, "reset_every=2"]
    full = train(compose_train(*run, "total_updates=4"), tmp_path / "full")
    curve_every = torch.load(every, weights_only=False)["curve"]
    curve_on = torch.load(full, weights_only=False)["curve"]
    assert curve_on[0] | {"wall_s": 0} == curve_every[0] | {"wall_s": 0}
    assert curve_on[1]["reward_per_decision"] != curve_every[1]["reward_per_decision"]
    assert curve_on[-1]["episodes"] > curve_every[-1]["episodes"]
    part = train(compose_train(*run, "total_updates=2"), tmp_path / "part")
    resumed = train(compose_train(*run, "total_updates=4", f"resume={part}"), tmp_path / "x")
    assert_same_training(full, resumed)


def test_reset_intervals_count_from_where_a_resumed_run_starts(tmp_path):
    """A run stopped between fresh starts (here by total_updates=3 with reset_every=2; in
    practice by max_minutes) resumes with fresh episodes and counts its intervals and
    checkpoints from there: its first interval is a whole one (no cut episodes), and a kill
    and resume after that continues the same curve as the uninterrupted resume."""
    import shutil
    import warnings

    from maipp_bench.train import train

    run = [*TINY_TRAIN, "steps_per_batch=6", "checkpoint_every=2", "reset_every=2"]
    stopped = train(compose_train(*run, "total_updates=3"), tmp_path / "a").parent
    shutil.copytree(stopped, tmp_path / "b")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        full = train(compose_train(*run, "total_updates=7", f"resume={stopped / 'checkpoint.pt'}"),
                     tmp_path / "x")
    assert not [w for w in caught if "most episodes were cut" in str(w.message)]
    killed = tmp_path / "b" / "checkpoint.pt"  # its next checkpoint: update 3 + 2
    assert train(compose_train(*run, "total_updates=5", f"resume={killed}"), tmp_path / "y") \
        == killed
    assert torch.load(killed, weights_only=False)["update"] == 5
    assert_same_training(full, train(compose_train(*run, "total_updates=7", f"resume={killed}"),
                                     tmp_path / "z"))


@pytest.mark.parametrize("fields, match", [
    (["reset_every=0"], "reset_every=0: must be >= 1"),
    (["reset_every=2", "checkpoint_every=3"],
     "checkpoint_every=3 must be a multiple of reset_every=2"),
])
def test_bad_reset_every_is_a_clear_error(tmp_path, fields, match):
    from maipp_bench.train import train

    with pytest.raises(ValueError, match=match):
        train(compose_train(*TINY_TRAIN, *fields), tmp_path)
    assert not (tmp_path / "checkpoint.pt").exists()  # refused before training


def test_resume_alone_continues_the_run_as_it_was_started(tmp_path, capsys):
    """``resume=<path>`` with none of the first command's settings keeps them (envs, seed,
    intents, the tiny world), so the curve is the uninterrupted one; a setting typed again
    wins; another algo is an error. (Once, a resume took untyped fields from the defaults:
    a GPU run of 128 envs with intents went on with 8 envs and none.)"""
    from maipp_bench.train import resumed_config, train

    run = [*TINY_TRAIN, "checkpoint_every=1", "seed=3", "algo.intent_rollouts=2",
           "algo.intent_depth=2"]
    full = train(compose_train(*run, "total_updates=2"), tmp_path / "full")
    part = train(compose_train(*run, "total_updates=1"), tmp_path / "part")
    typed = [f"resume={part}", "total_updates=2", "progress=false"]
    cfg = resumed_config(compose_train(*typed), typed)
    assert "n_envs=3 (this command: 8)" in capsys.readouterr().out
    assert (cfg.seed, cfg.n_envs, cfg.algo.intent_rollouts, cfg.env.n_nodes) == (3, 3, 2, 30)
    assert_same_training(full, train(cfg, tmp_path / "elsewhere"))
    again = resumed_config(compose_train(*typed, "n_envs=2"), [*typed, "n_envs=2"])
    assert (again.n_envs, again.seed) == (2, 3)
    logs = resumed_config(compose_train(*typed, "logger=tensorboard"),
                          [*typed, "logger=tensorboard"])  # a typed logger switches
    assert (logs.logger.backend, logs.n_envs) == ("tensorboard", 3)
    world = resumed_config(compose_train("env=risk_aware", *typed), ["env=risk_aware", *typed])
    assert world.env.n_nodes == 30  # env= names the group; the run's world stays
    here = resumed_config(compose_train(f"resume={part}"), [f"resume={part}"])
    assert here.progress is True  # saved false: where it runs is this command's
    with pytest.raises(ValueError, match="continues a run of algo 'ours', not algo=catnipp"):
        resumed_config(compose_train("algo=catnipp", *typed), ["algo=catnipp", *typed])
    with pytest.raises(ValueError, match="type a higher max_minutes"):  # not one update more
        train(resumed_config(compose_train(*typed, "total_updates=5", "max_minutes=1e-6"),
                             [*typed, "total_updates=5", "max_minutes=1e-6"]), tmp_path / "y")
    cli = subprocess.run([sys.executable, "-m", "maipp_bench.train", f"resume={part}",
                          "total_updates=3", "progress=false"],
                         capture_output=True, text=True, timeout=300)  # main()'s wiring
    assert cli.returncode == 0, cli.stderr
    assert "n_envs=3 (this command: 8)" in cli.stdout
    assert torch.load(part, weights_only=False)["config"]["n_envs"] == 3
    # A run saved before held-out set 2 existed goes on evaluating on set 1, unless typed.
    assert cfg.eval_heldout == 2
    old = torch.load(part, weights_only=False)
    del old["config"]["eval_heldout"]
    torch.save(old, tmp_path / "old.pt")
    typed = [f"resume={tmp_path / 'old.pt'}"]
    assert resumed_config(compose_train(*typed), typed).eval_heldout == 1
    assert "eval_heldout=1 (saved before the field existed)" in capsys.readouterr().out
    assert resumed_config(compose_train(*typed, "eval_heldout=2"),
                          [*typed, "eval_heldout=2"]).eval_heldout == 2


@pytest.mark.parametrize("mode", ["greedy", "ti", "ti_float64"])
def test_learned_policy_plays_valid_reproducible_episodes(tiny_checkpoint, mode):
    cfg = MAIPPConfig(n_agents=2, budget=1.0, n_nodes=40, k_neighbors=8)
    params = {"mode": mode[:2] if mode.startswith("ti") else mode, "rollouts": 3, "depth": 2}
    if mode == "ti_float64":
        params["fantasy_dtype"] = "float64"
    spec = algos.MethodSpec(name=f"tiny_{mode}", policy="attention", models_risk=True,
                            learned=True, params=params)
    rows = run_chunk(spec, cfg, [11, 12], trial_seed=5, checkpoint=str(tiny_checkpoint))
    again = run_chunk(spec, cfg, [11, 12], trial_seed=5, checkpoint=str(tiny_checkpoint))
    strip = lambda rs: [{k: v for k, v in r.items() if k != "planning_s"} for r in rs]  # noqa: E731
    assert strip(rows) == strip(again)
    for r in rows:
        assert r["distance"] <= cfg.team_budget + 1e-9 and 0 < r["trace"] <= 900


@pytest.mark.parametrize("intents", [True, False])
def test_ti_broadcasts_intents_unless_told_not_to(tiny_checkpoint, intents):
    from maipp_bench.envs import MAIPPEnv

    env = MAIPPEnv(MAIPPConfig(n_agents=2, budget=1.0, n_nodes=40, k_neighbors=8),
                   batch_size=[2])
    policy = algos.POLICIES["attention"](env, torch.tensor([3, 4]), mode="ti", rollouts=3,
                                         depth=2, intents=intents,
                                         checkpoint=str(tiny_checkpoint))
    td = env.reset()
    for _ in range(6):
        td = env.step(policy(td))["next"]
    assert bool(env.episode.intent_valid.any()) == intents


def test_ti_fantasies_in_float64_match_float32_to_its_precision(tiny_checkpoint, monkeypatch):
    """fantasy_dtype=float64 (ours_ti_float64) runs the same rollouts as float32 with the
    same noise: the same sampled slots, Tr(P) equal to float32's rounding; a bad dtype, or
    one without TI, is refused."""
    from maipp_bench.algos import learned
    from maipp_bench.envs import MAIPPEnv

    seen = {}
    real = learned.fantasy_rollouts

    def spy(*args):
        out = real(*args)
        seen.setdefault(args[-1], []).append(out)
        return out

    monkeypatch.setattr(learned, "fantasy_rollouts", spy)
    cfg = MAIPPConfig(n_agents=2, budget=1.0, n_nodes=40, k_neighbors=8)
    for dtype in ("float32", "float64"):
        env = MAIPPEnv(cfg, batch_size=[2])
        policy = algos.POLICIES["attention"](env, torch.tensor([3, 4]), mode="ti", rollouts=4,
                                             depth=3, fantasy_dtype=dtype,
                                             checkpoint=str(tiny_checkpoint))
        td = env.reset(TensorDict(instance_seed=torch.tensor([7, 8]),
                                  trial_seed=torch.tensor([1, 2]), batch_size=[2]))
        policy(td)  # the first decisions, from the same state
    (f32,), (f64,) = seen[torch.float32], seen[torch.float64]
    assert torch.equal(f32.first, f64.first) and torch.equal(f32.nodes, f64.nodes)
    assert f64.trace.dtype == torch.float64 and not torch.equal(f32.trace, f64.trace)
    torch.testing.assert_close(f32.trace, f64.trace, rtol=1e-5, atol=1e-5)
    env = MAIPPEnv(cfg, batch_size=[1])
    for bad in ({"mode": "ti", "fantasy_dtype": "float16"},
                {"mode": "greedy", "fantasy_dtype": "float64"}):
        with pytest.raises(ValueError, match="fantasy_dtype"):
            algos.POLICIES["attention"](env, torch.tensor([0]), checkpoint=str(tiny_checkpoint),
                                        **bad)


def test_ti_cpu_rounding_plays_both_dtypes_under_both_kernel_sets(tmp_path):
    """benchmarks/ti_cpu_rounding.py (docs/protocol.md, "Another CPU"): four children, the
    report's comparisons; a setting the suite does not have fails before any child."""
    script = Path(__file__).parents[1] / "benchmarks" / "ti_cpu_rounding.py"
    out = tmp_path / "r.json"
    proc = subprocess.run([sys.executable, str(script), "--suite", "smoke", "--method",
                           "ours_ti", "--setting", "budget=1.0", "--episodes", "1", "--out",
                           str(out)], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    report = json.loads(out.read_text())
    assert set(report["planning_s"]) == {f"{d}/{k}" for d in ("float32", "float64")
                                         for k in ("default", "cpu-independent")}
    assert report["float32_differs_from_board"] is None  # smoke has no committed board
    assert all(isinstance(v, list) for v in report["differ_between_kernels"].values())
    bad = subprocess.run([sys.executable, str(script), "--suite", "comm", "--setting",
                          "budget=5.0"], capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "is not a setting of comm" in bad.stderr



def test_ti_cpu_rounding_finds_the_first_decision_that_splits(monkeypatch):
    """--trace-instance's comparison: the first TI decision whose chosen slot differs
    (the rollout with the least Tr(P) of each agent row), with the drift before it."""
    monkeypatch.syspath_prepend(str(Path(__file__).parents[1] / "benchmarks"))
    from ti_cpu_rounding import first_split

    same = {"first": [[3, 4], [1, 2]], "trace": [[5.0, 6.0], [7.0, 8.0]]}
    drifted = {"first": [[3, 4], [1, 2]], "trace": [[5.0, 6.0], [7.0, 8.000008]]}
    flipped = {"first": [[3, 4], [1, 2]], "trace": [[5.0, 6.0], [7.2, 7.1]]}
    assert first_split([same, same], [same, drifted]) is None
    split = first_split([same, drifted, same], [same, drifted, flipped])
    assert split == {"decision": 2, "agent_row": 1, "drift_before": 0.0,
                     "first": [1, 2], "trace": [[7.0, 8.0], [7.2, 7.1]]}
    split = first_split([drifted, same], [same, flipped])
    assert split["decision"] == 1 and split["drift_before"] == pytest.approx(1e-6)


def test_distinct_rows_finds_one_row_per_value():
    from maipp_bench.algos.rollouts import distinct_rows

    key = torch.tensor([[0, 2], [1, 2], [0, 2], [0, 1], [1, 2]])
    keep, back = distinct_rows(key)
    assert torch.equal(key[keep][back], key)
    assert len(keep) == 3 and sorted(keep.tolist()) == [0, 1, 3]  # first of each value
    keep, back = distinct_rows(torch.zeros(0, 2, dtype=torch.long))
    assert keep.numel() == 0 and back.numel() == 0


def test_ti_runs_the_network_once_per_distinct_path_with_the_same_bits(tiny_checkpoint,
                                                                         monkeypatch):
    """16 rollouts over at most 4 slots must repeat paths: the network then runs on fewer
    rows, and every action and broadcast intent is bit-identical to running it on all."""
    from maipp_bench.algos import rollouts as ro
    from maipp_bench.envs import MAIPPEnv

    def play():
        env = MAIPPEnv(MAIPPConfig(n_agents=2, budget=1.5, n_nodes=30, k_neighbors=4),
                       batch_size=[3])
        policy = algos.POLICIES["attention"](env, torch.tensor([3, 4, 5]), mode="ti",
                                             rollouts=16, depth=3,
                                             checkpoint=str(tiny_checkpoint))
        rows, real = [], policy.core.forward
        monkeypatch.setattr(policy.core, "forward", lambda *a: rows.append(
            a[0].shape[0]) or real(*a))
        td, out = env.reset(), []
        while not bool(td.get("done").all()):
            td = policy(td)
            out.append(td.select(("agents", "action"), ("agents", "intent")).clone())
            td = env.step(td)["next"]
        return torch.stack(out), sum(rows)

    distinct, rows_distinct = play()
    with ro.path_merging(False):
        every, rows_every = play()
    assert (distinct == every).all()
    assert rows_distinct < 0.7 * rows_every


def test_ti_safety_layer_picks_the_best_safe_rollout():
    from maipp_bench.algos.rollouts import Rollouts

    first = torch.tensor([[0, 1, 2], [1, 1, 0], [2, 2, 2]])
    trace = torch.tensor([[1.0, 2.0, 3.0], [1.0, 2.0, 3.0], [3.0, 2.0, 1.0]],
                         dtype=torch.float64)
    unsafe = torch.tensor([[True, False, False], [False, True, False], [True, True, True]])
    ro = Rollouts(first=first, trace=trace, nodes=torch.zeros(3, 3, 2),
                  valid=torch.ones(3, 3, dtype=torch.bool))
    assert ro.best_first().tolist() == [0, 1, 2]
    ro.reject(unsafe)
    # Row 0: slot 0 is unsafe, the best safe rollout starts at 1; row 1: only slot 0 is
    # safe; row 2: every rollout starts unsafe, TI's choice stands.
    assert ro.best_first().tolist() == [1, 0, 2]


@pytest.mark.parametrize("layer", [True, False])
def test_ti_safety_layer_moves_under_its_buffer_whenever_a_rollout_does(
        tiny_checkpoint, monkeypatch, layer):
    """At every decision, with ``mu + 0.5 sd > 0.3`` read from the env's belief here: the
    move is under the buffer whenever one of the sampled rollouts starts under it."""
    from maipp_bench.algos import learned
    from maipp_bench.envs import MAIPPEnv

    sampled = []
    real = learned.fantasy_rollouts
    monkeypatch.setattr(learned, "fantasy_rollouts", lambda *a: sampled.append(
        real(*a)) or sampled[-1])
    env = MAIPPEnv(MAIPPConfig(n_agents=2, budget=2.0, n_nodes=40, k_neighbors=8),
                   batch_size=[3])
    params = {"safe_risk": 0.3, "safe_beta": 0.5} if layer else {}
    policy = algos.POLICIES["attention"](env, torch.tensor([3, 4, 5]), mode="ti", rollouts=3,
                                         depth=2, checkpoint=str(tiny_checkpoint), **params)
    td, g2 = env.reset(), env.config.n_grid
    could = over = 0
    while not bool(td.get("done").all()):
        st = env.episode
        first = st.deciding.nonzero().tolist()
        td = policy(td)
        starts = sampled.pop().first.tolist() if first else []
        for (e, a), slots in zip(first, starts):
            nbr = st.roadmap.neighbors[e, st.cur[e, a]]
            g = env.agent_belief_index[a]
            mu = st.belief.mu[e, g, g2 + nbr, 1]
            sd = st.belief.sigma2[e, g, g2 + nbr].clamp_min(0).sqrt()
            unsafe = (mu + 0.5 * sd > 0.3).tolist()
            if not all(unsafe[s] for s in slots):
                could += 1
                over += unsafe[int(td.get(("agents", "action"))[e, a])]
        td = env.step(td)["next"]
    assert could > 20
    assert (over == 0) if layer else (over > 0)  # without the layer TI does move over it


def test_missing_checkpoint_and_bad_mode_are_clear_errors(tiny_checkpoint):
    from maipp_bench.envs import MAIPPEnv

    env = MAIPPEnv(MAIPPConfig(n_nodes=30, k_neighbors=6), batch_size=[1])
    seeds = torch.zeros(1, dtype=torch.int64)
    with pytest.raises(FileNotFoundError, match="maipp_bench.train"):
        algos.POLICIES["attention"](env, seeds, checkpoint="/nonexistent/x.pt")
    with pytest.raises(ValueError, match="mode"):
        algos.POLICIES["attention"](env, seeds, checkpoint=str(tiny_checkpoint), mode="beam")
    with pytest.raises(ValueError, match="needs mode 'ti'"):
        algos.POLICIES["attention"](env, seeds, checkpoint=str(tiny_checkpoint), safe_risk=0.5)
    with pytest.raises(ValueError, match="safe_beta"):
        algos.POLICIES["attention"](env, seeds, checkpoint=str(tiny_checkpoint), mode="ti",
                                    safe_risk=0.5, safe_beta=-1.0)
    with pytest.raises(ValueError, match="read only with safe_risk"):
        algos.POLICIES["attention"](env, seeds, checkpoint=str(tiny_checkpoint), mode="ti",
                                    safe_beta=0.5)


@pytest.mark.parametrize("override, message", [
    ("algo=nonexistent", "Could not find 'algo/nonexistent'"),
    ("n_envs=many", "n_envs"),
    ("algo.lr=fast", "algo.lr"),
    ("env.budget=-1", "MAIPPConfig.budget"),
    ("device=gpu", "device='gpu' is invalid"),
    ("algo.precision=fp8", "algo.precision='fp8'; valid: ['bf16', 'float32']"),
])
def test_bad_overrides_get_clear_errors(override, message, tmp_path):
    proc = subprocess.run(
        [sys.executable, "-m", "maipp_bench.train", override, "env=tiny", "total_updates=1",
         f"hydra.run.dir={tmp_path}"], capture_output=True, text=True, timeout=300)
    assert proc.returncode != 0
    assert message in proc.stderr


@pytest.mark.parametrize("script, args, message", [
    *[("train_2h.sh", m, "stage minutes must be positive numbers")
      for m in (["1", "-2", "3"], ["0", "2", "3"], ["1", "2", "abc"],
                ["1", "-2", "3", "3e-5"])],  # a good LR3 passes its own check
    *[("train_2h.sh", ["1", "2", "3", lr], "LR3 must be a positive number")
      for lr in ("0", "0e-5", "-1e-4", "fast")],
    *[("train_gpu.sh", m, "MINUTES must be a positive number") for m in (["0"], ["-1"], ["x"])],
    *[("train_gpu.sh", ["6", n], "N_ENVS must be a positive integer") for n in ("0", "1.5")],
    *[("train_gpu.sh", ["6", n], "N_ENVS must divide 2560 frames per update into steps "
       "that divide 160") for n in ("48", "5120")],
    ("train_gpu.sh", "x", "SEED must be an integer")])
def test_training_scripts_reject_bad_arguments_before_training(script, args, message,
                                                                tmp_path):
    """benchmarks/train_2h.sh and train_gpu.sh check their numbers first: a bad minute used
    to reach bash arithmetic, which skipped a stage with only a printed error."""
    out = tmp_path / "run"
    seed, args = (args, []) if isinstance(args, str) else ("0", args)
    proc = subprocess.run(["bash", str(Path(__file__).parents[1] / "benchmarks" / script),
                           str(out), seed, *args], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    assert message in proc.stderr
    assert not out.exists()


def test_train_gpu_keeps_the_frames_per_update_and_the_steps_between_fresh_starts(tmp_path):
    """train_gpu.sh at any width collects 2,560 frames an update and starts fresh episodes
    every 160 env steps, as 16 envs x 160 steps do (a CPU smoke run of the tiny task)."""
    script = Path(__file__).parents[1] / "benchmarks" / "train_gpu.sh"
    proc = subprocess.run(["bash", str(script), str(tmp_path), "0", "0.001", "64",
                           "device=cpu", "env=tiny", *TINY_TRAIN[5:], "algo.epochs=1",
                           "algo.intent_rollouts=2", "algo.intent_depth=2"],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    cfg = torch.load(tmp_path / "run" / "checkpoint.pt", weights_only=False)["config"]
    assert (cfg["n_envs"], cfg["steps_per_batch"], cfg["reset_every"],
            cfg["checkpoint_every"]) == (64, 40, 4, 4)
    assert (tmp_path / "policy.pt").exists()


@pytest.mark.parametrize(("variable", "value", "message"), [
    ("SELECT", "yes", "SELECT must be 0 or 1"), ("FINAL", "yes", "FINAL must be 0 or 1"),
    ("FINAL_EPISODES", "1", "must be integers >= 2, got '1'"),
    ("SELECT_EPISODES", "many", "must be integers >= 2, got 'many'"),
    ("SELECT_EPISODES", "160 64", "one count or one per budget of SELECT_BUDGETS ('2')"),
    ("SELECT_BUDGETS", "2 0", "SELECT_BUDGETS must be positive numbers, got '0'"),
    ("SELECT_BUDGETS", "2 2.0", "SELECT_BUDGETS must name each budget once, got '2 2.0'"),
    ("SELECT_BUDGETS", " ", "SELECT_BUDGETS must name each budget once"),
    ("FINAL_BUDGETS", "4 x", "FINAL_BUDGETS must be positive numbers, got 'x'"),
    ("FINAL_BUDGETS", "4 5 4.0", "FINAL_BUDGETS must name each budget once, got '4 5 4.0'"),
    ("HELDOUT_SET", "3", "HELDOUT_SET must be 1 or 2, got '3'"),
    ("POP", "3", "POP must be 1 or 2, got '3'"), ("POP", "2", "POP=2 needs SELECT=1"),
    ("UPDATES", "1 2", "UPDATES must be three positive integers (stages 1, 2 and 3), got '1 2'"),
    ("UPDATES", "1 0 5", "UPDATES must be three positive integers"),
    ("STAGE3", "2", "STAGE3 must be 0 or 1, got '2'"),
    ("WIDE", "3", "WIDE must be a positive integer that divides 160 (e.g. 1, 2, 4, 8), got '3'"),
    ("WIDE", "0", "WIDE must be a positive integer that divides 160"),
    ("STAGE3", "0", "STAGE3=0 needs SELECT=1"),
    ("DEADLINE", "soon", "DEADLINE must be minutes >= 0 (0: none), got 'soon'"),
    ("DEADLINE", "-5", "DEADLINE must be minutes >= 0"),
    ("FINAL", "1", "FINAL=1 under DEADLINE estimates the final choice's minutes from SELECT=1")])
def test_train_2h_rejects_a_bad_switch_before_training(tmp_path, variable, value, message):
    out = tmp_path / "run"
    proc = subprocess.run(["bash", str(Path(__file__).parents[1] / "benchmarks" / "train_2h.sh"),
                           str(out)], capture_output=True, text=True, timeout=60,
                          env={**os.environ, variable: value})
    assert proc.returncode == 2
    assert message in proc.stderr
    assert not out.exists()


@pytest.mark.parametrize(("env", "args", "message"), [
    ({"FINAL": "1"}, [], "STAGE3=0 needs SELECT=1 (its choice is the policy) and no FINAL=1"),
    ({}, ["1", "2", "3"], "STAGE3=0 trains no stage 3: M3 and LR3 are not taken"),
    ({"UPDATES": "1 2 3"}, [], "UPDATES must be two positive integers (stages 1 and 2), got"),
    ({"UPDATES": "1 x"}, [], "UPDATES must be two positive integers"),
    ({"DEADLINE": "100"}, [], "DEADLINE trims stage 3's minutes: not with STAGE3=0 or UPDATES")])
def test_train_2h_without_stage3_rejects_what_it_cannot_use(tmp_path, env, args, message):
    out = tmp_path / "run"
    proc = subprocess.run(["bash", str(Path(__file__).parents[1] / "benchmarks" / "train_2h.sh"),
                           str(out), "0", *args], capture_output=True, text=True, timeout=60,
                          env={**os.environ, "SELECT": "1", "STAGE3": "0", **env})
    assert proc.returncode == 2
    assert message in proc.stderr
    assert not out.exists()


@pytest.mark.parametrize("body", ["", "raise ImportError('gone')"],
                         ids=["another_folder", "not_importable"])
def test_train_2h_refuses_a_maipp_bench_other_than_its_checkout(tmp_path, body):
    """The held-out choices run benchmarks/*.py, which import the installed maipp_bench:
    one from another folder (or none) is refused before training, not after stage 2."""
    other = tmp_path / "elsewhere"
    (other / "maipp_bench").mkdir(parents=True)
    (other / "maipp_bench" / "__init__.py").write_text(body)
    out = tmp_path / "run"
    proc = subprocess.run(["bash", str(Path(__file__).parents[1] / "benchmarks" / "train_2h.sh"),
                           str(out)], capture_output=True, text=True, timeout=60,
                          env={**os.environ, "PYTHONPATH": str(other)})
    assert proc.returncode == 2
    shown = "nowhere" if body else str(other)  # an import error shows no folder
    assert f"import maipp_bench from '{shown}', not from this checkout" in proc.stderr
    assert not out.exists()


@pytest.mark.parametrize("pop", ["1", "2"])
def test_train_2h_runs_its_stages_and_the_choices_end_to_end(tmp_path, pop):
    """benchmarks/train_2h.sh with SELECT=1 and FINAL=1 on the tiny task (OVERRIDES, typed
    after the script's own fields): three stages, the held-out choice of the start, the
    averaged policy file whose card names the averaged snapshots, the chosen start and every
    stage's command, and the final choice between the start and that file. With POP=2 two
    members train stages 1-2 side by side and the start is chosen among both."""
    out = tmp_path / "run"
    tiny = [*TINY_TRAIN, "algo.intent_rollouts=2", "algo.intent_depth=2"]
    # stage limits in updates: minute limits made fewer updates on a busy box (0.5 minutes
    # of stage 3 once gave no snapshot to average beside two other test processes)
    proc = subprocess.run(
        ["bash", str(Path(__file__).parents[1] / "benchmarks" / "train_2h.sh"), str(out), "3"],
        capture_output=True, text=True, timeout=600,
        env={**os.environ, "SELECT": "1", "SELECT_BUDGETS": "5 2 4", "SELECT_EPISODES": "2 3 2",
             "FINAL": "1", "FINAL_EPISODES": "2", "OVERRIDES": " ".join(tiny),
             "UPDATES": "1 2 10", "POP": pop})
    assert proc.returncode == 0, proc.stderr[-3000:]
    stamps = [line.split()[0] for line in (out / "wall.txt").read_text().splitlines()]
    members = int(pop)
    assert sorted(stamps[1:1 + 2 * members]) == ["stage1"] * members + ["stage2"] * members
    assert stamps[:1] + stamps[1 + 2 * members:] == ["start", "selected", "final", "end"]
    choice = json.loads((out / "select.json").read_text())
    runs = {str(Path(c["path"]).parent).removesuffix("/snapshots") for c in choice["candidates"]}
    assert runs == {str(out / "stage2"), *[str(out / "m1" / "stage2")] * (members - 1)}
    if members == 2:  # each member trained its own seed
        seeds = {torch.load(out / d / "checkpoint.pt", weights_only=False)["config"]["seed"]
                 for d in ("stage1", "m1/stage1")}
        assert seeds == {3, 1003}
    assert choice["budget"] == [2.0, 4.0, 5.0] and choice["episodes"] == [3, 2, 2]  # per budget
    assert choice["heldout_set"] == 2  # a roadmap per held-out episode, as the protocol
    card = json.loads((out / "avg.json").read_text())
    assert card["averaged_updates"] == [5, 10]  # stage 3's snapshots of its 10 updates
    assert card["init"]["path"] == choice["chosen"]["path"]
    commands = [card["init"]["command"], *card["init"]["resumed_with"], card["command"]]
    assert all("env=tiny" in c and "algo.intent_depth=2" in c for c in commands)
    assert "algo.lr=3e-5" in card["command"]
    core, _ = load_core(out / "avg.pt")
    assert core.net.cfg.embed_dim == 32

    final = json.loads((out / "final_select.json").read_text())
    assert final["budget"] == [4.0, 5.0] and final["episodes"] == 2
    assert final["heldout_set"] == 2
    assert [Path(c["path"]).name for c in final["candidates"]] == ["start.pt", "avg.pt"]
    for c in final["candidates"]:  # the score is the geometric mean of the two budgets'
        assert c["mean"] == pytest.approx((c["mean_B4"] * c["mean_B5"]) ** 0.5)
    assert final["chosen"] == min(final["candidates"][::-1], key=lambda c: c["mean"])
    chosen = Path(final["chosen"]["path"])
    assert (out / "final.pt").read_bytes() == chosen.read_bytes()
    assert (out / "final.json").read_text() == chosen.with_suffix(".json").read_text()
    assert final["first"] == 3  # after the most SELECT_EPISODES worlds the start was chosen on
    assert "chosen on held-out episodes at B = 2 4 5 (" in card["selected_by"]
    start = json.loads((out / "start.json").read_text())
    assert start["selected_update"] == choice["chosen"]["update"]
    # benchmarks/ship_draw.py ships the finished run under a card prefix: the policy file,
    # both choices, the curves, the stamps and the set-aside candidate's card
    cards = tmp_path / "cards"
    cards.mkdir()
    proc = _ship_draw(out, cards / "draw")
    assert proc.returncode == 0, proc.stderr
    set_aside = "avg" if chosen.name == "start.pt" else "start"
    assert {p.name.removeprefix("draw") for p in cards.iterdir()} == {
        ".pt", ".json", "_choice.json", "_start_choice.json", "_stages12.jsonl", "_wall.txt",
        f"_stage3_{set_aside}.json", *["_m1_stages12.jsonl"] * (members - 1)}
    assert (cards / "draw.pt").read_bytes() == (out / "final.pt").read_bytes()
    assert ((cards / f"draw_stage3_{set_aside}.json").read_text()
            == (out / f"{set_aside}.json").read_text())


def test_train_2h_without_stage3_ships_the_start_choice(tmp_path):
    """benchmarks/train_2h.sh with STAGE3=0 (and POP=2): stages 1-2 of both members, the
    held-out choice among their last snapshots, and that choice exported with its card as
    the policy file final.pt; no stage 3, no average, no second choice."""
    out = tmp_path / "run"
    tiny = [*TINY_TRAIN, "algo.intent_rollouts=2", "algo.intent_depth=2"]
    proc = subprocess.run(
        ["bash", str(Path(__file__).parents[1] / "benchmarks" / "train_2h.sh"), str(out), "3"],
        capture_output=True, text=True, timeout=600,
        env={**os.environ, "SELECT": "1", "STAGE3": "0", "POP": "2", "SELECT_EPISODES": "2",
             "OVERRIDES": " ".join(tiny), "UPDATES": "1 2"})
    assert proc.returncode == 0, proc.stderr[-3000:]
    stamps = [line.split()[0] for line in (out / "wall.txt").read_text().splitlines()]
    assert sorted(stamps[1:5]) == ["stage1", "stage1", "stage2", "stage2"]
    assert stamps[:1] + stamps[5:] == ["start", "selected", "final", "end"]
    assert not (out / "stage3").exists() and not (out / "avg.pt").exists()
    choice = json.loads((out / "select.json").read_text())
    assert choice["budget"] == [2.0, 5.0]  # POP=2's default budgets
    chosen = Path(choice["chosen"]["path"])
    card = json.loads((out / "final.json").read_text())
    assert card["selected_update"] == choice["chosen"]["update"]
    assert "STAGE3=0" in card["selected_by"] and str(chosen) in card["selected_by"]
    theirs = torch.load(chosen, weights_only=False)["core"]
    ours = torch.load(out / "final.pt", weights_only=False)["core"]
    assert theirs.keys() == ours.keys()
    assert all(torch.equal(ours[k], theirs[k]) for k in theirs)


def test_train_2h_wide_keeps_each_stage_s_frames_and_steps_between_fresh_starts(tmp_path):
    """benchmarks/train_2h.sh with WIDE=4: stage 1 runs 8 x 4 envs and stage 2 16 x 4, each
    for 160 / 4 steps an update with fresh episodes every 4 updates (160 env steps, as
    without it), and checkpoints on those fresh starts."""
    out = tmp_path / "run"
    tiny = [o for o in TINY_TRAIN if not o.startswith(("n_envs=", "steps_per_batch="))]
    proc = subprocess.run(
        ["bash", str(Path(__file__).parents[1] / "benchmarks" / "train_2h.sh"), str(out), "3"],
        capture_output=True, text=True, timeout=600,
        env={**os.environ, "SELECT": "1", "STAGE3": "0", "SELECT_EPISODES": "2", "WIDE": "4",
             "UPDATES": "1 1",
             "OVERRIDES": " ".join([*tiny, "algo.intent_rollouts=2", "algo.intent_depth=2"])})
    assert proc.returncode == 0, proc.stderr[-3000:]
    for stage, n_envs in (("stage1", 32), ("stage2", 64)):
        cfg = torch.load(out / stage / "checkpoint.pt", weights_only=False)["config"]
        assert (cfg["n_envs"], cfg["steps_per_batch"], cfg["reset_every"],
                cfg["checkpoint_every"]) == (n_envs, 40, 4, 4), stage
    assert (out / "final.pt").exists()


def test_train_2h_refuses_a_deadline_with_updates(tmp_path):
    out = tmp_path / "run"
    proc = subprocess.run(["bash", str(Path(__file__).parents[1] / "benchmarks" / "train_2h.sh"),
                           str(out)], capture_output=True, text=True, timeout=60,
                          env={**os.environ, "DEADLINE": "90", "UPDATES": "1 2 5"})
    assert proc.returncode == 2
    assert "DEADLINE trims stage 3's minutes: not with STAGE3=0 or UPDATES" in proc.stderr
    assert not out.exists()


def test_train_2h_past_its_deadline_ships_the_start_choice(tmp_path):
    """benchmarks/train_2h.sh with DEADLINE (minutes, not UPDATES): a deadline already
    spent leaves stage 3 fewer than FLOOR minutes, so there is no stage 3 and no final
    choice: the start choice is exported as the policy file, the plan in deadline.json."""
    out = tmp_path / "run"
    tiny = [*TINY_TRAIN, "algo.intent_rollouts=2", "algo.intent_depth=2"]
    proc = subprocess.run(  # stage 2's limit counts stage 1's minutes: room for one update
        ["bash", str(Path(__file__).parents[1] / "benchmarks" / "train_2h.sh"), str(out), "3",
         "0.01", "0.4", "5"], capture_output=True, text=True, timeout=600,
        env={**os.environ, "SELECT": "1", "SELECT_EPISODES": "2", "FINAL": "1",
             "FINAL_EPISODES": "2", "DEADLINE": "1", "OVERRIDES": " ".join(tiny)})
    assert proc.returncode == 0, proc.stderr[-3000:]
    stamps = [line.split()[0] for line in (out / "wall.txt").read_text().splitlines()]
    assert stamps == ["start", "stage1", "stage2", "selected", "final", "end"]
    plan = json.loads((out / "deadline.json").read_text())
    assert plan["minutes"] == 0 and plan["deadline"] == 1 and plan["left"] < plan["floor"]
    assert plan["final_estimate"] > 0  # FINAL=1: the final choice's minutes were reserved
    assert not (out / "stage3").exists() and not (out / "final_select.json").exists()
    chosen = Path(json.loads((out / "select.json").read_text())["chosen"]["path"])
    card = json.loads((out / "final.json").read_text())
    assert "under DEADLINE=1" in card["selected_by"] and str(chosen) in card["selected_by"]
    theirs = torch.load(chosen, weights_only=False)["core"]
    ours = torch.load(out / "final.pt", weights_only=False)["core"]
    assert all(torch.equal(ours[k], theirs[k]) for k in theirs)


def _stage3_minutes(tmp_path, *args, spent=90.0, seconds=600.0, wall=None):
    """benchmarks/stage3_minutes.py on a run begun ``spent`` minutes ago (or with ``wall``
    as its wall.txt) whose start choice (4 candidates, 96 episodes at B = 2 and 48 at
    B = 5, as POP=2's) took ``seconds``."""
    begun = datetime.now(timezone.utc) - timedelta(minutes=spent)
    (tmp_path / "wall.txt").write_text(wall or f"start {begun:%Y-%m-%dT%H:%M:%SZ}\n")
    (tmp_path / "select.json").write_text(json.dumps(
        {"budget": [2.0, 5.0], "episodes": [96, 48], "seconds": seconds,
         "candidates": [{}] * 4}))
    return subprocess.run(
        [sys.executable, str(Path(__file__).parents[1] / "benchmarks" / "stage3_minutes.py"),
         "--wall", str(tmp_path / "wall.txt"), "--minutes", "26", "--deadline", "120", *args],
        capture_output=True, text=True, timeout=60)


def test_stage3_minutes_leaves_room_for_the_final_choice(tmp_path):
    """The final choice (2 candidates x 64 episodes at B = 4 and 5: 1152 episode-budgets
    against the start choice's 1728) is estimated at 600 s x 1152 / 1728 = 400 s, x 1.5
    = 10 minutes; with 2 minutes' allowance and 90 spent, stage 3 gets 18 of its 26."""
    proc = _stage3_minutes(tmp_path, "--select", str(tmp_path / "select.json"), "--final",
                           "--out", str(tmp_path / "plan.json"))
    assert proc.returncode == 0, proc.stderr
    assert float(proc.stdout) == pytest.approx(18.0, abs=0.05)
    plan = json.loads((tmp_path / "plan.json").read_text())
    assert plan["final_estimate"] == pytest.approx(10.0) and plan["allowance"] == 2.0
    # no final choice: only the allowance is reserved, and stage 3 keeps its typed minutes
    proc = _stage3_minutes(tmp_path, "--select", str(tmp_path / "select.json"))
    assert float(proc.stdout) == 26
    # fewer than 8 minutes left: no stage 3
    proc = _stage3_minutes(tmp_path, "--select", str(tmp_path / "select.json"), "--final",
                           spent=102.5)
    assert float(proc.stdout) == 0 and "no stage 3" in proc.stderr
    # FINAL_BUDGETS="2 4 5": 2 x 64 x 11 = 1408 episode-budgets, 600 s x 1408 / 1728 x 1.5
    # = 12.22 minutes reserved, so stage 3 gets 120 - 90 - 2 - 12.22 = 15.78
    proc = _stage3_minutes(tmp_path, "--select", str(tmp_path / "select.json"), "--final",
                           "--final-budgets", "2", "4", "5", "--out", str(tmp_path / "plan.json"))
    assert proc.returncode == 0, proc.stderr
    assert float(proc.stdout) == pytest.approx(15.78, abs=0.05)
    assert json.loads((tmp_path / "plan.json").read_text())["final_estimate"] == pytest.approx(
        12.22, abs=0.01)


@pytest.mark.parametrize(("args", "wall", "message"), [
    (["--final"], None, "needs the start choice's seconds (SELECT=1's select.json)"),
    (["--final-budgets", "4", "0"], None, "--final-budgets positive"),
    ([], "begun 2026-12-03T16:01:13Z\n", "the first line is not 'start <time>'")])
def test_stage3_minutes_bad_input_is_a_clear_error(tmp_path, args, wall, message):
    proc = _stage3_minutes(tmp_path, *args, wall=wall)
    assert proc.returncode == 2
    assert message in proc.stderr


def _ship_draw(run, prefix, *args):
    return subprocess.run(
        [sys.executable, str(Path(__file__).parents[1] / "benchmarks" / "ship_draw.py"),
         str(run), str(prefix), *args], capture_output=True, text=True, timeout=60)


def test_ship_draw_refuses_what_it_cannot_ship(tmp_path):
    """benchmarks/ship_draw.py: an unfinished run, a final.pt that is not the candidate the
    final choice kept, a board never scored and a prefix already shipped are clear errors,
    and nothing is copied."""
    run, cards = tmp_path / "run", tmp_path / "cards"
    (run / "stage2").mkdir(parents=True)
    cards.mkdir()
    for name in ("final.json", "stage2/curve.jsonl", "start.json", "avg.json"):
        (run / name).write_text("{}")
    (run / "final.pt").write_bytes(b"average")
    (run / "avg.pt").write_bytes(b"average")
    (run / "start.pt").write_bytes(b"start")
    (run / "wall.txt").write_text("start 2026-12-05T02:28:28Z\n")
    proc = _ship_draw(run, cards / "draw")
    assert proc.returncode == 2 and "not a finished train_2h.sh run" in proc.stderr
    (run / "wall.txt").write_text("start 2026-12-05T02:28:28Z\nend 2026-12-05T04:24:00Z\n")
    (run / "final_select.json").write_text(json.dumps({"chosen": {"path": "run/start.pt"}}))
    proc = _ship_draw(run, cards / "draw")
    assert proc.returncode == 2 and "final.pt is not the start.pt that" in proc.stderr
    (run / "final_select.json").write_text(json.dumps({"chosen": {"path": "run/avg.pt"}}))
    proc = _ship_draw(run, cards / "draw", "--board", str(tmp_path / "boards"))
    assert proc.returncode == 2 and "risk_aware.json is missing: score the run" in proc.stderr
    # --results: the policy file's rows at B = 5, each of the protocol's 300 episodes once
    suite = load_protocol(1).suite("risk_aware")
    digest = hashlib.sha256(b"average").hexdigest()
    rows = [{"setting": f"budget={b}", "checkpoint_sha256": sha, "instance": i, "trial": t,
             "protocol_version": 1}
            for i in suite.instance_seeds for t in suite.trial_seeds
            for b, sha in ((5.0, digest), (4.0, digest), (5.0, "0" * 64))]
    results = tmp_path / "results" / "risk_aware" / "ours_ti.jsonl"
    results.parent.mkdir(parents=True)
    for lines, message in ((rows[3:], "holds 299 of the protocol's 300 budget=5.0 episodes"),
                           (rows[:3] + rows, "; 301 rows): score it in full first"),
                           (rows + ["{"], "ours_ti.jsonl:901 is not a result row")):
        results.write_text("\n".join(map(json.dumps, lines)) + "\n")
        proc = _ship_draw(run, cards / "draw", "--results", str(results.parents[1]))
        assert proc.returncode == 2 and message in proc.stderr, proc.stderr
    proc = _ship_draw(run, cards / "draw", "--results", str(tmp_path / "boards"))
    assert proc.returncode == 2 and "ours_ti.jsonl is missing: score the run" in proc.stderr
    assert not any(cards.iterdir())
    results.write_text("\n".join(map(json.dumps, rows)) + "\n")
    assert _ship_draw(run, cards / "draw", "--results", str(results.parents[1])).returncode == 0
    assert sorted(p.name for p in cards.iterdir()) == [
        "draw.json", "draw.pt", "draw_b5_results", "draw_choice.json", "draw_stage3_start.json",
        "draw_stages12.jsonl", "draw_wall.txt"]
    shipped = (cards / "draw_b5_results" / "risk_aware" / "ours_ti.jsonl").read_text()
    assert [json.loads(line) for line in shipped.splitlines()] == rows[::3]
    for path in cards.glob("draw?*"):  # only the episodes are there: still refused
        if path.is_file():
            path.unlink()
    proc = _ship_draw(run, cards / "draw", "--results", str(results.parents[1]))
    assert proc.returncode == 2 and "1 files are already there" in proc.stderr
    assert "draw_b5_results/risk_aware/ours_ti.jsonl" in proc.stderr
    assert _ship_draw(run, cards / "draw", "--force").returncode == 0
    proc = _ship_draw(run, cards / "draw")
    assert proc.returncode == 2 and "6 files are already there" in proc.stderr
    assert _ship_draw(run, cards / "draw", "--force").returncode == 0


def test_ship_draw_without_the_final_choice_ships_stage3_s_average(tmp_path):
    """Without FINAL=1 (and with stage 3) train_2h.sh's policy file is avg.pt: that is
    what ships as the prefix's .pt, with no choice and no set-aside card."""
    run, cards = tmp_path / "run", tmp_path / "cards"
    (run / "stage2").mkdir(parents=True)
    cards.mkdir()
    (run / "stage2" / "curve.jsonl").write_text("{}")
    (run / "avg.pt").write_bytes(b"average")
    (run / "avg.json").write_text('{"averaged_updates": [5]}')
    (run / "wall.txt").write_text("start 2026-12-05T02:28:28Z\nend 2026-12-05T04:24:00Z\n")
    proc = _ship_draw(run, cards / "draw")
    assert proc.returncode == 0, proc.stderr
    assert sorted(p.name for p in cards.iterdir()) == [
        "draw.json", "draw.pt", "draw_stages12.jsonl", "draw_wall.txt"]
    assert (cards / "draw.pt").read_bytes() == b"average"
    assert (cards / "draw.json").read_text() == (run / "avg.json").read_text()


def test_final_choice_refuses_a_run_it_cannot_read(tmp_path):
    """benchmarks/final_choice.sh: an unfinished run, or one whose card names a start that
    is not there (another working folder), is a clear error before any export."""
    script = Path(__file__).parents[1] / "benchmarks" / "final_choice.sh"
    run = tmp_path / "run"
    (run / "stage3" / "snapshots").mkdir(parents=True)
    proc = subprocess.run(["bash", str(script), str(run)], capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 2 and "not a finished train_2h.sh run" in proc.stderr
    (run / "avg.json").write_text(json.dumps({"init": {"path": "elsewhere/checkpoint.pt"}}))
    proc = subprocess.run(["bash", str(script), str(run)], capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 2 and "elsewhere/checkpoint.pt" in proc.stderr
    assert not (run / "start.pt").exists()
    proc = subprocess.run(["bash", str(script), str(run)], capture_output=True, text=True,
                          timeout=60, env={**os.environ, "HELDOUT_SET": "3"})
    assert proc.returncode == 2 and "HELDOUT_SET must be 1 or 2, got '3'" in proc.stderr


def test_final_choice_exports_a_stage2_snapshot_start(tmp_path):
    """benchmarks/final_choice.sh on a hand-built run whose stage 3 started from a kept
    stage-2 snapshot (SELECT=1's usual case): start.pt is that snapshot's network, with
    its card, and final.pt / final.json are the chosen candidate's."""
    from maipp_bench.train import train

    run = tmp_path / "run"
    stage2 = run / "stage2"
    threads = torch.get_num_threads()  # train() sets its own
    train(compose_train(*TINY_TRAIN, "total_updates=2", "keep_snapshots=true",
                        "snapshot_every=1"), stage2)
    torch.set_num_threads(threads)
    (run / "stage3" / "snapshots").mkdir(parents=True)
    shutil.copy(stage2 / "checkpoint.pt", run / "avg.pt")
    start = stage2 / "snapshots" / "update_0001.pt"
    (run / "avg.json").write_text(json.dumps({"init": {"path": str(start)}}))
    script = Path(__file__).parents[1] / "benchmarks" / "final_choice.sh"
    proc = subprocess.run(["bash", str(script), str(run)], capture_output=True, text=True,
                          timeout=600, env={**os.environ, "FINAL_EPISODES": "2",
                                            "FINAL_BUDGETS": "2 5"})
    assert proc.returncode == 0, proc.stderr[-3000:]
    card = json.loads((run / "start.json").read_text())
    assert card["selected_update"] == 1 and "stage 3 of" in card["selected_by"]
    theirs = torch.load(start, weights_only=False)["core"]
    ours = torch.load(run / "start.pt", weights_only=False)["core"]
    assert all(torch.equal(ours[k], theirs[k]) for k in theirs)
    final = json.loads((run / "final_select.json").read_text())
    assert final["first"] == 160 and final["episodes"] == 2
    assert final["budget"] == [2.0, 5.0]  # FINAL_BUDGETS, not the default 4 5
    chosen = Path(final["chosen"]["path"])
    assert (run / "final.pt").read_bytes() == chosen.read_bytes()
    assert (run / "final.json").read_text() == chosen.with_suffix(".json").read_text()


def test_select_snapshot_show_prints_every_candidates_paired_z(monkeypatch) -> None:
    """select_snapshot.py --show: the docs' "N standard errors" of a held-out choice come
    from this output, the chosen candidate's own differences against the last included."""
    monkeypatch.syspath_prepend(str(Path(__file__).parents[1] / "benchmarks"))
    from select_snapshot import margins

    start = {"update": 9, "path": "start.pt", "mean": 10.0, "position": 0,
             "minus_end_B2": 1.0, "se_B2": 4.0, "minus_end_B5": -0.9, "se_B5": 0.3}
    last = {"update": 4, "path": "avg.pt", "mean": 10.5, "position": 1,
            "minus_end_B2": 0.0, "se_B2": 0.0, "minus_end_B5": 0.0, "se_B5": 0.0}
    chosen, other = margins({"chosen": start, "candidates": [start, last]})
    assert chosen == ("chosen: update 9 (start.pt), score 10.00; minus the last candidate: "
                      "B2: +1.00 ± 4.00 (z +0.2)  B5: -0.90 ± 0.30 (z -3.0)")
    assert other == ("  update 4 (avg.pt): 10.50, +0.50 behind the chosen; "
                     "minus the last candidate: none (it is the last)")
    # the last candidate chosen: no differences of its own to print
    assert margins({"chosen": last, "candidates": [start, last]})[0] == (
        "chosen: update 4 (avg.pt), score 10.50")


def test_select_snapshot_scores_the_window_and_picks_the_lowest(tiny_checkpoint, tmp_path,
                                                                monkeypatch, capsys):
    """benchmarks/select_snapshot.py (train_2h.sh's SELECT=1): the candidates are the run's
    end and its snapshots inside the window; the choice is the lowest mean Tr(P_f)."""
    script = Path(__file__).parents[1] / "benchmarks" / "select_snapshot.py"
    run = tmp_path / "run"
    (run / "snapshots").mkdir(parents=True)
    shutil.copy(tiny_checkpoint, run / "checkpoint.pt")  # update 2
    payload = torch.load(tiny_checkpoint, weights_only=False)
    other = copy.deepcopy(payload)  # a different network, so the scores differ
    with torch.no_grad():
        for value in other["core"].values():
            if value.is_floating_point():
                value.mul_(-1.0)
    torch.save(other, run / "snapshots" / "update_0001.pt")
    torch.save(payload, run / "snapshots" / "update_0000.pt")  # outside --window 1
    out = tmp_path / "select.json"
    proc = subprocess.run([sys.executable, str(script), "--run", str(run), "--window", "1",
                           "--episodes", "2", "--workers", "1", "--out", str(out)],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    result = json.loads(out.read_text())
    assert [c["update"] for c in result["candidates"]] == [1, 2]
    assert result["heldout_set"] == 2  # a roadmap per episode unless asked
    first, end = result["candidates"]
    assert first["mean"] != end["mean"]  # the choice below follows the scores
    assert result["chosen"] == min(first, end, key=lambda c: c["mean"])
    assert proc.stdout.strip() == result["chosen"]["path"]  # stdout is the path alone
    assert result["candidates"][-1]["minus_end"] == 0.0
    # bad arguments fail before any worker starts: checked in this process (a Python
    # start per case cost ~5 s each)
    monkeypatch.syspath_prepend(str(script.parent))
    from select_snapshot import main as select_main

    def refused(*argv: str) -> str:
        monkeypatch.setattr(sys, "argv", ["select_snapshot.py", *argv])
        with pytest.raises(SystemExit) as exit_:
            select_main()
        assert exit_.value.code == 2
        return capsys.readouterr().err

    monkeypatch.setattr(sys, "argv", ["select_snapshot.py", "--run", str(tmp_path / "none")])
    with pytest.raises(FileNotFoundError, match="no training checkpoint"):
        select_main()
    monkeypatch.setattr(sys, "argv", ["select_snapshot.py", "--candidates",
                                      str(run / "checkpoint.pt"), str(tmp_path / "none.pt")])
    with pytest.raises(FileNotFoundError, match=f"no such file: {tmp_path / 'none.pt'}"):
        select_main()
    assert "not allowed with argument" in refused("--run", str(run), "--candidates",
                                                  str(run / "checkpoint.pt"))
    assert "one count or one per budget" in refused("--run", str(run), "--budget", "2", "5",
                                                    "--episodes", "2", "3", "4")
    assert "--budget takes each budget once, got 2 2" in refused("--run", str(run), "--budget",
                                                                "2", "2.0")
    # --candidates at two budgets, episodes per budget in --budget's order: equal scores
    # go to the later file
    shutil.copy(run / "checkpoint.pt", tmp_path / "copy.pt")
    common = ["--first", "7", "--workers", "1", "--heldout-set", "1"]
    tie = subprocess.run([sys.executable, str(script), "--candidates",
                          str(run / "checkpoint.pt"), str(tmp_path / "copy.pt"), "--budget",
                          "5", "4", "--episodes", "3", "2", *common, "--out", str(out)],
                         capture_output=True, text=True, timeout=300)
    assert tie.returncode == 0, tie.stderr
    result = json.loads(out.read_text())
    assert result["first"] == 7 and result["budget"] == [4.0, 5.0]
    assert result["episodes"] == [2, 3] and result["heldout_set"] == 1
    first, copy_ = result["candidates"]
    assert first["mean"] == copy_["mean"] and copy_["minus_end_B5"] == 0.0
    assert result["chosen"]["path"] == tie.stdout.strip() == str(tmp_path / "copy.pt")
    alone = subprocess.run([sys.executable, str(script), "--candidates", str(tmp_path / "copy.pt"),
                            "--budget", "5", "--episodes", "3", *common, "--out", str(out)],
                           capture_output=True, text=True, timeout=300)
    assert alone.returncode == 0, alone.stderr  # B = 5 played its own 3 episodes above
    assert json.loads(out.read_text())["chosen"]["mean"] == copy_["mean_B5"]


def test_paired_subset_leaves_out_excluded_episodes_and_names_the_worst(tmp_path):
    """benchmarks/paired_subset.py --exclude: the left-out episode's rows are printed apart
    and the paired mean is over the rest; a bad INSTANCE:TRIAL is refused."""
    script = Path(__file__).parents[1] / "benchmarks" / "paired_subset.py"
    traces = {"mine": [10.0, 20.0, 700.0], "base": [12.0, 19.0, 30.0]}
    for name, folder in (("mine", "sub"), ("base", "res")):
        (tmp_path / folder / "s").mkdir(parents=True)
        rows = [{"setting": "budget=2.0", "instance": i, "trial": 5, "trace": t,
                 "traps": int(t > 100), "distance": 1.0} for i, t in enumerate(traces[name])]
        (tmp_path / folder / "s" / "m.jsonl").write_text(
            "".join(json.dumps(r) + "\n" for r in rows))
    args = [sys.executable, str(script), "--subset", str(tmp_path / "sub"), "--suite", "s",
            "--method", "m", "--results", str(tmp_path / "res"), "--against", "m"]
    whole = subprocess.run(args, capture_output=True, text=True, timeout=120)
    assert whole.returncode == 0, whole.stderr
    assert "3 episodes" in whole.stdout and "worst 700.0 (instance 2 trial 5)" in whole.stdout
    kept = subprocess.run(args + ["--exclude", "2:5"], capture_output=True, text=True,
                          timeout=120)
    assert kept.returncode == 0, kept.stderr
    assert "2 episodes" in kept.stdout
    assert "left out: instance 2 trial 5: Tr(P_f) 700.0  traps 1" in kept.stdout
    assert "minus m  -0.50 ± 1.50" in kept.stdout  # mean of (-2, +1) and its standard error
    assert "minus m  -0.50 ± 1.50 (z -0.3)" in kept.stdout  # the difference in standard errors
    bad = subprocess.run(args + ["--exclude", "2"], capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "expected INSTANCE:TRIAL" in bad.stderr


def test_heldout_vs_protocol_ranks_networks_from_chunked_rows(tiny_checkpoint, tmp_path):
    """benchmarks/heldout_vs_protocol.py: each network's held-out mean per set, played in
    chunks, is the mean of one unchunked call of that set; networks are found by sha256 in
    the suite's protocol rows and ranked against them; --cached-only computes nothing and
    reports the same from the cache."""
    from maipp_bench.protocol.protocol import file_sha256
    from maipp_bench.train import heldout_rows

    script = Path(__file__).parents[1] / "benchmarks" / "heldout_vs_protocol.py"
    payload = torch.load(tiny_checkpoint, weights_only=False)
    nets, means, rows = [], {1: [], 2: []}, []
    for i, scale in enumerate((1.0, -1.0, 0.5)):  # three different networks
        other = copy.deepcopy(payload)
        with torch.no_grad():
            for value in other["core"].values():
                if value.is_floating_point():
                    value.mul_(scale)
        nets.append(tmp_path / f"net{i}.pt")
        torch.save(other, nets[-1])
        core, saved = load_core(nets[-1])
        for h in (1, 2):
            traces = [r["trace"] for r in heldout_rows(
                core, MAIPPConfig.from_dict(saved["env"]), 3, 1.0,
                algos.get_method("ours_greedy"), heldout=h)]
            means[h].append(sum(traces) / 3)
        rows += [{"checkpoint_sha256": file_sha256(nets[-1]), "setting": "budget=1.0",
                  "trace": t} for t in (10.0 * i, 10.0 * i + 2.0)]  # protocol means 1, 11, 21
    assert len(set(means[2])) == 3
    (tmp_path / "res" / "smoke").mkdir(parents=True)
    (tmp_path / "res" / "smoke" / "ours_greedy.jsonl").write_text(
        "".join(json.dumps(r) + "\n" for r in rows))
    out = tmp_path / "report.json"
    args = [sys.executable, str(script), "--nets", *map(str, nets), "--results",
            str(tmp_path / "res"), "--suite", "smoke", "--method", "ours_greedy", "--budgets",
            "1", "1.5", "--episodes", "3", "--chunk", "2", "--cache", str(tmp_path / "cache"),
            "--permutations", "50", "--workers", "1", "--out"]
    proc = subprocess.run(args + [str(out), "--sets", "1", "2"], capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert "no smoke protocol rows of ours_greedy at B = 1.5; left out" in proc.stderr
    report = json.loads(out.read_text())["report"]
    assert [(r["budget"], r["heldout_set"]) for r in report] == [(1.0, 1), (1.0, 2)]
    for r in report:
        assert [n["heldout"] for n in r["networks"]] == pytest.approx(means[r["heldout_set"]],
                                                                    rel=1e-12)
        assert [n["protocol"] for n in r["networks"]] == [1.0, 11.0, 21.0]
        ranks = [sorted(means[r["heldout_set"]]).index(m) for m in means[r["heldout_set"]]]
        same = sum(ranks[a] < ranks[b] for a, b in ((0, 1), (0, 2), (1, 2)))
        assert (r["pairs_same"], r["pairs"]) == (same, 3)
        assert r["rho"] == pytest.approx(1 - 6 * sum((k - n) ** 2 for n, k in
                                                     enumerate(ranks)) / (3 * 8))
    cached = tmp_path / "cached.json"
    again = subprocess.run(args + [str(cached), "--sets", "1", "2", "--cached-only"],
                           capture_output=True, text=True, timeout=120)
    assert again.returncode == 0, again.stderr
    assert json.loads(cached.read_text()) == json.loads(out.read_text())
    assert "[1/" not in again.stderr  # nothing computed
    empty = subprocess.run(args + [str(cached), "--sets", "2", "--cached-only", "--cache",
                                   str(tmp_path / "none")], capture_output=True, text=True,
                           timeout=120)
    assert empty.returncode == 0, empty.stderr
    assert "set 2: 0 networks with every row; no ranking" in empty.stdout


def test_training_curve_plot(tiny_checkpoint, tmp_path):
    from maipp_bench.curves import main, read_curve

    rows = read_curve(tiny_checkpoint.parent)
    assert [r["update"] for r in rows] == [1, 2]
    out = tmp_path / "c.png"
    main([f"tiny={tiny_checkpoint.parent}", "--out", str(out)])
    assert out.stat().st_size > 5000


def test_training_curve_marks_the_shipped_update(tmp_path):
    from maipp_bench.curves import main, selected_frames

    card = tmp_path / "card.json"
    curve = [{"update": u, "frames": 100 * u, "trace_final": 1.0 / u} for u in (1, 2, 3)]
    card.write_text(json.dumps({"curve": curve, "selected_update": 2}))
    assert selected_frames(card) == 200
    assert selected_frames(tmp_path) is None  # a run folder ships nothing
    main([f"x={card}", "--out", str(tmp_path / "c.png")])
    assert (tmp_path / "c.png").stat().st_size > 5000


def test_a_fine_tunes_curve_continues_from_its_starting_networks_frames(tmp_path):
    from maipp_bench.curves import read_curve, selected_frames

    card = tmp_path / "card.json"
    curve = [{"update": u, "frames": 100 * u} for u in (1, 2, 3)]
    card.write_text(json.dumps({"curve": curve, "selected_update": 2, "frames": 200,
                                "init": {"frames": 5000}, "frames_with_init": 5200}))
    assert [r["frames"] for r in read_curve(card)] == [5100, 5200, 5300]
    assert selected_frames(card) == 5200


def test_curves_plot_against_updates_or_minutes_from_a_fine_tunes_start(tmp_path):
    import matplotlib.pyplot as plt

    from maipp_bench.curves import figure, init_offsets, main, read_curve

    card = tmp_path / "card.json"
    curve = [{"update": u, "frames": 100 * u, "wall_s": 30.0 * u, "trace_final": 1.0 / u,
              "reward_per_decision": 0.1} for u in (1, 2, 3)]
    card.write_text(json.dumps({"curve": curve, "selected_update": 2, "frames": 300,
                                "wall_s": 90.0, "frames_with_init": 5300,
                                "init": {"frames": 5000, "update": 40, "wall_s": 1200.0}}))
    offsets = init_offsets(card)
    assert offsets == {"update": 40, "wall_s": 1200.0}
    assert init_offsets(tmp_path) == {}  # a run folder starts at zero
    twice = tmp_path / "twice.json"  # a fine-tune of a fine-tune counts both before it
    twice.write_text(json.dumps({"curve": curve, "wall_s": 90.0, "init": {
        "update": 40, "wall_s": 1200.0, "init": {"update": 100, "wall_s": 3000.0}}}))
    assert init_offsets(twice) == {"update": 140, "wall_s": 4200.0}
    rows = read_curve(card)
    for axis, xs in (("updates", [41, 42, 43]), ("minutes", [20.5, 21.0, 21.5]),
                     ("frames", [5100, 5200, 5300])):
        fig = figure({"ft": rows}, selected={"ft": xs[1]}, x=axis, offsets={"ft": offsets})
        lines = {line.get_label(): line for line in fig.axes[0].get_lines()}
        label = fig.axes[0].get_xlabel()
        plt.close(fig)
        assert list(lines["ft"].get_xdata()) == xs
        assert list(lines["ft: selected update"].get_xdata()) == [xs[1], xs[1]]
        assert label == {"updates": "updates", "minutes": "minutes of update time",
                         "frames": "env frames"}[axis]
    main([f"ft={card}", "--x", "minutes", "--out", str(tmp_path / "m.png")])
    assert (tmp_path / "m.png").stat().st_size > 5000
    fig = figure({"ft": rows}, x="updates", offsets={"ft": offsets}, xmax=42)
    assert all(ax.get_xlim() == (0, 42) for ax in fig.axes)
    plt.close(fig)
    with pytest.raises(SystemExit):
        main([f"ft={card}", "--xmax", "0", "--out", str(tmp_path / "z.png")])
    with pytest.raises(ValueError, match="valid: frames, updates, minutes"):
        figure({"ft": rows}, x="seconds")


def test_a_curve_keeps_its_colour_in_every_panel():
    import matplotlib.pyplot as plt

    from maipp_bench.curves import figure

    # "a" has no held-out evaluations: "b" must not take its colour in that panel.
    a = [{"update": u, "frames": u, "trace_final": 1.0, "reward_per_decision": 0.1}
         for u in (1, 2)]
    b = [r | {"eval/trace": 2.0} for r in a]
    fig = figure({"a": a, "b": b}, selected={"a": 2, "b": 2})
    colors = [{line.get_label(): line.get_color() for line in ax.get_lines()}
              for ax in fig.axes]
    legend = [t.get_text() for t in fig.legends[0].get_texts()]
    plt.close(fig)  # pyplot's figure list stays empty for other tests (test_viz)
    assert legend == ["a", "a: selected update", "b", "b: selected update"]
    assert "a" not in colors[1]
    assert colors[0]["a"] != colors[0]["b"]
    for panel in colors:
        assert panel["b"] == colors[0]["b"]
        assert panel["a: selected update"] == colors[0]["a"]  # drawn where "a" has no points


def test_a_panel_without_points_is_left_out():
    """Runs without held-out evaluations draw two panels, not an empty third; a figure
    with nothing to draw is a clear error."""
    import matplotlib.pyplot as plt

    from maipp_bench.curves import figure

    rows = [{"update": u, "frames": u, "trace_final": 1.0, "reward_per_decision": 0.1,
             "eval/trace": float("nan")} for u in (1, 2)]
    fig = figure({"a": rows, "b": rows})
    titles = [ax.get_title() for ax in fig.axes]
    plt.close(fig)
    assert titles == ["Tr(P_f), training episodes", "reward per decision"]
    with pytest.raises(ValueError, match="no curve has any point"):
        figure({"a": [{"update": 1, "frames": 1}]})


def test_eleven_curves_have_eleven_colours():
    """Past the default cycle's ten colours the eleventh curve took the first's (the
    two-hour draws' figure drew the shipped run and a draw in one blue)."""
    import matplotlib.pyplot as plt

    from maipp_bench.curves import figure

    rows = [{"update": 1, "frames": 1, "trace_final": 1.0, "reward_per_decision": 0.1}]
    fig = figure({f"c{i}": rows for i in range(11)})
    colors = {str(line.get_color()) for line in fig.axes[0].get_lines()}
    plt.close(fig)
    assert len(colors) == 11


def test_eval_panel_title_names_the_evaluations():
    from maipp_bench.curves import eval_title

    old = [{"update": 1, "eval/trace": 9.0}, {"update": 2}]  # before eval tags: greedy
    tagged = [{"update": 3, "eval/trace": 8.0, "eval/tag": "greedy@3"}]
    ti = [{"update": 4, "eval/trace": 7.0, "eval/tag": "ours_ti@2,3"}]
    assert eval_title({"a": old}) == "Tr(P_f), held-out greedy eval"
    assert eval_title({"a": old + tagged}) == "Tr(P_f), held-out greedy@3 eval"
    assert eval_title({"a": old + tagged, "b": ti}) == (
        "Tr(P_f), held-out greedy@3 / ours_ti@2,3 eval")
    assert eval_title({"a": [{"update": 1}]}) == "Tr(P_f), held-out greedy eval"


def test_algo_configs_compose_as_documented():
    catnipp = compose_train("algo=catnipp")
    assert catnipp.algo.feature_set == "catnipp" and catnipp.env.prune_risky_nodes
    assert not compose_train("algo=catnipp", "env=tiny").env.prune_risky_nodes  # CLI wins
    mappo = compose_train("algo=mappo")
    assert (mappo.algo.critic, mappo.algo.loss) == ("state", "mappo")
    ours = compose_train()
    assert ours.algo.name == "ours" and ours.env.node_encoding_dim == 32
    assert (ours.algo.lr, ours.algo.minibatch, ours.algo.epochs) == (1e-4, 256, 8)


@pytest.mark.parametrize("algo", ["catnipp", "mappo"])
def test_other_algos_train(algo, tmp_path):
    from maipp_bench.train import train

    path = train(compose_train(*TINY_TRAIN, f"algo={algo}", "env=tiny", "total_updates=1"),
                 tmp_path)
    row = torch.load(path, weights_only=False)["curve"][0]
    assert np.isfinite(row["loss_objective"]) and np.isfinite(row["loss_critic"])


# A KL cap of 1e-9 can stop the update before its first optimizer step; the schedule still
# advances once per update, which torch flags when no step came before it.
@pytest.mark.filterwarnings("ignore:Detected call of `lr_scheduler.step\\(\\)`:UserWarning")
def test_target_kl_ends_an_update_early(tmp_path):
    from maipp_bench.train import train

    def first_update(*extra: str) -> dict:
        path = train(compose_train(*TINY_TRAIN, "total_updates=1", *extra), tmp_path / extra[0])
        return torch.load(path, weights_only=False)["curve"][0]

    full = first_update("algo.target_kl=0")  # off: every minibatch of every epoch
    capped = first_update("algo.target_kl=1e-9")  # any KL above rounding ends it
    assert full["minibatches"] >= 2 * 2  # 2 epochs of at least 2 minibatches (tiny config)
    assert capped["minibatches"] < full["minibatches"]


@pytest.mark.parametrize("backend, pattern", [
    ("csv", "logs/ours/scalars/loss_critic.csv"),
    ("tensorboard", "logs/ours/events.out.tfevents.*"),
    ("wandb", "wandb/offline-run-*/run-*.wandb"),  # offline: no network, ever
])
def test_loggers_write_offline(backend, pattern, tmp_path, monkeypatch):
    from maipp_bench.train import train

    monkeypatch.setenv("WANDB_SILENT", "true")
    train(compose_train(*TINY_TRAIN, f"logger={backend}", "total_updates=1"), tmp_path)
    assert list(tmp_path.glob(pattern)), sorted(str(p) for p in tmp_path.rglob("*"))


def test_eval_records_checkpoints_and_never_mixes_their_rows(tiny_checkpoint, tmp_path,
                                                              monkeypatch):
    import json

    from maipp_bench import eval as eval_cli
    from maipp_bench.algos import checkpoint as ckpt

    other = tmp_path / "other.pt"
    state = torch.load(tiny_checkpoint, weights_only=False)
    next(iter(state["core"].values())).add_(1e-3)  # another network, another hash
    torch.save(state, other)
    args = ["--suite", "smoke", "--methods", "ours_greedy", "--episodes", "2", "--out",
            str(tmp_path / "res"), "--no-progress", "--workers", "1"]
    first = eval_cli.main([*args, "--checkpoint", f"ours_greedy={tiny_checkpoint}"])
    second = eval_cli.main([*args, "--checkpoint", f"ours_greedy={other}"])
    sha = [b["checkpoints"]["ours_greedy"]["sha256"] for b in (first, second)]
    assert sha[0] != sha[1]
    stored = [json.loads(line) for line in
              (tmp_path / "res/subset-2/smoke/ours_greedy.jsonl").read_text().splitlines()]
    assert sorted({r["checkpoint_sha256"] for r in stored}) == sorted(sha)
    assert len(stored) == 2 * 2 * 2  # 2 settings x 2 episodes, once per checkpoint
    # Without a shipped file, asking for a learned method says how to get one.
    monkeypatch.setattr(ckpt, "SHIPPED_DIR", tmp_path / "empty")
    with pytest.raises(SystemExit, match="maipp_bench.train"):
        eval_cli.main(args)
    with pytest.raises(SystemExit, match="not a learned method"):
        eval_cli.main([*args[:2], "--methods", "greedy", "--checkpoint", f"greedy={other}"])


def test_export_writes_policy_and_card(tmp_path):
    import json

    from maipp_bench.train import train

    out = tmp_path / "shipped" / "tiny.pt"
    path = train(compose_train(*TINY_TRAIN, "total_updates=1", f"export={out}"), tmp_path)
    card = json.loads(out.with_suffix(".json").read_text())
    for key in ("command", "seed", "commit", "wall_s", "machine", "curve", "updates", "frames"):
        assert key in card, key
    assert card["command"].startswith("python -m maipp_bench.train")
    assert len(card["curve"]) == 1 and card["updates"] == 1
    assert "init" not in card  # trained from scratch
    core, _ = load_core(out)
    full, _ = load_core(path)
    for name, tensor in core.state_dict().items():
        assert torch.equal(tensor, full.state_dict()[name])
    assert out.stat().st_size < path.stat().st_size  # slim: no optimiser state


def test_best_held_out_checkpoint_is_exported(tmp_path):
    import json

    from maipp_bench.train import train

    out = tmp_path / "shipped.pt"
    train(compose_train(*TINY_TRAIN, "total_updates=3", "eval_every=1", "eval_episodes=2",
                        f"export={out}"), tmp_path / "run")
    card = json.loads(out.with_suffix(".json").read_text())
    evals = [r["eval/trace"] for r in card["curve"]]
    assert len(evals) == 3 and card["updates"] == 3
    assert card["selected_update"] == 1 + evals.index(min(evals))
    assert torch.load(out, weights_only=False)["update"] == card["selected_update"]


def test_held_out_evaluation_can_run_the_ranked_method_at_several_budgets(tmp_path):
    import math

    from maipp_bench.train import train

    out = tmp_path / "shipped.pt"
    train(compose_train(*TINY_TRAIN, "total_updates=2", "eval_every=1", "eval_episodes=2",
                        "eval_method=ours_ti", "eval_budgets=[1.0,1.5]", f"export={out}"),
          tmp_path / "run")
    card = json.loads(out.with_suffix(".json").read_text())
    for row in card["curve"]:
        per_budget = [row["eval/trace_B1"], row["eval/trace_B1.5"]]
        assert row["eval/trace"] == pytest.approx(math.sqrt(per_budget[0] * per_budget[1]))
        assert row["eval/tag"] == "ours_ti@1,1.5/h2"
    assert "ours_ti@1,1.5/h2" in card["selected_by"]
    # Resuming under another evaluation restarts the selection: old scores never compete.
    train(compose_train(*TINY_TRAIN, "total_updates=3", "eval_every=1", "eval_episodes=2",
                        f"resume={tmp_path / 'run' / 'checkpoint.pt'}", f"export={out}"),
          tmp_path / "run")
    card = json.loads(out.with_suffix(".json").read_text())
    assert card["selected_update"] == 3  # not an update scored by ours_ti
    assert "greedy@" in card["selected_by"]


@pytest.mark.parametrize("override,message", [
    ("eval_method=random", "'ours' network"),
    ("eval_method=catnipp_ti", "'ours' network"),  # another network's features / roadmap
    ("eval_method=nonexistent", "nonexistent"),
    ("eval_budgets=[0.0]", "eval_budgets"),
    ("eval_heldout=3", r"held-out episode set 3; valid: \[1, 2\]"),
])
def test_bad_held_out_evaluation_is_a_clear_error(override, message, tmp_path):
    from maipp_bench.train import train

    with pytest.raises(ValueError, match=message):
        train(compose_train(*TINY_TRAIN, override), tmp_path / "run")


def test_eval_tag_names_what_a_score_measures():
    from maipp_bench.train import eval_tag, row_tag

    cfg = compose_train(*TINY_TRAIN, "eval_method=ours_ti", "eval_budgets=[3,2,2]")
    assert eval_tag(cfg) == "ours_ti@2,3/h2"  # sorted, each budget once
    assert eval_tag(compose_train(*TINY_TRAIN, "eval_budget=4")) == "greedy@4/h2"
    # the shared-roadmap set's tags have no suffix: its rows predate held-out sets
    assert eval_tag(compose_train(*TINY_TRAIN, "eval_heldout=1")) == "greedy@3"
    # rows written before tags existed: greedy at the eval_budget of their run
    assert row_tag({"eval/trace": 1.0}, {"config": {"eval_budget": 4.0}}) == "greedy@4"
    assert row_tag({"eval/tag": "ours_ti@2,3"}, {}) == "ours_ti@2,3"


@pytest.mark.parametrize("heldout,roadmaps", [(1, 1), (2, 3)])
def test_held_out_sets_share_one_roadmap_or_draw_one_per_episode(heldout, roadmaps,
                                                                 tiny_checkpoint):
    """Set 1 (the runs documented up to 2026-11-27) plays every held-out episode on one
    roadmap and start; set 2 draws each its own, as the protocol does per (instance,
    trial). Either way an episode's row depends on its own seeds only, and its method
    randomness is its own."""
    from maipp_bench.train import greedy_method, heldout_rows

    core, payload = load_core(str(tiny_checkpoint))
    cfg, spec = MAIPPConfig.from_dict(payload["env"]), greedy_method("ours")
    first_nodes = []

    def record(env, td):
        if not first_nodes:
            first_nodes.append(env.episode.roadmap.nodes.clone())

    rows = heldout_rows(core, cfg, 3, 1.0, spec, on_action=record, heldout=heldout)
    assert len(torch.unique(first_nodes[0], dim=0)) == roadmaps
    assert len({r["trial"] for r in rows}) == roadmaps
    later = heldout_rows(core, cfg, 2, 1.0, spec, first=1, heldout=heldout)
    strip = [{k: v for k, v in r.items() if k != "planning_s"} for r in (*rows[1:], *later)]
    assert strip[:2] == strip[2:]
    # every episode its own method randomness (set 2's first version, trial seed = instance
    # seed, gave all one: the two cancel in the method key's hash)
    from maipp_bench.heldout import heldout_seeds
    from maipp_bench.protocol.runner import method_seeds

    assert len(torch.unique(method_seeds(*heldout_seeds(0, 64, heldout)))) == 64


@pytest.mark.cuda
@pytest.mark.parametrize("algo,precision", [("ours", "float32"), ("catnipp", "float32"),
                                            ("mappo", "float32"), ("ours", "bf16"),
                                            ("catnipp", "bf16"), ("mappo", "bf16")])
def test_training_and_ti_run_on_cuda(algo, precision, tmp_path):
    """One update on CUDA (collector, loss, held-out evaluation, checkpoint), then the
    trained network plays TI episodes there: finite losses, valid episodes; bf16 autocasts
    on the CUDA device (algo.precision)."""
    if not torch.cuda.is_available():
        pytest.skip("CUDA is not available")
    from maipp_bench.train import train

    intents = ["algo.intent_rollouts=2", "algo.intent_depth=2"] if algo == "ours" else []
    path = train(compose_train(*TINY_TRAIN, f"algo={algo}", "total_updates=1", "device=cuda",
                               "eval_every=1", "eval_episodes=2", f"algo.precision={precision}",
                               *intents), tmp_path)
    row = torch.load(path, weights_only=False, map_location="cpu")["curve"][0]
    assert np.isfinite(row["loss_objective"]) and np.isfinite(row["loss_critic"])
    assert 0 < row["eval/trace"] <= 900
    cfg = MAIPPConfig(n_agents=2, budget=1.0, n_nodes=40, k_neighbors=8)
    spec = algos.MethodSpec(name="tiny_ti", policy="attention", models_risk=True, learned=True,
                            params={"mode": "ti", "rollouts": 3, "depth": 2})
    rows = run_chunk(spec, cfg, [11, 12], trial_seed=5, checkpoint=str(path), device="cuda")
    for r in rows:
        assert r["distance"] <= cfg.team_budget + 1e-9 and 0 < r["trace"] <= 900


@pytest.mark.parametrize("rollouts", [0, 2])
def test_training_agents_broadcast_intents_when_asked(rollouts):
    from maipp_bench.algos.ppo import build_learner
    from maipp_bench.train import make_collection

    cfg = compose_train(*TINY_TRAIN, f"algo.intent_rollouts={rollouts}", "algo.intent_depth=2")
    env_cfg = MAIPPConfig.from_dict(dict(cfg.env))
    torch.manual_seed(0)
    learner = build_learner(cfg.algo, env_cfg.node_encoding_dim, env_cfg.interest_threshold)
    env, collector, _ = make_collection(cfg, env_cfg, learner)
    env.set_seed(0)
    batch = next(iter(collector))
    collector.shutdown()
    intent = batch.get(("agents", "observation", "node_features"))[..., 5]  # NODE_FEATURES
    if rollouts:
        assert (intent > 0).any() and intent.max() <= 1.0 + 1e-6
        # The executed actions are still the policy's samples: valid and logged.
        deciding = batch.get(("agents", "deciding"))
        mask = batch.get(("agents", "action_mask"))
        action = batch.get(("agents", "action"))
        assert mask.gather(-1, action.unsqueeze(-1)).squeeze(-1)[deciding].all()
        assert torch.isfinite(batch.get(("agents", "action_log_prob"))[deciding]).all()
    else:
        assert (intent == 0).all()


def test_training_with_intents_updates_and_bad_ti_is_a_clear_error(tmp_path):
    from maipp_bench.train import train

    path = train(compose_train(*TINY_TRAIN, "total_updates=1", "algo.intent_rollouts=2",
                               "algo.intent_depth=2"), tmp_path / "ok")
    row = torch.load(path, weights_only=False)["curve"][0]
    assert np.isfinite(row["loss_objective"]) and np.isfinite(row["loss_critic"])
    bad = {"algo.intent_rollouts=-1": "algo.intent_rollouts=-1",
           "algo.intent_depth=0": "algo.intent_depth=0",
           "algo=catnipp": "does not read intents"}
    for override, message in bad.items():
        with pytest.raises(ValueError, match=message):  # before anything is written
            train(compose_train(*TINY_TRAIN, "total_updates=1", "algo.intent_rollouts=2",
                                override), tmp_path / "bad")
        assert not (tmp_path / "bad").exists()


def test_selecting_an_intent_trained_network_without_intents_warns():
    from maipp_bench.train import eval_spec, warn_unseen_intents

    intents = ["algo.intent_rollouts=2", "eval_every=1"]
    for silent in ("eval_method=greedy", "eval_method=ours_ti_no_intent"):
        cfg = compose_train(*TINY_TRAIN, *intents, silent)
        with pytest.warns(UserWarning, match="sends none"):
            warn_unseen_intents(cfg, eval_spec(cfg)[0])
    for fine in ([*intents, "eval_method=ours_ti"], ["eval_every=1"],
                 ["algo.intent_rollouts=2", "eval_every=0"]):
        cfg = compose_train(*TINY_TRAIN, *fine)
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            warn_unseen_intents(cfg, eval_spec(cfg)[0])


def test_bf16_training_on_a_cpu_that_emulates_it_warns(monkeypatch):
    """algo.precision=bf16 runs at about half float32's speed where bfloat16 is emulated:
    training says so; on a CPU with native bf16, with float32, or on CUDA it stays quiet."""
    import maipp_bench.train as train_mod
    from maipp_bench.hardware import machine_name

    monkeypatch.setattr(train_mod, "native_bf16", lambda: False)
    with pytest.warns(UserWarning, match="without native bfloat16.*algo.precision=float32"):
        train_mod.warn_emulated_bf16("bf16", "cpu")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        train_mod.warn_emulated_bf16("float32", "cpu")
        train_mod.warn_emulated_bf16("bf16", "cuda")
        monkeypatch.setattr(train_mod, "native_bf16", lambda: True)
        train_mod.warn_emulated_bf16("bf16", "cpu")
    assert f"{os.cpu_count()} cores, native bf16: " in machine_name()  # cards name the CPU


def test_init_starts_from_a_networks_weights(tiny_checkpoint, tmp_path):
    from maipp_bench.train import train

    # lr = 0: the update cannot move the weights, so the run ends where init put it.
    path = train(compose_train(*TINY_TRAIN, "total_updates=1", "algo.lr=0",
                               f"init={tiny_checkpoint}"), tmp_path / "ft")
    got, want = torch.load(path, weights_only=False), torch.load(tiny_checkpoint,
                                                                  weights_only=False)
    assert got["update"] == 1
    for name, tensor in want["core"].items():
        assert torch.equal(got["core"][name], tensor), name
    with pytest.raises(ValueError, match="is not this run's"):
        train(compose_train(*TINY_TRAIN, "total_updates=1", "algo.net.embed_dim=16",
                            f"init={tiny_checkpoint}"), tmp_path / "bad")


def test_a_fine_tunes_card_accounts_for_the_network_it_started_from(tiny_checkpoint,
                                                                    tmp_path):
    import json

    from maipp_bench.protocol.protocol import file_sha256
    from maipp_bench.train import _command_init, train

    # Older checkpoints: the init of the run's first command, as typed (quotes and all).
    assert _command_init("python -m maipp_bench.train init=a.pt 'export_note=x y'") == "a.pt"
    assert _command_init("python -m maipp_bench.train init=a.pt export_note='it's'") == "a.pt"
    assert _command_init("python -m maipp_bench.train algo=ours") is None

    def card(name: str) -> dict:
        return json.loads((tmp_path / f"{name}.json").read_text())

    base = torch.load(tiny_checkpoint, weights_only=False)
    run = train(compose_train(*TINY_TRAIN, "total_updates=1", f"init={tiny_checkpoint}",
                              f"export={tmp_path / 'ft.pt'}"), tmp_path / "ft")
    ft = card("ft")
    assert ft["init"]["path"] == str(tiny_checkpoint)
    assert ft["init"]["sha256"] == file_sha256(tiny_checkpoint)
    assert ft["init"]["update"] == base["update"] == 2 and "init" not in ft["init"]
    assert ft["frames_with_init"] == ft["frames"] + base["frames"] > ft["frames"]
    assert ft["wall_s_with_init"] == pytest.approx(ft["wall_s"] + base["wall_s"])
    # Resumed (without init= on its command line), the run still knows where it began.
    train(compose_train(*TINY_TRAIN, f"resume={run}", "total_updates=2",
                        f"export={tmp_path / 'ft2.pt'}"), tmp_path / "ft")
    assert card("ft2")["init"] == ft["init"] and card("ft2")["updates"] == 2
    # A fine-tune of the fine-tune: the whole chain, and the training behind it all.
    train(compose_train(*TINY_TRAIN, "total_updates=1", f"init={tmp_path / 'ft.pt'}",
                        f"export={tmp_path / 'ft3.pt'}"), tmp_path / "ft3")
    ft3 = card("ft3")
    assert ft3["init"]["sha256"] == file_sha256(tmp_path / "ft.pt")
    assert ft3["init"]["init"]["sha256"] == file_sha256(tiny_checkpoint)
    assert ft3["frames_with_init"] == ft3["frames"] + ft["frames"] + base["frames"]
    # The init of an exported network gone (as a shipped file's run folder is), its card
    # still accounts for it.
    gone = tmp_path / "gone.pt"
    gone.write_bytes(tiny_checkpoint.read_bytes())
    train(compose_train(*TINY_TRAIN, "total_updates=1", f"init={gone}",
                        f"export={tmp_path / 'kept.pt'}"), tmp_path / "kept")
    gone.unlink()
    train(compose_train(*TINY_TRAIN, "total_updates=1", f"init={tmp_path / 'kept.pt'}",
                        f"export={tmp_path / 'ft4.pt'}"), tmp_path / "ft4")
    assert card("ft4")["init"]["init"] == card("kept")["init"]
    assert card("ft4")["init"]["init"]["sha256"] == file_sha256(tiny_checkpoint)
    assert card("ft4")["frames_with_init"] == card("ft4")["frames"] + ft["frames"] + base[
        "frames"]


def test_weighted_averages_mix_networks_and_refuse_different_ones(tiny_checkpoint,
                                                                   tmp_path):
    base = torch.load(tiny_checkpoint, weights_only=False)
    other = base | {"core": {k: v + 1 if v.is_floating_point() else v
                             for k, v in base["core"].items()}}
    torch.save(other, tmp_path / "other.pt")
    mixed = average_policies([tiny_checkpoint, tmp_path / "other.pt"], weights=[0.25, 0.75])
    for k, v in base["core"].items():
        if v.is_floating_point():
            assert torch.allclose(mixed["core"][k], v + 0.75)
    assert average_policies([tiny_checkpoint])["core"].keys() == base["core"].keys()
    with pytest.raises(ValueError, match="2 networks"):
        average_policies([tiny_checkpoint, tmp_path / "other.pt"], weights=[1.0])
    wider = base | {"core": base["core"] | {"net.embed.bias": torch.zeros(3)}}
    torch.save(wider, tmp_path / "wider.pt")
    with pytest.raises(ValueError, match="different networks"):
        average_policies([tiny_checkpoint, tmp_path / "wider.pt"])


def test_snapshots_keep_every_evaluated_update(tiny_checkpoint, tmp_path):
    from maipp_bench.train import train

    assert not (tiny_checkpoint.parent / "snapshots").exists()  # off by default
    run = tmp_path / "run"
    train(compose_train(*TINY_TRAIN, "total_updates=4", "eval_every=2", "eval_episodes=2",
                        "keep_snapshots=true"), run)
    snaps = sorted((run / "snapshots").glob("*.pt"))
    assert [s.name for s in snaps] == ["update_0002.pt", "update_0004.pt"]
    best = torch.load(run / "best.pt", weights_only=False)
    snap = run / "snapshots" / f"update_{best['update']:04d}.pt"
    core, payload = load_core(snap)
    assert payload["update"] == best["update"] and "optimizer" not in payload
    for name, tensor in core.state_dict().items():  # the same weights as best.pt
        assert torch.equal(tensor, best["core"][name])
    last, _ = load_core(snaps[-1])
    final = torch.load(run / "checkpoint.pt", weights_only=False)["core"]
    assert all(torch.equal(t, final[n]) for n, t in last.state_dict().items())

    # A kept snapshot exported afterwards from the finished run: its weights, the curve
    # up to it (in the file and the card), and the note on how it was chosen.
    import json

    out = tmp_path / "shipped" / "snap.pt"
    threads = torch.get_num_threads()
    try:  # exported with two threads: the card still names the one the run trained with
        train(compose_train(*TINY_TRAIN, f"resume={run / 'checkpoint.pt'}", "total_updates=0",
                            f"export={out}", "export_from=2", "export_note=picked by hand",
                            "threads=2"), run)
    finally:
        torch.set_num_threads(threads)
    core, payload = load_core(out)
    snap2, _ = load_core(snaps[0])
    assert all(torch.equal(t, snap2.state_dict()[n]) for n, t in core.state_dict().items())
    card = json.loads(out.with_suffix(".json").read_text())
    assert card["selected_update"] == card["updates"] == payload["update"] == 2
    assert [r["update"] for r in card["curve"]] == [r["update"] for r in payload["curve"]] == [
        1, 2]
    assert card["run_continued_to"] == 4 and "exported_with" in card  # (argv: pytest's here)
    assert card["selected_by"].endswith("update 2, picked by hand")
    assert ", 1 torch thread(s), device cpu" in card["machine"]
    assert torch.load(run / "checkpoint.pt", weights_only=False)["update"] == 4  # untouched
    with pytest.raises(FileNotFoundError, match=r"updates \[2, 4\]"):
        train(compose_train(*TINY_TRAIN, f"resume={run / 'checkpoint.pt'}",
                            "total_updates=0", f"export={out}", "export_from=3"), run)
    # The average of the kept snapshots of a span: their mean weights, the last one's
    # curve, and the updates averaged in the file and the card.
    avg = tmp_path / "shipped" / "avg.pt"
    train(compose_train(*TINY_TRAIN, f"resume={run / 'checkpoint.pt'}", "total_updates=0",
                        f"export={avg}", "export_from=2-4"), run)
    core, payload = load_core(avg)
    cores = [load_core(s)[0].state_dict() for s in snaps]
    for name, tensor in core.state_dict().items():
        assert torch.equal(tensor, torch.stack([c[name] for c in cores]).mean(0))
    assert not torch.equal(cores[0]["net.embed.weight"], cores[1]["net.embed.weight"])
    card = json.loads(avg.with_suffix(".json").read_text())
    assert card["averaged_updates"] == payload["averaged_updates"] == [2, 4]
    assert card["selected_update"] == payload["update"] == 4
    assert "uniform average" in card["selected_by"] and len(card["curve"]) == 4
    for bad in ("newest", "4-2", "2-3-4", "-4"):
        with pytest.raises(ValueError, match=f"export_from='{bad}'"):
            train(compose_train(*TINY_TRAIN, f"export_from={bad}"), tmp_path / "bad")
    with pytest.raises(FileNotFoundError, match=r"update_0001.pt; snapshots kept .*\[2, 4\]"):
        train(compose_train(*TINY_TRAIN, f"resume={run / 'checkpoint.pt'}",
                            "total_updates=0", f"export={avg}", "export_from=1-4"), run)
    # A snapshot this run will not keep is an error before training, not after it.
    for extra in ([], ["keep_snapshots=true", "eval_every=2", "total_updates=2"]):
        for span in ("3", "2-3"):
            with pytest.raises(ValueError, match=r"keeps no snapshot of update [23]\b"):
                train(compose_train(*TINY_TRAIN, f"export={out}", f"export_from={span}",
                                    *extra), tmp_path / "bad")
            assert not (tmp_path / "bad" / "checkpoint.pt").exists()
    with pytest.warns(UserWarning, match="without export"):
        train(compose_train(*TINY_TRAIN, "total_updates=0", "export_from=last"),
              tmp_path / "noop")


def test_snapshots_every_n_updates_need_no_evaluation(tmp_path):
    """snapshot_every keeps snapshots without held-out evaluations (eval_every=0), and the
    same weights as a run that evaluates: evaluation never touches training's randomness."""
    from maipp_bench.train import train

    quiet, evaluated = tmp_path / "quiet", tmp_path / "evaluated"
    train(compose_train(*TINY_TRAIN, "total_updates=4", "keep_snapshots=true",
                        "snapshot_every=2"), quiet)
    train(compose_train(*TINY_TRAIN, "total_updates=4", "keep_snapshots=true",
                        "eval_every=2", "eval_episodes=2"), evaluated)
    names = [p.name for p in sorted((quiet / "snapshots").glob("*.pt"))]
    assert names == ["update_0002.pt", "update_0004.pt"] and not (quiet / "best.pt").exists()
    for name in names:
        a, b = (load_core(run / "snapshots" / name)[0].state_dict() for run in (quiet, evaluated))
        assert all(torch.equal(t, b[n]) for n, t in a.items())
    # An export of a span that snapshot_every will keep is accepted before training
    # (snapshot_every alone keeps them: it implies keep_snapshots).
    out = tmp_path / "avg.pt"
    train(compose_train(*TINY_TRAIN, "total_updates=2", "snapshot_every=1", f"export={out}",
                        "export_from=1-2"), tmp_path / "s1")
    assert load_core(out)[1]["averaged_updates"] == [1, 2]
    for bad, match in ((["keep_snapshots=true"], "keeps nothing with eval_every=0"),
                       (["snapshot_every=-1"], "snapshot_every=-1: must be >= 0")):
        with pytest.raises(ValueError, match=match):
            train(compose_train(*TINY_TRAIN, *bad), tmp_path / "bad")
        assert not (tmp_path / "bad" / "checkpoint.pt").exists()


def _train_throughput(*args: str) -> subprocess.CompletedProcess:
    script = Path(__file__).parents[1] / "benchmarks" / "train_throughput.py"
    return subprocess.run([sys.executable, str(script), *args], capture_output=True,
                          text=True, timeout=300)


def test_train_throughput_launches_needs_cuda():
    """--launches counts CUDA kernel launches: on the CPU it is a clear error, not zeros."""
    proc = _train_throughput(*TINY_TRAIN, "--updates", "1", "--launches")
    assert proc.returncode == 2 and "--launches counts CUDA kernel launches" in proc.stderr


@pytest.mark.cuda
def test_train_throughput_launches_counts_the_collection(tmp_path):
    """--launches on CUDA: kernel launches, copies and device time per env step of one
    more collection, with intents in it; the kernels' time fits inside its wall time."""
    if not torch.cuda.is_available():
        pytest.skip("CUDA is not available")
    out = tmp_path / "t.json"
    proc = _train_throughput(*TINY_TRAIN, "device=cuda", "algo.intent_rollouts=2",
                             "algo.intent_depth=2", "--updates", "1", "--launches",
                             "--out", str(out))
    assert proc.returncode == 0, proc.stderr[-3000:]
    counts = json.loads(out.read_text())["collection_launches"]
    assert counts["launches_per_step"] > 0 and counts["copies_per_step"] > 0
    assert 0 < counts["device_ms_per_step"] < counts["profiled_wall_ms_per_step"]


def test_train_throughput_profile_names_where_the_update_goes(tmp_path):
    """benchmarks/train_throughput.py --profile reports every phase it names as found in
    the profile (a renamed function would show 0 calls), the intents inside collection."""
    out = tmp_path / "t.json"
    proc = _train_throughput(*TINY_TRAIN, "algo.intent_rollouts=2", "algo.intent_depth=2",
                             "--updates", "1", "--profile", "--out", str(out))
    assert proc.returncode == 0, proc.stderr[-3000:]
    phases = json.loads(out.read_text())["profile"]
    assert all(p["calls"] > 0 for p in phases.values()), phases
    seconds = [p["seconds"] for p in phases.values()]
    assert seconds[1] <= seconds[0]  # teammates' intents are part of collection


def test_curve_compare_weights_per_episode_fields_by_the_episodes_that_ended(monkeypatch):
    """benchmarks/curve_compare.py: a per-episode mean (trace_final) counts each update by
    the episodes that ended in it, so updates in which none ended (NaN, as after a fresh
    start with reset_every > 1) count nothing; other fields are plain means."""
    monkeypatch.syspath_prepend(str(Path(__file__).parents[1] / "benchmarks"))
    from curve_compare import window_means

    rows = [{"episodes": 0, "trace_final": math.nan, "reward_per_decision": 0.1, "frames": 1},
            {"episodes": 3, "trace_final": 10.0, "reward_per_decision": 0.3, "frames": 2},
            {"episodes": 4, "trace_final": 30.0, "reward_per_decision": 0.5, "frames": 3},
            {"episodes": 4, "trace_final": math.nan, "reward_per_decision": 0.7, "frames": 4}]
    assert window_means(rows, "trace_final", 3, 0)["1-"] == pytest.approx(15.0)  # (3*10+30)/4
    assert math.isnan(window_means(rows, "trace_final", 3, 0)["4-"])
    assert window_means(rows, "reward_per_decision", 2, 0) == pytest.approx(
        {"1-": 0.2, "3-": 0.6})


def test_score_draw_waits_for_the_run_then_scores_its_policy_file_in_passes(tmp_path):
    """benchmarks/score_draw.py: an unfinished run is refused without --wait; with it, the
    script waits for the 'end' stamp, then scores final.pt as ours_ti one pass of budgets
    at a time (B = 5 before B = 2 here), stamps each pass into score.txt, and ship_draw.py
    ships those stamps with the board they made (not with the run alone)."""
    script = Path(__file__).parents[1] / "benchmarks" / "score_draw.py"
    run = tmp_path / "run"
    (run / "stage2").mkdir(parents=True)
    shutil.copyfile(Path(algos.__file__).parent.parent / "checkpoints" / "ours.pt",
                    run / "final.pt")
    for name in ("final.json", "stage2/curve.jsonl"):
        (run / name).write_text("{}")
    (run / "wall.txt").write_text("start 2026-12-05T02:28:28Z\n")
    args = [sys.executable, str(script), str(run), "--episodes", "1", "--pass", "5",
            "--pass", "2", "--workers", "1"]
    proc = subprocess.run(args, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and "not a finished train_2h.sh run" in proc.stderr
    proc = subprocess.run([*args[:-4], "--pass", "5", "--workers", "1"], capture_output=True,
                          text=True, timeout=60)
    assert proc.returncode == 2 and "a budget is in more than one pass" in proc.stderr
    waiting = subprocess.Popen([*args, "--wait", "--poll", "0.1"], stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True)
    try:
        with pytest.raises(subprocess.TimeoutExpired):
            waiting.wait(timeout=1)
        assert not (run / "score.txt").exists()
        with open(run / "wall.txt", "a") as f:
            f.write("end 2026-12-05T04:24:00Z\n")
        _, err = waiting.communicate(timeout=300)
    finally:
        waiting.kill()
    assert waiting.returncode == 0, err[-3000:]
    kinds = [line.split()[:-1] for line in (run / "score.txt").read_text().splitlines()]
    assert kinds == [["score_start"], ["scored", "B=5"], ["scored", "B=2"]]
    rows = [json.loads(line) for line in
            (tmp_path / "run_results" / "subset-1" / "risk_aware" / "ours_ti.jsonl").open()]
    assert [r["setting"] for r in rows] == ["budget=5.0", "budget=2.0"]
    digest = hashlib.sha256((run / "final.pt").read_bytes()).hexdigest()
    assert {r["checkpoint_sha256"] for r in rows} == {digest}
    cards = tmp_path / "cards"
    cards.mkdir()
    assert _ship_draw(run, cards / "draw").returncode == 0
    assert not (cards / "draw_score.txt").exists()  # the stamps travel with their board
    board = tmp_path / "run_results" / "subset-1" / "leaderboards"
    assert _ship_draw(run, cards / "draw", "--board", str(board), "--force").returncode == 0
    assert (cards / "draw_score.txt").read_text() == (run / "score.txt").read_text()
    # a subset's episodes are not the protocol's: --results refuses to ship them
    proc = _ship_draw(run, cards / "draw", "--results", str(tmp_path / "run_results" /
                                                          "subset-1"), "--force")
    assert proc.returncode == 2
    assert "holds 1 of the protocol's 300 budget=5.0 episodes" in proc.stderr


def test_train_throughput_splits_a_card_where_its_stages_change(tmp_path):
    """benchmarks/train_throughput.py --card ... --split stages: stage 1's last update is
    where the frames an update double (train_2h.sh's stage 2), not typed; update numbers
    out of the curve or not numbers are clear errors."""
    curve = tmp_path / "curve.jsonl"
    frames = [1280, 2560, 3840, 6400, 8960]
    curve.write_text("".join(json.dumps({"update": u, "frames": f, "decisions": 10,
                                         "wall_s": 10.0 * u}) + "\n"
                             for u, f in enumerate(frames, 1)))
    proc = _train_throughput("--card", str(curve), "--split", "stages")
    assert proc.returncode == 0, proc.stderr
    segments = json.loads(proc.stdout)["segments"]
    assert [s["updates"] for s in segments] == ["1-3", "4-5", "1-5"]
    assert [s["frames_per_s"] for s in segments] == [128.0, 256.0, 8960 / 50]
    for split, message in ((["5"], "increasing updates in 1..4"),
                           (["x"], "update numbers or 'stages'")):
        proc = _train_throughput("--card", str(curve), "--split", *split)
        assert proc.returncode == 2 and message in proc.stderr


def test_train_throughput_prints_a_snapshot_cards_run_continued_to(tmp_path):
    """--card on an exported snapshot's card also prints ``run_continued_to`` (the docs cite
    it for the updates stage 3 made); a card without the field prints no such key."""
    rows = [{"update": u, "frames": 1280 * u, "decisions": 10, "wall_s": 10.0 * u}
            for u in (1, 2, 3)]
    for extra, expected in (({"run_continued_to": 5}, 5), ({}, None)):
        card = tmp_path / "card.json"
        card.write_text(json.dumps({"curve": rows, **extra}))
        proc = _train_throughput("--card", str(card))
        assert proc.returncode == 0, proc.stderr
        out = json.loads(proc.stdout)
        assert out.get("run_continued_to") == expected
        assert [s["updates"] for s in out["segments"]] == ["1-3"]


def test_draw_figures_reprints_a_shipped_draws_figures():
    """benchmarks/draw_figures.sh PREFIX reprints the figures results.md writes up for a
    shipped draw from its committed cards (here the fifty-second's); no card is exit 2."""
    root = Path(__file__).parents[1]
    script = root / "benchmarks" / "draw_figures.sh"
    prefix = "docs/cards/ours_2h_intent_seed49_bf16_final_h2_pop2_wide8"
    proc = subprocess.run(["bash", str(script), prefix], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert "end 2026-12-06T04:23:22Z" in proc.stdout  # the wall stamps
    assert '"run_continued_to": 36' in proc.stdout  # stage 3's updates, from its card
    # the final choice kept its start by 0.92 on held-out episodes (docs: "by 0.92")
    assert "update 35 (outputs/h52/avg.pt): 29.37, +0.92 behind the chosen" in proc.stdout
    assert "| `ours_ti` | 35.0 ± 9.2 | 22.8 ± 5.5 | 131.0 ± 29.9 | 60.1 ± 18.4 |" in proc.stdout
    assert "minus catnipp_ti  -0.11 ± 0.37" in proc.stdout  # B = 5, paired
    proc = subprocess.run(["bash", str(script), "docs/cards/no_such_draw"],
                          capture_output=True, text=True)
    assert proc.returncode == 2 and "no card docs/cards/no_such_draw.json" in proc.stderr


def test_draw_rate_families_keep_a_quoted_switch_whole(monkeypatch):
    """benchmarks/draw_rate.py counts draws per recipe family from the table's recipe cell:
    ``FINAL_BUDGETS="2 4 5"`` is one switch, so those WIDE=8 draws are a family of their
    own, and a WIDE=8 cell without it stays WIDE=8's."""
    monkeypatch.syspath_prepend(str(Path(__file__).parents[1] / "benchmarks"))
    from draw_rate import family
    from draw_signals import switches

    cell = '`WIDE=8 POP=2 SELECT=1 FINAL=1 FINAL_BUDGETS="2 4 5"`, bf16, 115.0 min'
    assert switches(cell) == {"WIDE=8", "POP=2", "SELECT=1", "FINAL=1",
                              "FINAL_BUDGETS=2 4 5"}  # as the shell splits it
    assert family(cell) == 'WIDE=8 FINAL_BUDGETS="2 4 5"'
    assert family("`WIDE=8 POP=2 SELECT=1 FINAL=1`, bf16") == "WIDE=8"
    assert family('`WIDE=8 FINAL_BUDGETS="2 5"`, bf16') == "WIDE=8"  # another value
    assert family("`POP=2 SELECT=1`, bf16") == "POP=2"
    assert family("the defaults, float32") == "fixed"  # no code span, no switches
