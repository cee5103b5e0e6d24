"""Unpaired differences of a leaderboard's means: the "difference of the board's means ±
the unpaired standard error" figures of docs/results.md, read from a committed board
alone (no stored episodes needed; ``paired_subset.py --subset`` gives the paired ones,
which the shared worlds make smaller, where both methods' episodes are stored).

For every setting of the board: ``--method``'s mean Tr(P_f) minus each ``--against``
method's, ± sqrt(s1² / n1 + s2² / n2).

Usage:
    python benchmarks/board_diff.py --suite risk_aware --method ours_ti \\
        --against sga_rrt_0.3_0.4 greedy catnipp_ti catnipp_greedy oracle
    python benchmarks/board_diff.py --suite comm --method ours_ti --against oracle
    python benchmarks/board_diff.py --suite risk_aware --method ours_ti --against catnipp_ti \\
        --method-from outputs/cand_boards   # a candidate's rows, run apart from the board
"""

from __future__ import annotations

import argparse
from pathlib import Path

import boards


def differences(board: dict, method: str, against: list[str]) -> list[dict]:
    """One dict per setting: ``setting``, ``mean`` of ``method`` and, per other method,
    ``(difference, standard error)``; settings where ``method`` has no row are skipped."""
    rows = boards.keyed(board, [method, *against])
    out = []
    for setting in dict.fromkeys(s for m, s in rows if m == method):
        mine = rows[method, setting]
        entry = {"setting": setting, "mean": mine["trace_mean"], "diff": {}}
        for other in against:
            theirs = rows.get((other, setting))
            if theirs is None:
                continue
            se = (mine["trace_std"] ** 2 / mine["n"]
                  + theirs["trace_std"] ** 2 / theirs["n"]) ** 0.5
            entry["diff"][other] = (mine["trace_mean"] - theirs["trace_mean"], se)
        out.append(entry)
    return out


def with_rows_from(board: dict, method: str, directory: str | Path) -> dict:
    """``board`` with ``method``'s rows replaced by those of the same suite's board in
    ``directory`` (a candidate's, run with ``eval --leaderboards DIR --fresh-board``);
    exits if that board has none."""
    theirs = [r for r in boards.load(board["suite"], directory)["rows"] if r["method"] == method]
    if not theirs:
        raise SystemExit(f"{method} has no row on {directory}/{board['suite']}.json")
    return board | {"rows": [r for r in board["rows"] if r["method"] != method] + theirs}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--suite", required=True)
    p.add_argument("--method", required=True)
    p.add_argument("--against", nargs="+", required=True)
    p.add_argument("--leaderboards", default="leaderboards")
    p.add_argument("--method-from", metavar="DIR",
                   help="read --method's rows from the board in DIR instead (e.g. a "
                        "candidate's, run with eval --leaderboards DIR --fresh-board)")
    args = p.parse_args()
    board = boards.load(args.suite, args.leaderboards)
    if args.method_from:
        board = with_rows_from(board, args.method, args.method_from)
    for entry in differences(board, args.method, args.against):
        cells = "  ".join(f"{m} {d:+.1f} ± {se:.1f}" for m, (d, se) in entry["diff"].items())
        print(f"{entry['setting']:>28}  {args.method} {entry['mean']:.1f}  minus: {cells}")


if __name__ == "__main__":
    main()
