"""The two-hour draws' B = 2 column against a recomputed `sga_rrt_0.3_0.4` row.

docs/results.md's table "All two-hour runs, one table" gives each draw's B = 2 mean minus
the board's `sga_rrt_0.3_0.4` B = 2 mean, ± the unpaired standard error, as the board was
when the draw was scored. When that row is recomputed (`sga_rrt` v3, docs/protocol.md),
each entry moves by the change of the row's mean, and its error by the change of the
row's share of it: se_new² = se_old² - s_old²/n_old + s_new²/n_new (the draw's own share
is unchanged). Prints every draw's entry before and after, and whether it still leads
(negative: ahead) and by more than two standard errors. Entries marked "(v3)" were
scored against the recomputed row already (draws after the recompute) and do not move.

Usage:
    python benchmarks/draw_b2_recheck.py --before 3358ddd            # against the working tree
    python benchmarks/draw_b2_recheck.py --before 3358ddd --after 83fd56b
"""

from __future__ import annotations

import argparse
import math

import boards
from draw_signals import table_rows

METHOD, SETTING = "sga_rrt_0.3_0.4", "budget=2.0"


V3_MARK = "(v3)"  # a B = 2 cell scored against the recomputed row


def b2_column() -> dict[int, tuple[float, float, bool]]:
    """Each draw's "B = 2 minus `sga_rrt_0.3_0.4`" cell: (difference, standard error,
    whether it is against the recomputed row already)."""
    column = {}
    for draw, cells in table_rows().items():
        cell = cells[7]
        diff, se = (float(x) for x in cell.removesuffix(V3_MARK).split("±"))
        column[draw] = (diff, se, cell.endswith(V3_MARK))
    return column


def standing(diff: float, se: float) -> str:
    """"ahead" (negative: the draw's mean is lower) or "behind", and whether by 2 se."""
    return ("ahead" if diff < 0 else "behind") + (" (by 2 se)" if abs(diff) > 2 * se else "")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--before", required=True, help="git revision of the board the draws used")
    p.add_argument("--after", help="git revision of the recomputed board (default: the tree)")
    args = p.parse_args()
    old = boards.keyed(boards.at_revision("risk_aware", args.before))[(METHOD, SETTING)]
    new_board = (boards.at_revision("risk_aware", args.after) if args.after
                 else boards.load("risk_aware"))
    new = boards.keyed(new_board)[(METHOD, SETTING)]
    shift = old["trace_mean"] - new["trace_mean"]
    print(f"{METHOD} {SETTING}: {old['trace_mean']:.3f} ± {old['trace_std']:.2f} -> "
          f"{new['trace_mean']:.3f} ± {new['trace_std']:.2f}; every unmarked entry moves by "
          f"{shift:+.2f}")
    flips = []
    for draw, (diff, se, scored_after) in sorted(b2_column().items()):
        if scored_after:  # against the old row it would have been diff - shift
            print(f"  draw {draw:>2}: {diff:+6.1f} ± {se:.1f} (scored against it; "
                  f"{diff - shift:+.1f} against the old row)  {standing(diff, se)}")
            continue
        var = se**2 - old["trace_std"] ** 2 / old["n"] + new["trace_std"] ** 2 / new["n"]
        d2, se2 = diff + shift, math.sqrt(max(var, 0.0))
        now, was = standing(d2, se2), standing(diff, se)
        if now != was:
            flips.append(draw)
        print(f"  draw {draw:>2}: {diff:+6.1f} ± {se:.1f} -> {d2:+6.1f} ± {se2:.1f}  {now}"
              + ("" if now == was else f"   was {was}"))
    print(f"entries whose standing changed: {flips or 'none'}")


if __name__ == "__main__":
    main()
