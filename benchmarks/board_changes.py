"""What a recompute changed on a board, read from two versions of it: per row, the mean
Tr(P_f) before -> after and its relative change, eval's verdict on the first trial
(``leaderboard.reproduces``) and the first-trial episodes that differ, by position in the
suite's instance order. These are the "old -> new" figures of docs/protocol.md's table
"Boards recomputed under the pinned kernels" and the episode lists of "Another CPU".

Usage:
    python benchmarks/board_changes.py --suite agents10 --before 2f3000e --after 0c34417
    python benchmarks/board_changes.py --suite comm --before 90311d0   # against the working tree
"""

from __future__ import annotations

import argparse
import math

import boards

from maipp_bench.protocol.leaderboard import reproduces

REL = 1e-9  # eval's tolerance for a first-trial episode on another CPU or other kernels


def changes(before: dict, after: dict) -> list[dict]:
    """One dict per row of ``after`` that ``before`` also has: ``method``, ``setting``,
    ``old`` and ``new`` mean, ``rel`` change, eval's ``verdict`` and the positions of the
    first-trial episodes that differ beyond :data:`REL` (``differing``)."""
    old_rows = boards.keyed(before)
    verdicts = {(m, s): v for m, s, v in reproduces(after, before, rel=REL)}
    out = []
    for key, row in boards.keyed(after).items():
        old = old_rows.get(key)
        if old is None:
            continue
        theirs = dict(zip(old["spot_check"]["instances"], old["spot_check"]["trace"]))
        differing = [i for i, (inst, v) in enumerate(zip(row["spot_check"]["instances"],
                                                        row["spot_check"]["trace"]))
                     if inst in theirs and not math.isclose(v, theirs[inst], rel_tol=REL,
                                                           abs_tol=REL)]
        out.append({"method": key[0], "setting": key[1], "old": old["trace_mean"],
                    "new": row["trace_mean"],
                    "rel": abs(row["trace_mean"] - old["trace_mean"]) / abs(old["trace_mean"]),
                    "verdict": verdicts[key], "differing": differing})
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--suite", required=True)
    p.add_argument("--before", required=True, metavar="REV", help="git revision of the old board")
    p.add_argument("--after", metavar="REV", help="git revision of the new board "
                   "(default: the board in --leaderboards)")
    p.add_argument("--leaderboards", default="leaderboards")
    p.add_argument("--moved", type=float, default=1e-12,
                   help="list rows whose mean moved by more than this, relative")
    args = p.parse_args()
    after = (boards.at_revision(args.suite, args.after) if args.after
             else boards.load(args.suite, args.leaderboards))
    rows = changes(boards.at_revision(args.suite, args.before), after)
    for c in rows:
        if c["rel"] > args.moved or c["differing"]:
            episodes = ", ".join(map(str, c["differing"])) or "none"
            print(f"{c['method']:>26} {c['setting']:>28}  {c['old']:.3f} -> {c['new']:.3f}"
                  f"  ({c['rel']:.1e})  first-trial episodes differing: {episodes}"
                  f"  [{c['verdict']}]")
    rest = [c["rel"] for c in rows if c["rel"] <= args.moved]
    print(f"{len(rows)} rows compared; the {len(rest)} others moved by at most "
          f"{max(rest, default=0.0):.1e} relative")


if __name__ == "__main__":
    main()
