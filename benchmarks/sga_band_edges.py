"""Where `sga_rrt`'s episodes turn on another CPU (docs/protocol.md, "Where the `sga_rrt`
episodes turn"): plays instances of one setting's first trial with the candidate band's
edges [a, b] moved by small offsets, next to the board's spot check; with ``--margins``,
also the smallest relative gap between the best candidate path's Tr(P) and the next
different one (a near tie there would flip on last bits) and the branch lengths that sit
within 1e-14 of an edge (where the last bit decides candidacy).

The edges are moved by patching the planner in this process only (a diagnostic: the
method and its fingerprint are unchanged). Written for `sga_rrt` v2: the figures
docs/protocol.md quotes from it are v2's against v2's boards; since v3 (the cause of
those episodes, "`sga_rrt` v3") it plays v3 against v3's rows.

Usage:
    python benchmarks/sga_band_edges.py --method sga_rrt_0.9_1.0 --setting budget=2.0 \\
        --instances 353904 365460 --offsets 0,0 0,-1e-12 0,1e-12 -1e-12,0 1e-12,0
    python benchmarks/sga_band_edges.py --method sga_rrt_0.3_0.4 --setting budget=2.0 \\
        --episodes 30 --margins
"""

from __future__ import annotations

import argparse
import contextlib
from collections import Counter

import boards
import torch

import maipp_bench.algos.sga_rrt as sga
from maipp_bench import algos
from maipp_bench.protocol.protocol import load_protocol
from maipp_bench.protocol.runner import run_chunk


@contextlib.contextmanager
def moved_edges(da: float, db: float):
    """Every SGARRTPolicy built inside uses [a + da, b + db]."""
    init = sga.SGARRTPolicy.__init__

    def shifted(self, *args, **kwargs):
        init(self, *args, **kwargs)
        self.a, self.b = self.a + da, self.b + db

    sga.SGARRTPolicy.__init__ = shifted
    try:
        yield
    finally:
        sga.SGARRTPolicy.__init__ = init


@contextlib.contextmanager
def recorded(gaps: list[torch.Tensor], edges: Counter):
    """Record each decision's candidate Tr(P) and the branch lengths near the edges."""
    trace, grow = sga.interest_trace, sga.SGARRTPolicy._grow

    def trace_rec(*args, **kwargs):
        tr = trace(*args, **kwargs)
        gaps.append(tr.to(torch.float64).clone())
        return tr

    def grow_rec(self, *args, **kwargs):
        nodes, parent, cost, depth = grow(self, *args, **kwargs)
        for edge in (self.a, self.b):
            for c in cost[(cost - edge).abs() < 1e-14].tolist():
                edges[(edge, repr(c))] += 1
        return nodes, parent, cost, depth

    sga.interest_trace, sga.SGARRTPolicy._grow = trace_rec, grow_rec
    try:
        yield
    finally:
        sga.interest_trace, sga.SGARRTPolicy._grow = trace, grow


def smallest_gap(decisions: list[torch.Tensor], env_index: int) -> float:
    """Over an episode's decisions: the best candidate's relative lead on the next
    different finite Tr(P) (exact ties go to the first index, the same on any CPU)."""
    best = float("inf")
    for tr in decisions:
        v = tr[env_index]
        v = torch.sort(v[torch.isfinite(v)]).values
        above = v[v > v[0]] if v.numel() else v
        if above.numel():
            best = min(best, float((above[0] - v[0]) / v[0].abs().clamp_min(1e-300)))
    return best


def sga_target(p: argparse.ArgumentParser, args: argparse.Namespace):
    """``(suite, setting, method spec)`` of ``--suite``, ``--setting`` and an ``sga_rrt``
    ``--method``; a bad one ends the script with the parser's error."""
    if not args.method.startswith("sga_rrt"):
        p.error(f"--method must be an sga_rrt method, got {args.method!r}")
    suite = load_protocol(1).suite(args.suite)
    try:
        setting = suite.setting(args.setting)
    except ValueError as e:
        p.error(str(e))
    return suite, setting, algos.get_method(args.method)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--suite", default="risk_aware")
    p.add_argument("--method", required=True, help="an sga_rrt_<a>_<b> method")
    p.add_argument("--setting", required=True, help="a setting key of the suite")
    group = p.add_mutually_exclusive_group(required=True)
    group.add_argument("--instances", type=int, nargs="+")
    group.add_argument("--episodes", type=int, help="the suite's first N instances")
    p.add_argument("--offsets", nargs="+", default=["0,0"], metavar="DA,DB",
                   help="edge offsets to play, each 'da,db'")
    p.add_argument("--margins", action="store_true")
    args = p.parse_args()
    suite, setting, spec = sga_target(p, args)
    seeds = args.instances or list(suite.instance_seeds[: args.episodes])
    row = boards.keyed(boards.load(args.suite))[(args.method, args.setting)]
    board = dict(zip(row["spot_check"]["instances"], row["spot_check"]["trace"]))
    torch.set_num_threads(1)
    for offsets in args.offsets:
        da, db = (float(x) for x in offsets.split(","))
        gaps: list[torch.Tensor] = []
        edges: Counter = Counter()
        with (torch.inference_mode(), moved_edges(da, db),
              recorded(gaps, edges) if args.margins else contextlib.nullcontext()):
            rows = run_chunk(spec, suite.env_config(setting), seeds, suite.trial_seeds[0])
        print(f"edges moved by ({da:g}, {db:g}):")
        for j, r in enumerate(rows):
            ref = board.get(r["instance"])
            same = "" if ref is None else ("  = board" if abs(r["trace"] - ref) <= 1e-9 * abs(ref)
                                           else f"  board {ref:.4f}")
            gap = f"  smallest Tr gap {smallest_gap(gaps, j):.1e}" if args.margins else ""
            print(f"  instance {r['instance']:>7}  Tr(P_f) {r['trace']:.4f}{same}{gap}")
        for (edge, length), n in sorted(edges.items()):
            print(f"  branch length {length} against edge {edge}: {n} nodes")


if __name__ == "__main__":
    main()
