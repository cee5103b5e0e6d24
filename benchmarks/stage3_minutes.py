"""Stage 3's minutes under a deadline: ``DEADLINE`` of ``benchmarks/train_2h.sh``.

Stages 1-2 stop after the minutes typed for them, but the held-out choices after them play
a fixed number of episodes, and those take longer on a slower box. Two draws ran past two
hours that way (122.9 and 126.8 minutes; docs/results.md, "All two-hour runs, one
table"). With a deadline, stage 3 gets what is left of it once the minutes already spent
(since ``start`` in ``OUT_DIR/wall.txt``) and a reserve for what follows stage 3 are taken
out, and never more than the minutes typed for it:

    reserve = ALLOWANCE (stage 3's start-up and saves, the exports)
              + with FINAL=1, the final choice's estimate: the start choice's own seconds
                (``select.json``) x the final choice's work / the start choice's work
                x MARGIN, where a choice's work is candidates x sum over budgets of
                episodes x budget (an episode's decisions grow with its budget).

``--calibrate`` prints how far the estimate (MARGIN 1) was from finished draws' final
choices. Where fewer than FLOOR minutes are left, stage 3 could not make the 5 updates of
its first snapshot on the slowest box measured, so the answer is 0: no stage 3, and the
start choice is the policy file (as with ``STAGE3=0``).

stdout is the minutes alone (0: skip stage 3); the reasoning goes to stderr and, with
``--out``, to a JSON file.

Usage:
    python benchmarks/stage3_minutes.py --wall OUT/wall.txt --minutes 26 --deadline 120 \\
        --select OUT/select.json --final --final-episodes 64 --out OUT/deadline.json
    python benchmarks/stage3_minutes.py --calibrate docs/cards/ours_2h_intent_seed32_final_h2_pop2
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
from datetime import datetime, timezone
from pathlib import Path

# Stage 3's start-up, saves and last update past its minutes, and the exports after it
# (avg.pt, start.pt): 0.3-1.5 minutes in the seventeen POP=2 FINAL=1 draws to the thirty-ninth
# (``--calibrate`` on every docs/cards/*_final_h2_pop2 prefix: their wall.txt between the two
# choices, less stage 3's 26 minutes and the final choice).
ALLOWANCE = 2.0
# The final choice's seconds over the estimate of them (MARGIN 1) ran 0.84-1.40 in those
# draws (``--calibrate``): the largest, rounded up.
MARGIN = 1.5
# The slowest stage 3 measured made about one update a minute (float32, AMD EPYC): its
# first snapshot (update 5) and some slack.
FLOOR = 8.0
FINAL_BUDGETS = (4.0, 5.0)  # benchmarks/final_choice.sh's default (its FINAL_BUDGETS)
FINAL_CANDIDATES = 2  # stage 3's start and its average


def work(choice: dict) -> float:
    """Candidates x sum over budgets of episodes x budget, of a select_snapshot.py JSON."""
    budgets = choice["budget"] if isinstance(choice["budget"], list) else [choice["budget"]]
    episodes = choice["episodes"]
    if not isinstance(episodes, list):
        episodes = [episodes] * len(budgets)
    return len(choice["candidates"]) * sum(e * b for e, b in zip(episodes, budgets))


def scaled_seconds(select: dict, final: dict) -> float:
    """A finished final choice's seconds as estimated from the start choice's (MARGIN 1):
    the work of each (``work``) scales them; ``--calibrate`` compares it with the real."""
    return select["seconds"] * work(final) / work(select)


def final_seconds(select: dict, final_episodes: int,
                  budgets: tuple[float, ...] = FINAL_BUDGETS) -> float:
    """The final choice's seconds estimated from the start choice's (MARGIN 1): the work
    (episodes x budget) scales them."""
    planned = FINAL_CANDIDATES * sum(final_episodes * b for b in budgets)
    return select["seconds"] * planned / work(select)


def started(wall: Path) -> datetime:
    """The run's start, the first line of train_2h.sh's wall.txt ("start <UTC time>")."""
    first = wall.read_text().split("\n", 1)[0].split()
    if len(first) != 2 or first[0] != "start":
        raise ValueError(f"{wall}: the first line is not 'start <time>': {' '.join(first)!r}")
    return datetime.fromisoformat(first[1].replace("Z", "+00:00"))


def plan(elapsed: float, minutes: float, deadline: float, select: dict | None, final: bool,
         final_episodes: int, final_budgets: tuple[float, ...] = FINAL_BUDGETS) -> dict:
    """Stage 3's minutes (0: skip it) and the figures they come from."""
    estimate = None
    if final:
        if select is None:
            raise ValueError("FINAL=1 under a deadline needs the start choice's seconds "
                             "(SELECT=1's select.json) to estimate the final choice's")
        estimate = final_seconds(select, final_episodes, final_budgets) * MARGIN / 60
    reserve = ALLOWANCE + (estimate or 0.0)
    left = deadline - elapsed - reserve
    given = 0.0 if left < FLOOR else min(minutes, left)
    return {"deadline": deadline, "elapsed": round(elapsed, 2), "typed": minutes,
            "allowance": ALLOWANCE, "final_estimate": None if estimate is None
            else round(estimate, 2), "margin": MARGIN, "floor": FLOOR, "left": round(left, 2),
            "minutes": round(given, 2)}


