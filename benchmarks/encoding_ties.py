"""Which protocol roadmaps' Laplacian encodings change with the tie-safe sign rule of
``laplacian_encoding`` (2026-11-27)? The earlier rule took each eigenvector's sign from its
largest-magnitude entry, and where two entries tie in magnitude with opposite signs
(symmetric roadmaps) float rounding, which differs with the batch, chose. This replays the
encodings as the learned methods compute them for the protocol (one batch per chunk: a
(suite, setting, trial) over the suite's instances; risk-unaware methods' pruned
roadmaps too) under both rules and counts the episodes whose encodings differ: none means
the committed leaderboard rows stand.

Usage:
    python benchmarks/encoding_ties.py [--dim 32] [--suites risk_aware agents10 comm aoi_bias]
"""

from __future__ import annotations

import argparse

import torch
from tensordict import TensorDict

from maipp_bench.envs.maipp_env import MAIPPEnv
from maipp_bench.envs.roadmap import SIGN_TIE, laplacian_encoding
from maipp_bench.protocol.protocol import load_protocol


def earlier_rule(neighbors: torch.Tensor, valid: torch.Tensor, dim: int) -> torch.Tensor:
    """The encoding with the sign of each vector's argmax-magnitude entry (before the fix)."""
    enc = laplacian_encoding(neighbors, valid, dim)  # signs fixed by the tie-safe rule
    peak = enc.gather(-2, enc.abs().argmax(-2, keepdim=True))
    return enc * torch.where(peak < 0, -1.0, 1.0)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--dim", type=int, default=32, help="the networks' pe_dim (paper: 32)")
    p.add_argument("--suites", nargs="+", default=["risk_aware", "agents10", "comm", "aoi_bias"])
    args = p.parse_args()
    protocol = load_protocol(1)
    for name in args.suites:
        suite = protocol.suites[name]
        changed = tied = total = 0
        for setting in suite.settings:
            base = suite.env_config(setting)
            for prune in (False, True) if base.risk_enabled else (False,):  # task_config's
                cfg = base.replace(prune_risky_nodes=prune)
                for trial in suite.trial_seeds:
                    e = len(suite.instance_seeds)
                    env = MAIPPEnv(cfg, batch_size=[e])
                    env.reset(TensorDict(
                        instance_seed=torch.tensor(suite.instance_seeds, dtype=torch.int64),
                        trial_seed=torch.full((e,), trial, dtype=torch.int64),
                        batch_size=[e]))
                    rm = env.episode.roadmap
                    new = laplacian_encoding(rm.neighbors, rm.neighbor_valid, args.dim)
                    old = earlier_rule(rm.neighbors, rm.neighbor_valid, args.dim)
                    changed += int((new != old).flatten(1).any(1).sum())
                    top2 = new.abs().topk(2, dim=-2).values  # [E, 2, dim]
                    tied += int(((top2[:, 0] - top2[:, 1]) <= SIGN_TIE).any(-1).sum())
                    total += e
        print(f"{name}: of {total} chunk episodes (settings x trials x instances; pruned "
              f"roadmaps too), {tied} have a vector whose sign the two largest magnitudes "
              f"tie for, {changed} encode differently", flush=True)


if __name__ == "__main__":
    main()
