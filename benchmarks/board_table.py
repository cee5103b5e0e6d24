"""A committed board as the markdown tables of docs/results.md: one line per method, Tr(P_f)
mean ± std per setting, traps per episode and planning seconds per episode (the mean over
the settings shown), read from ``leaderboards/<suite>.json`` alone.

Usage:
    python benchmarks/board_table.py --suite risk_aware
    python benchmarks/board_table.py --suite comm --setting-prefix comm_range=0.6
    python benchmarks/board_table.py --suite agents10 --methods ours_ti catnipp_ti greedy
"""

from __future__ import annotations

import argparse

import boards


def table(board: dict, methods: list[str] | None = None, setting_prefix: str = "") -> str:
    """Markdown table of ``board``'s rows whose setting starts with ``setting_prefix``, in
    the board's order of methods and settings (``methods`` picks and orders them)."""
    rows = {k: r for k, r in boards.keyed(board, methods).items()
            if k[1].startswith(setting_prefix)}
    if not rows:
        raise SystemExit(f"no setting of the {board['suite']} board starts with {setting_prefix!r}")
    on_board = list(dict.fromkeys(m for m, _ in rows))
    settings = list(dict.fromkeys(s for _, s in rows))
    lines = [
        "| method | " + " | ".join(settings) + " | traps / episode | planning s / episode |",
        "|---|" + "---:|" * (len(settings) + 2),
    ]
    for method in methods or on_board:
        mine = [rows.get((method, s)) for s in settings]
        cells = [f"{r['trace_mean']:.1f} ± {r['trace_std']:.1f}" if r else "-" for r in mine]
        present = [r for r in mine if r]
        traps = [f"{r['traps_mean']:.2f}" for r in present]
        traps = traps[:1] if len(set(traps)) == 1 else traps  # one figure when all agree
        planning = sum(r["planning_s_per_episode"] for r in present) / len(present)
        lines.append(f"| `{method}` | " + " | ".join(cells)
                     + f" | {' / '.join(traps)} | {planning:.2f} |")
    return "\n".join(lines)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--suite", required=True)
    p.add_argument("--methods", nargs="+", help="these methods, in this order (default: all)")
    p.add_argument("--setting-prefix", default="",
                   help="only settings starting with this, e.g. comm_range=0.3")
    p.add_argument("--leaderboards", default="leaderboards")
    args = p.parse_args()
    board = boards.load(args.suite, args.leaderboards)
    print(table(board, args.methods, args.setting_prefix))


if __name__ == "__main__":
    main()