def stamps(wall: Path) -> dict[str, datetime]:
    """The last time of each kind of line of a wall.txt ("selected <path> <time>",
    "stage1 done <time> <dir>", ...)."""
    found = {}
    for line in wall.read_text().splitlines():
        time = re.search(r"\d{4}-\d\d-\d\dT\S+Z", line)
        if time:
            found[line.split()[0]] = datetime.fromisoformat(time[0].replace("Z", "+00:00"))
    return found


def calibrate(prefixes: list[str], minutes: float) -> None:
    """Each finished draw's final choice against the estimate from its start choice, the
    minutes between the two choices beyond stage 3's ``minutes`` and the final choice's
    own (what ALLOWANCE covers), and the minutes stage 3 would have had under the default
    deadline (120, with FINAL=1's 64 episodes)."""
    ratios, rests = [], []
    for prefix in prefixes:
        path = Path(prefix)
        select, final, wall = ((path / "select.json", path / "final_select.json",
                                path / "wall.txt") if path.is_dir() else
                               (Path(f"{prefix}_start_choice.json"),
                                Path(f"{prefix}_choice.json"), Path(f"{prefix}_wall.txt")))
        select, final = json.loads(select.read_text()), json.loads(final.read_text())
        estimate = scaled_seconds(select, final)
        ratios.append(final["seconds"] / estimate)
        line = (f"{prefix}: start choice {select['seconds']:.0f} s, final choice "
                f"{final['seconds']:.0f} s, estimated {estimate:.0f} s: {ratios[-1]:.2f}x")
        if wall.exists():
            at = stamps(wall)
            between = (at["final"] - at["selected"]).total_seconds() / 60
            rests.append(between - minutes - final["seconds"] / 60)
            line += f"; between the choices {between:.1f} min, {rests[-1]:.1f} beyond both"
            spent = (at["selected"] - at["start"]).total_seconds() / 60
            given = plan(spent, minutes, 120.0, select, True, 64)["minutes"]
            ends = spent + given + rests[-1] + final["seconds"] / 60  # the same rest and choice
            line += (f"; DEADLINE=120 would give stage 3 {given:.1f} min, the run ending "
                     f"after about {ends:.1f}")
        print(line)
    print(f"{len(ratios)} draws: the final choice took {min(ratios):.2f}x to "
          f"{max(ratios):.2f}x the estimate (MARGIN is {MARGIN})")
    if rests:
        print(f"beyond stage 3's {minutes:g} minutes and the final choice: {min(rests):.1f} "
              f"to {max(rests):.1f} minutes (ALLOWANCE is {ALLOWANCE:g})")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--calibrate", nargs="+", metavar="RUN_OR_CARD",
                   help="finished draws: run folders (select.json, final_select.json) or card "
                        "prefixes (<prefix>_start_choice.json, <prefix>_choice.json)")
    p.add_argument("--wall", type=Path, help="the run's wall.txt")
    p.add_argument("--minutes", type=float,
                   help="stage 3's typed minutes (M3; with --calibrate, the draws', 26)")
    p.add_argument("--deadline", type=float, help="minutes of the whole run")
    p.add_argument("--select", type=Path, help="the start choice's select.json")
    p.add_argument("--final", action="store_true", help="FINAL=1: a final choice follows")
    p.add_argument("--final-episodes", type=int, default=64)
    p.add_argument("--final-budgets", type=float, nargs="+", default=list(FINAL_BUDGETS),
                   help="the final choice's budgets (final_choice.sh's FINAL_BUDGETS)")
    p.add_argument("--out", type=Path, help="write the plan here (JSON)")
    args = p.parse_args()
    if args.calibrate:
        calibrate(args.calibrate, 26.0 if args.minutes is None else args.minutes)
        return
    if args.wall is None or args.minutes is None or args.deadline is None:
        p.error("--wall, --minutes and --deadline are needed (or --calibrate)")
    if not (math.isfinite(args.deadline) and args.deadline > 0 and args.minutes > 0
            and args.final_episodes >= 2 and all(b > 0 for b in args.final_budgets)):
        p.error("--deadline and --minutes must be positive, --final-episodes >= 2, "
                "--final-budgets positive")
    select = json.loads(args.select.read_text()) if args.select else None
    try:
        elapsed = (datetime.now(timezone.utc) - started(args.wall)).total_seconds() / 60
        found = plan(elapsed, args.minutes, args.deadline, select, args.final,
                     args.final_episodes, tuple(args.final_budgets))
    except ValueError as e:
        p.error(str(e))
    if args.out:
        args.out.write_text(json.dumps(found, indent=2) + "\n")
    verdict = ("no stage 3: the start choice is the policy file" if found["minutes"] == 0
               else f"stage 3 gets {found['minutes']:g} of its {args.minutes:g} minutes")
    print(f"deadline {args.deadline:g} min: {elapsed:.1f} spent, reserve "
          f"{found['allowance']:g} + {found['final_estimate'] or 0:g} for what follows stage 3, "
          f"{found['left']:.1f} left (floor {FLOOR:g}): {verdict}", file=sys.stderr)
    print(f"{found['minutes']:g}")


if __name__ == "__main__":
    main()
