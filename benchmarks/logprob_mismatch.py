"""How far PPO's first ratio is from 1 when nothing has been learnt yet, per precision.

PPO's ratio is pi_theta(a) / pi_old(a), where pi_old(a) is the log-probability the
collector stored while sampling and pi_theta(a) the one the loss recomputes on the same
decision rows. Before the first optimiser step both come from the same weights, so the
ratio should be exactly 1: every departure is rounding, and it spends part of the clip
range (0.2) before any learning. This script collects one batch with the configured
training set-up, then recomputes every row's log-probability the way the loss does (train
mode, minibatches of ``algo.minibatch``) and reports, for each precision given, side by
side on the same weights and the same update seed:

* mean and max of |log pi_theta(a) - log pi_old(a)| over the batch's decision rows;
* the share of rows whose ratio is already outside [1 - clip, 1 + clip];
* the floor of that: the loss's log-probs in two minibatch orders against each other
  (what rounding alone gives when the computation's structure is the same);
* the loss's own ``kl_approx`` and ``clip_fraction`` on its first minibatch;
* for scale, the collector's log-probs against the same rows' in float32.

``--init`` takes a trained policy file (a peaked policy shows rounding differently from a
fresh one). Hydra overrides as for training.

Usage:
    python benchmarks/logprob_mismatch.py algo.intent_rollouts=4 \
        --init maipp_bench/checkpoints/ours.pt
"""

from __future__ import annotations

import argparse
import json
import os
import platform

import torch
from hydra import compose, initialize_config_module
from omegaconf import OmegaConf

import maipp_bench.train as train_mod
from maipp_bench.algos.modules import LOG_PROB_KEY, PRECISIONS, full_precision
from maipp_bench.algos.ppo import build_learner
from maipp_bench.allocator import keep_freed_memory
from maipp_bench.envs.config import MAIPPConfig


def mismatch(learner, rows, minibatch: int, clip: float) -> dict:
    """|log-prob the loss computes - log-prob the collector stored| over ``rows``, and the
    floor: the loss's log-probs in two minibatch orders against each other."""
    now, again = (learner.action_log_prob(rows, minibatch, torch.Generator().manual_seed(seed))
                  .double() for seed in (0, 1))
    with torch.no_grad():
        first = learner.loss(rows[:minibatch].clone())
    signed = now - rows.get(LOG_PROB_KEY).double()
    d, ratio = signed.abs(), signed.exp()
    return {"rows": rows.numel(), "mean_abs_dlogp": float(d.mean()),
            "max_abs_dlogp": float(d.max()),
            "outside_clip": float(((ratio > 1 + clip) | (ratio < 1 - clip)).double().mean()),
            "loss_vs_loss_mean_abs": float((now - again).abs().mean()),
            "loss_vs_loss_max_abs": float((now - again).abs().max()),
            "first_kl_approx": float(first["kl_approx"]),
            "first_clip_fraction": float(first["clip_fraction"])}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("overrides", nargs="*")
    p.add_argument("--init", help="a policy file to start from (default: fresh weights)")
    p.add_argument("--precisions", nargs="+", default=sorted(PRECISIONS),
                   choices=sorted(PRECISIONS))
    p.add_argument("--update", type=int, default=0, help="the update seed to collect with")
    args = p.parse_args()
    with initialize_config_module("maipp_bench.conf", version_base=None):
        cfg = compose("train", overrides=args.overrides)
    keep_freed_memory()
    torch.set_num_threads(cfg.threads)
    torch.manual_seed(cfg.seed)
    env_cfg = MAIPPConfig.from_dict(OmegaConf.to_container(cfg.env))
    learner = build_learner(cfg.algo, env_cfg.node_encoding_dim, env_cfg.interest_threshold,
                            cfg.device)
    if args.init:
        train_mod.init_weights(learner, args.init, cfg.algo, env_cfg.interest_threshold)
    env, collector, _ = train_mod.make_collection(cfg, env_cfg, learner)
    nets = learner.precision_modules()  # the same weights in each precision
    table = {}
    for name in args.precisions:
        for m in nets:
            m.autocast = PRECISIONS[name]
        torch.manual_seed(args.update)
        env.set_seed(args.update)
        collector.reset()
        learner.core.eval()
        batch = collector.next()
        rows = train_mod.collected_decisions(learner, batch, cfg.algo)
        table[name] = mismatch(learner, rows, cfg.algo.minibatch, cfg.algo.clip_epsilon)
        # the size of the rounding itself: the same rows' log-probs in float32
        with full_precision(*nets):
            exact = learner.action_log_prob(rows, cfg.algo.minibatch).double()
        table[name]["vs_float32_mean_abs"] = float(
            (exact - rows.get(LOG_PROB_KEY).double()).abs().mean())
    collector.shutdown()
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, "
          f"{torch.get_num_threads()} torch thread(s); overrides {args.overrides}, "
          f"init {args.init or 'fresh'}")
    print("| precision | rows | loss vs collector: mean abs d log p | max | ratio outside "
          "clip | loss vs loss (other order): mean | max | loss kl_approx (1st minibatch) "
          "| loss clip_fraction (1st minibatch) | collector vs float32: mean |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for name, r in table.items():
        print(f"| {name} | {r['rows']} | {r['mean_abs_dlogp']:.2e} | {r['max_abs_dlogp']:.2e} "
              f"| {r['outside_clip']:.4f} | {r['loss_vs_loss_mean_abs']:.2e} "
              f"| {r['loss_vs_loss_max_abs']:.2e} | {r['first_kl_approx']:.2e} "
              f"| {r['first_clip_fraction']:.4f} | {r['vs_float32_mean_abs']:.2e} |")
    print(json.dumps(table))


if __name__ == "__main__":
    main()
