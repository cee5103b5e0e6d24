"""Why the belief keeps L^-1 and the project runs one torch thread per process.

Measures, side by side in one run, for a batch of E small systems (as in ``GPBelief.add``):

* a batched triangular solve ``torch.linalg.solve_triangular(L, B)`` against the matrix
  product ``L^-1 @ B`` that replaces it, for identity-padded factors (the unused rows of a
  belief's buffers) and for dense ones;
* a short ``MAIPPEnv`` rollout;

each with 1 and 2 torch threads. Usage::

    python benchmarks/linalg_threads.py            # E = 1024, n = 49, P = 3
    python benchmarks/linalg_threads.py --envs 256 --repeats 5
"""

from __future__ import annotations

import argparse
import platform

import torch
from bench_timing import seconds_per_call

from maipp_bench.envs import MAIPPConfig, MAIPPEnv


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--envs", type=int, default=1024)
    p.add_argument("--size", type=int, default=49)
    p.add_argument("--points", type=int, default=3)
    p.add_argument("--repeats", type=int, default=3)
    args = p.parse_args()
    e, n, k = args.envs, args.size, args.points
    gen = torch.Generator().manual_seed(0)
    a = torch.randn(e, n, n, generator=gen, dtype=torch.float64)
    dense = torch.linalg.cholesky(a @ a.transpose(-1, -2) + n * torch.eye(n, dtype=torch.float64))
    padded = torch.eye(n, dtype=torch.float64).expand(e, n, n).clone()
    padded[:, :5, :5] = dense[:, :5, :5]
    rhs = torch.randn(e, n, k, generator=gen, dtype=torch.float64)
    rhs_padded = rhs.clone()
    rhs_padded[:, 5:] = 0.0
    inv_dense, inv_padded = torch.linalg.inv(dense), torch.linalg.inv(padded)
    print(f"# {platform.processor() or platform.machine()}, torch {torch.__version__}, "
          f"E={e}, n={n}, P={k}; milliseconds per call (mean of {args.repeats})")
    print("| operation | 1 thread | 2 threads |")
    print("|---|---:|---:|")
    rows = {
        "solve_triangular, identity-padded L": lambda: torch.linalg.solve_triangular(
            padded, rhs_padded, upper=False),
        "L^-1 @ B, identity-padded": lambda: inv_padded @ rhs_padded,
        "solve_triangular, dense L": lambda: torch.linalg.solve_triangular(
            dense, rhs, upper=False),
        "L^-1 @ B, dense": lambda: inv_dense @ rhs,
    }
    env = MAIPPEnv(MAIPPConfig(budget=2.0), batch_size=[8])

    def rollout() -> None:
        torch.manual_seed(0)
        env.set_seed(0)
        env.rollout(60, break_when_any_done=False)

    rows["MAIPPEnv rollout, E=8, 60 steps"] = rollout
    previous = torch.get_num_threads()
    for name, fn in rows.items():
        cells = []
        for threads in (1, 2):
            torch.set_num_threads(threads)
            cells.append(f"{1e3 * seconds_per_call(fn, args.repeats):.1f}")
        print(f"| {name} | {cells[0]} | {cells[1]} |")
    torch.set_num_threads(previous)


if __name__ == "__main__":
    main()
