"""Steady-state milliseconds per ``MAIPPEnv`` step of the checkout run from, to compare
two checkouts side by side (alternate them: these machines drift).

E envs, a random masked policy with auto-reset (``env.rand_action`` +
``env.step_and_maybe_reset``), ``--warmup`` untimed steps so that episodes of every age
are in the batch, then ``--steps`` timed ones; one torch thread. For example, three
alternating pairs of the checkouts ``../before`` and ``.``:

    for i in 1 2 3; do
      (cd ../before && OMP_NUM_THREADS=1 python ../main/benchmarks/step_time.py)
      OMP_NUM_THREADS=1 python benchmarks/step_time.py
    done

(``maipp_bench`` is imported from the working directory when it holds the package.)
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

# The checkout run from, not an installed copy. Self-contained (not env_profile's
# steady_env): it must import whatever an older checkout's package holds.
sys.path.insert(0, str(Path.cwd()))
import maipp_bench  # noqa: E402
from maipp_bench.envs import MAIPPConfig, MAIPPEnv  # noqa: E402


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--envs", type=int, default=1024)
    p.add_argument("--warmup", type=int, default=150)
    p.add_argument("--steps", type=int, default=100)
    p.add_argument("--dtype", default="float64", choices=["float64", "float32"])
    args = p.parse_args()
    if min(args.envs, args.warmup + 1, args.steps) < 1:
        p.error("--envs and --steps must be >= 1, --warmup >= 0")
    torch.set_num_threads(1)
    env = MAIPPEnv(MAIPPConfig(budget=3.0, dtype=args.dtype), batch_size=[args.envs])
    env.set_seed(0)
    torch.manual_seed(0)
    td = env.reset()
    for _ in range(args.warmup):
        _, td = env.step_and_maybe_reset(env.rand_action(td))
    t0 = time.perf_counter()
    for _ in range(args.steps):
        _, td = env.step_and_maybe_reset(env.rand_action(td))
    ms = 1000 * (time.perf_counter() - t0) / args.steps
    print(f"{ms:.1f} ms per step  E={args.envs} {args.dtype}  "
          f"maipp_bench from {Path(maipp_bench.__file__).parent}")


if __name__ == "__main__":
    main()
