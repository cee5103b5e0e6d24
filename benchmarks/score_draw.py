"""Score a ``benchmarks/train_2h.sh`` draw under the protocol, as soon as it has finished.

A draw's policy file (``OUT/final.pt``, or without FINAL=1 stage 3's average ``avg.pt``)
is scored as ``ours_ti`` on the ``risk_aware`` suite in passes of budgets: by default B = 5
and 4 first (where most draws miss, so their verdict comes first), then B = 2 and 3. The
first pass writes a fresh board (``--fresh-board``: only this draw's rows), the next ones
add their rows to it. Each pass is one ``python -m maipp_bench.eval`` process, whose
output goes through; the UTC time of each pass's start and end is appended to
``OUT/score.txt`` (``benchmarks/ship_draw.py`` ships it beside the wall-clock stamps).

With ``--wait`` it waits for the run's ``end`` stamp first, so that it can be launched
beside the training run and score it the minute it ends; without, an unfinished run is
an error. ``--episodes N`` scores a quick subset instead (stored and reported apart from
full runs, under ``RESULTS/subset-N``).

Usage:
    python benchmarks/score_draw.py outputs/h45 --wait > outputs/h45_eval.log 2>&1
        # results in outputs/h45_results, the board in outputs/h45_boards
    python benchmarks/ship_draw.py outputs/h45 docs/cards/PREFIX --board outputs/h45_boards \\
        --results outputs/h45_results
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

from ship_draw import METHOD, SUITE, finished, policy_file

PASSES = ((5.0, 4.0), (2.0, 3.0))


def stamp(run: Path, what: str) -> str:
    """Append ``what`` with the UTC time to ``run``/score.txt; the line written."""
    line = f"{what} {datetime.now(timezone.utc):%Y-%m-%dT%H:%M:%SZ}"
    with open(run / "score.txt", "a") as f:
        f.write(line + "\n")
    return line


def commands(run: Path, results: Path, boards: Path, passes: list[tuple[float, ...]],
             workers: int, episodes: int | None = None) -> list[list[str]]:
    """One ``maipp_bench.eval`` command line per pass of budgets."""
    common = ["--suite", SUITE, "--methods", METHOD, "--checkpoint",
              f"{METHOD}={policy_file(run)}", "--out", str(results), "--leaderboards",
              str(boards), "--workers", str(workers), "--no-progress",
              *(["--episodes", str(episodes)] if episodes is not None else [])]
    return [[sys.executable, "-m", "maipp_bench.eval", *common, "--budgets",
             *(f"{b:g}" for b in budgets), *(["--fresh-board"] if i == 0 else [])]
            for i, budgets in enumerate(passes)]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path, help="train_2h.sh's OUT_DIR")
    parser.add_argument("--results", type=Path,
                        help="per-episode results (default: OUT_DIR_results beside it)")
    parser.add_argument("--boards", type=Path,
                        help="the board's folder (default: OUT_DIR_boards beside it)")
    parser.add_argument("--pass", dest="passes", type=float, nargs="+", action="append",
                        metavar="B", help="budgets of one pass, in order (repeatable; "
                        "default: --pass 5 4 --pass 2 3)")
    parser.add_argument("--workers", type=int, default=2, help="eval's worker processes")
    parser.add_argument("--episodes", type=int, help="quick subset of N episodes a setting")
    parser.add_argument("--wait", action="store_true",
                        help="wait for the run's 'end' stamp instead of refusing an "
                        "unfinished run")
    parser.add_argument("--poll", type=float, default=20.0, help="seconds between looks")
    args = parser.parse_args(argv)
    passes = [tuple(p) for p in args.passes] if args.passes else list(PASSES)
    budgets = [b for p in passes for b in p]
    if len(set(budgets)) != len(budgets):
        parser.error(f"a budget is in more than one pass: {budgets}")
    if not args.run.is_dir():
        parser.error(f"{args.run} is not a folder")
    while not finished(args.run):
        if not args.wait:
            print(f"score_draw.py: {args.run} is not a finished train_2h.sh run (no 'end' "
                  f"line in {args.run / 'wall.txt'}); --wait waits for it", file=sys.stderr)
            return 2
        time.sleep(args.poll)
    results = args.results or args.run.with_name(args.run.name + "_results")
    boards = args.boards or args.run.with_name(args.run.name + "_boards")
    print(stamp(args.run, "score_start"), flush=True)
    for budgets, command in zip(passes, commands(args.run, results, boards, passes,
                                                 args.workers, args.episodes)):
        print("python", *command[1:], flush=True)  # as a user would type it
        code = subprocess.run(command).returncode
        if code:
            print(stamp(args.run, f"score_failed B={','.join(f'{b:g}' for b in budgets)}"),
                  flush=True)
            return code
        print(stamp(args.run, f"scored B={','.join(f'{b:g}' for b in budgets)}"), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
