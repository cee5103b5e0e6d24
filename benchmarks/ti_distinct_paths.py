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
from maipp_bench.protocol.protocol import Setting, load_protocol
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


def ti_parser(description: str) -> argparse.ArgumentParser:
    """The options of the scripts that replay protocol episodes of a learned TI method."""
    p = argparse.ArgumentParser(description=description)
    p.add_argument("--suite", default="risk_aware")
    p.add_argument("--method", default="ours_ti")
    p.add_argument("--budgets", type=float, nargs="+", default=[2.0, 5.0])
    p.add_argument("--instances", type=int, default=30)
    return p


class ProtocolEpisodes:
    """The suite's first ``args.instances`` instances and first trial for ``args.method``,
    one thread and the eval CLI's allocator setting, with the committed board's spot checks
    to compare replays against."""

    def __init__(self, args: argparse.Namespace) -> None:
        keep_freed_memory()  # as the eval CLI does
        torch.set_num_threads(1)
        self.suite = load_protocol().suite(args.suite)
        board = ROOT / "leaderboards" / f"{args.suite}.json"
        self.spots = {(r["method"], r["setting"]): r["spot_check"] for r in
                      json.loads(board.read_text())["rows"]} if board.exists() else {}
        self.method, self.spec = args.method, algos.get_method(args.method)
        self.instances = list(self.suite.instance_seeds[:args.instances])
        self.trial = self.suite.trial_seeds[0]
        self.settings = [s for s in self.suite.settings
                         if s.as_dict().get("budget") in args.budgets]
        print(f"{platform.machine()}, torch {torch.__version__}, 1 thread; {args.suite} "
              f"{args.method}, {len(self.instances)} episodes per setting (trial "
              f"{self.trial})")

    def play(self, setting: Setting, distinct: bool = True) -> dict:
        """One replay of the episodes at ``setting`` (see :func:`play`)."""
        return play(self.spec, self.suite.env_config(setting), self.instances, self.trial,
                    distinct)

    def same_as_board(self, setting: Setting, trace: list[float]) -> str:
        """", board's spot check identical" (or DIFFERENT) when the board holds these
        episodes' spot check, else ""."""
        spot = self.spots.get((self.method, setting.key))
        if not (spot and spot["trial"] == self.trial and spot["instances"] == self.instances):
            return ""
        return ", board's spot check " + ("identical" if trace == spot["trace"]
                                          else "DIFFERENT")


def main() -> None:
    args = ti_parser(__doc__.splitlines()[0]).parse_args()
    episodes = ProtocolEpisodes(args)
    for setting in episodes.settings:
        every = episodes.play(setting, distinct=False)
        once = episodes.play(setting, distinct=True)
        same = "identical" if once["trace"] == every["trace"] else "DIFFERENT"
        same += episodes.same_as_board(setting, once["trace"])
        print(f"  {setting.key}: every rollout {every['wall']:6.1f} s, {every['rows']:8d} "
              f"rows | distinct paths {once['wall']:6.1f} s, {once['rows']:8d} rows | "
              f"{every['wall'] / once['wall']:.2f}x time, {every['rows'] / once['rows']:.2f}x "
              f"rows, Tr(P_f) {same}")


if __name__ == "__main__":
    main()
