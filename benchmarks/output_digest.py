"""Digest of everything a seeded ``MAIPPEnv`` rollout produces, to check that a speed-up
keeps the environment's bits (committed leaderboard rows are reproduced bit for bit).

For each configuration: E envs under seeded random masked actions with automatic reset,
for ``--steps`` steps; every key of the step output and of the next root, the belief
caches and Tr(P) of every env go into one sha256. Run it on two checkouts and compare:

    OMP_NUM_THREADS=1 python benchmarks/output_digest.py > after.txt
    (cd ../before && OMP_NUM_THREADS=1 python ../main/benchmarks/output_digest.py) > before.txt
    diff before.txt after.txt && echo same bits

(``maipp_bench`` is imported from the working directory when it holds the package, so
the second line digests the other checkout's code.) Digests depend on the CPU's vector
units and on torch's kernels: compare runs on one machine only.
"""

from __future__ import annotations

import argparse
import hashlib
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path.cwd()))  # the checkout run from, not an installed copy
import maipp_bench  # noqa: E402
from maipp_bench.envs import MAIPPConfig, MAIPPEnv  # noqa: E402

CONFIGS = {
    "default": dict(budget=3.0),
    "float32": dict(budget=3.0, dtype="float32"),
    "comm0.3": dict(budget=2.0, comm_range=0.3),
    "aoi_prune": dict(budget=2.0, aoi_enabled=True, prune_risky_nodes=True),
    "agents10": dict(budget=2.0, n_agents=10),
}


def _update(h, td) -> None:
    for key in sorted(td.keys(True, True), key=str):
        h.update(str(key).encode())
        h.update(td.get(key).contiguous().cpu().numpy().tobytes())


def digest(overrides: dict, n_envs: int, steps: int) -> str:
    """sha256 of a seeded auto-reset rollout of ``MAIPPConfig(**overrides)``."""
    env = MAIPPEnv(MAIPPConfig(**overrides), batch_size=[n_envs])
    env.set_seed(3)
    torch.manual_seed(0)
    td = env.reset()
    h = hashlib.sha256()
    for _ in range(steps):
        nxt, td = env.step_and_maybe_reset(env.rand_action(td))
        _update(h, nxt)
        _update(h, td)
        st = env.episode
        for t in (st.belief.cross, st.belief.factor_inv, st.belief.mu, st.belief.sigma2,
                  st.trace, st.objective):
            h.update(t.contiguous().cpu().numpy().tobytes())
    return h.hexdigest()


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--envs", type=int, default=96)
    p.add_argument("--steps", type=int, default=260)
    p.add_argument("--configs", nargs="+", default=list(CONFIGS), choices=list(CONFIGS))
    args = p.parse_args()
    if args.envs < 1 or args.steps < 1:
        p.error("--envs and --steps must be >= 1")
    print(f"# maipp_bench from {Path(maipp_bench.__file__).parent}", file=sys.stderr)
    for name in args.configs:
        print(name, digest(CONFIGS[name], args.envs, args.steps), flush=True)


if __name__ == "__main__":
    main()
