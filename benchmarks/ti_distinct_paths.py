"""TI(a, j) with the network run once per distinct sampled path, against once per rollout.

Rollouts of one deciding agent that sampled the same moves so far hold the same state
(belief, node, budget, LSTM), so :func:`~maipp_bench.algos.rollouts.fantasy_rollouts`
runs the network on one row per distinct path and copies its output to the others. This
script plays the same protocol episodes (the suite's first ``--instances`` instances, its
first trial) with a learned TI method both ways, one after the other, and reports the planning
seconds, the rows the network ran on, and whether every episode's Tr(P_f) is identical,
both ways and to the committed board's spot check of that row (the same episodes when
``--instances`` is the suite's 30).

Usage:
    OMP_NUM_THREADS=1 python benchmarks/ti_distinct_paths.py --suite risk_aware \
        --method ours_ti --budgets 2 5
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path
from unittest import mock

import torch

from maipp_bench import algos
from maipp_bench.algos import rollouts
from maipp_bench.algos.modules import AttentionCore
from maipp_bench.allocator import keep_freed_memory
from maipp_bench.protocol.protocol import load_protocol
from maipp_bench.protocol.runner import run_chunk

ROOT = Path(__file__).resolve().parent.parent


def play(spec, cfg, instances: list[int], trial: int, distinct: bool) -> dict:
    rows = [0]
    real = AttentionCore.forward

    def counted(self, *args):
        rows[0] += args[0].shape[0]
        return real(self, *args)

    with (mock.patch.object(AttentionCore, "forward", counted),
          rollouts.path_merging(distinct), torch.inference_mode()):
        t0 = time.perf_counter()
        out = run_chunk(spec, cfg, instances, trial, checkpoint=str(spec.checkpoint(None)))
        wall = time.perf_counter() - t0
    return {"wall": wall, "rows": rows[0], "trace": [r["trace"] for r in out]}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--suite", default="risk_aware")
    p.add_argument("--method", default="ours_ti")
    p.add_argument("--budgets", type=float, nargs="+", default=[2.0, 5.0])
    p.add_argument("--instances", type=int, default=30)
    args = p.parse_args()
    keep_freed_memory()  # as the eval CLI does
    torch.set_num_threads(1)
    suite = load_protocol().suite(args.suite)
    board = ROOT / "leaderboards" / f"{args.suite}.json"
    spots = {(r["method"], r["setting"]): r["spot_check"] for r in
             json.loads(board.read_text())["rows"]} if board.exists() else {}
    spec = algos.get_method(args.method)
    instances, trial = list(suite.instance_seeds[:args.instances]), suite.trial_seeds[0]
    print(f"{platform.machine()}, torch {torch.__version__}, 1 thread; {args.suite} "
          f"{args.method}, {len(instances)} episodes per setting (trial {trial})")
    for setting in suite.settings:
        if setting.as_dict().get("budget") not in args.budgets:
            continue
        cfg = suite.env_config(setting)
        every = play(spec, cfg, instances, trial, distinct=False)
        once = play(spec, cfg, instances, trial, distinct=True)
        same = "identical" if once["trace"] == every["trace"] else "DIFFERENT"
        spot = spots.get((args.method, setting.key))
        if spot and spot["trial"] == trial and spot["instances"] == instances:
            same += ", board's spot check " + (
                "identical" if once["trace"] == spot["trace"] else "DIFFERENT")
        print(f"  {setting.key}: every rollout {every['wall']:6.1f} s, {every['rows']:8d} "
              f"rows | distinct paths {once['wall']:6.1f} s, {once['rows']:8d} rows | "
              f"{every['wall'] / once['wall']:.2f}x time, {every['rows'] / once['rows']:.2f}x "
              f"rows, Tr(P_f) {same}")


if __name__ == "__main__":
    main()
