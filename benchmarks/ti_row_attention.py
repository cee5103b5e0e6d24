"""TI(a, j) evaluation with the encoder's row attention against the layer's own.

``AttentionPolicyNet.encode`` calls :func:`~maipp_bench.algos.attention.attend_rows`, the
``nn.MultiheadAttention`` function for keys = values without its sequence-first copies
(the same bits in float32). This script plays the same protocol episodes (the suite's
first ``--instances`` instances, its first trial) with a learned TI method through both,
alternating which goes first over ``--pairs`` pairs, and reports the planning seconds and
whether every episode's Tr(P_f) is identical, both ways and to the committed board's spot
check of that row (the same episodes when ``--instances`` is the suite's 30).

Usage:
    OMP_NUM_THREADS=1 python benchmarks/ti_row_attention.py --suite risk_aware \
        --method ours_ti --budgets 2 5
"""

from __future__ import annotations

import argparse
import json
import platform
from pathlib import Path
from unittest import mock

import torch
from ti_distinct_paths import play

from maipp_bench import algos
from maipp_bench.algos import attention
from maipp_bench.allocator import keep_freed_memory
from maipp_bench.protocol.protocol import load_protocol

ROOT = Path(__file__).resolve().parent.parent


def layer_attention(attn, query, kv):
    """What ``encode`` called before: the layer's own module (sequence-first inside)."""
    return attn(query, kv, kv, need_weights=False)[0]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--suite", default="risk_aware")
    p.add_argument("--method", default="ours_ti")
    p.add_argument("--budgets", type=float, nargs="+", default=[2.0, 5.0])
    p.add_argument("--instances", type=int, default=30)
    p.add_argument("--pairs", type=int, default=2)
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
          f"{args.method}, {len(instances)} episodes per setting (trial {trial}), "
          f"{args.pairs} pairs, alternating order")
    for setting in suite.settings:
        if setting.as_dict().get("budget") not in args.budgets:
            continue
        cfg = suite.env_config(setting)
        walls: dict[str, float] = {"layer": 0.0, "rows": 0.0}
        traces = {}
        for i in range(args.pairs):
            for way in (("layer", "rows") if i % 2 == 0 else ("rows", "layer")):
                fn = layer_attention if way == "layer" else attention.attend_rows
                with mock.patch.object(attention, "attend_rows", fn):
                    out = play(spec, cfg, instances, trial, distinct=True)
                walls[way] += out["wall"] / args.pairs
                traces.setdefault(way, out["trace"])
                assert out["trace"] == traces[way], "a replay changed its own episodes"
        same = "identical" if traces["layer"] == traces["rows"] else "DIFFERENT"
        spot = spots.get((args.method, setting.key))
        if spot and spot["trial"] == trial and spot["instances"] == instances:
            same += ", board's spot check " + (
                "identical" if traces["rows"] == spot["trace"] else "DIFFERENT")
        print(f"  {setting.key}: layer's attention {walls['layer']:6.1f} s | row attention "
              f"{walls['rows']:6.1f} s | {walls['layer'] / walls['rows']:.2f}x, Tr(P_f) {same}")


if __name__ == "__main__":
    main()
