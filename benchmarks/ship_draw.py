"""Ship a finished ``benchmarks/train_2h.sh`` draw into ``docs/cards/`` under one prefix.

A two-hour draw is documented by a fixed set of files, each named after the card prefix
(for example ``docs/cards/ours_2h_intent_seed39_bf16_final_h2_pop2_wide8``):

    PREFIX.pt / PREFIX.json          the policy file and its card (OUT/final.pt, or without
                                     FINAL=1 stage 3's average OUT/avg.pt)
    PREFIX_choice.json               FINAL=1's choice between stage 3's start and average
    PREFIX_start_choice.json         SELECT=1's choice of stage 3's start
    PREFIX_deadline.json             DEADLINE's plan for stage 3's minutes
    PREFIX_stages12.jsonl            the main member's stage 1-2 curve
    PREFIX_m1_stages12.jsonl         POP=2: the second member's stage 1-2 curve
    PREFIX_wall.txt                  the wall-clock stamps
    PREFIX_score.txt                 with --board: benchmarks/score_draw.py's stamps of the
                                     protocol's passes (shipped with the board they made, so
                                     that a run shipped at its end stamp ships no partial one)
    PREFIX_stage3_start.json         FINAL=1: the card of the candidate the final choice
      or PREFIX_stage3_avg.json        set aside (the start's, or the average's)
    PREFIX_board/risk_aware.json     with --board: the protocol's board of the policy file
    PREFIX_b5_results/risk_aware/ours_ti.jsonl
                                     with --results: the policy file's 300 protocol episodes
                                     at B = 5, so that the paired comparison with the
                                     committed docs/cards/catnipp_ti_risk_aware_b5_results
                                     (benchmarks/paired_subset.py) runs from a fresh clone

Files a switch did not make (no FINAL, no DEADLINE, POP=1; no score.txt where the
board was not scored by score_draw.py) are left out; the others must be there. The run
must be finished (an ``end`` stamp in its wall.txt), and the kept candidate is read from
final_select.json and checked byte for byte against final.pt, so that a card never names
the wrong network; the shipped episodes are those of that network (its sha256).
Existing files under the prefix are an error unless ``--force``.

Usage:
    python benchmarks/ship_draw.py outputs/h42 \\
        docs/cards/ours_2h_intent_seed39_bf16_final_h2_pop2_wide8 --board outputs/h42_boards \\
        --results outputs/h42_results
"""

from __future__ import annotations

import argparse
import filecmp
import itertools
import json
import shutil
import sys
from pathlib import Path

from stage3_minutes import stamps

SUITE = "risk_aware"
METHOD = "ours_ti"
# The budget whose episodes ship: where draws come closest to catnipp_ti (most misses are
# behind it there), and the one whose catnipp_ti episodes are committed to pair with.
PAIRED_BUDGET = 5.0
# (file in the run, suffix after the prefix, made only by a switch)
FILES = (
    ("final_select.json", "_choice.json", True),  # FINAL=1
    ("select.json", "_start_choice.json", True),  # SELECT=1
    ("deadline.json", "_deadline.json", True),  # DEADLINE
    ("stage2/curve.jsonl", "_stages12.jsonl", False),
    ("m1/stage2/curve.jsonl", "_m1_stages12.jsonl", True),  # POP=2
    ("wall.txt", "_wall.txt", False),
)
# FINAL=1's candidates (benchmarks/final_choice.sh): the one not kept ships its card.
SET_ASIDE = {"start.pt": ("avg.json", "_stage3_avg.json"),
             "avg.pt": ("start.json", "_stage3_start.json")}


class DrawError(ValueError):
    """A run folder or prefix that cannot be shipped as it stands."""


def shipped(prefix: Path, suffix: str) -> Path:
    """The file (or folder) that ``suffix`` names under the card ``prefix``."""
    return prefix.with_name(prefix.name + suffix)


def episodes_file(prefix: Path) -> Path:
    """Where ``--results`` ships the :data:`PAIRED_BUDGET` episodes under ``prefix``, laid
    out as a results folder so that paired_subset.py's ``--subset`` reads it."""
    return shipped(prefix, f"_b{PAIRED_BUDGET:g}_results") / SUITE / f"{METHOD}.jsonl"


def finished(run: Path) -> bool:
    """Whether train_2h.sh wrote its ``end`` stamp into ``run``/wall.txt."""
    wall = run / "wall.txt"
    return wall.is_file() and "end" in stamps(wall)


def policy_file(run: Path) -> Path:
    """A finished run's policy file: final.pt, or without FINAL=1 (and with stage 3)
    stage 3's average avg.pt."""
    return run / ("final.pt" if (run / "final.pt").is_file() or not (run / "avg.pt").is_file()
                  else "avg.pt")


def plan(run: Path, prefix: Path, board: Path | None = None) -> list[tuple[Path, Path]]:
    """The (source, destination) pairs that ship ``run`` under ``prefix``; raises
    :class:`DrawError` on an unfinished run, a missing file or an inconsistent choice."""
    if not finished(run):
        raise DrawError(f"{run} is not a finished train_2h.sh run (no 'end' line in "
                        f"{run / 'wall.txt'})")

    policy = policy_file(run).stem
    files = [(f"{policy}.pt", ".pt", False), (f"{policy}.json", ".json", False), *FILES]
    pairs = []
    for name, suffix, optional in files:
        source = run / name
        if source.is_file():
            pairs.append((source, shipped(prefix, suffix)))
        elif not optional:
            raise DrawError(f"{source} is missing: every train_2h.sh run writes it")
    final = run / "final_select.json"
    if final.is_file():
        kept = Path(json.loads(final.read_text())["chosen"]["path"]).name
        if kept not in SET_ASIDE:
            raise DrawError(f"{final} kept {kept}, not one of {sorted(SET_ASIDE)}")
        if not filecmp.cmp(run / kept, run / "final.pt", shallow=False):
            raise DrawError(f"{run / 'final.pt'} is not the {kept} that {final} kept")
        card, suffix = SET_ASIDE[kept]
        if not (run / card).is_file():
            raise DrawError(f"{run / card} is missing: the final choice's other candidate")
        pairs.append((run / card, shipped(prefix, suffix)))
    if board is not None:
        source = board / f"{SUITE}.json"
        if not source.is_file():
            raise DrawError(f"{source} is missing: score the run first (maipp_bench.eval "
                            f"--leaderboards {board})")
        pairs.append((source, shipped(prefix, "_board") / source.name))
        if (run / "score.txt").is_file():  # benchmarks/score_draw.py's, when it scored it
            pairs.append((run / "score.txt", shipped(prefix, "_score.txt")))
    return pairs


def paired_episodes(run: Path, results: Path) -> list[str]:
    """The lines of ``results``/risk_aware/ours_ti.jsonl that are the run's policy file's
    episodes at :data:`PAIRED_BUDGET`, each of the protocol's episodes once; raises
    :class:`DrawError` when some are missing or doubled, or a line is not a result row."""
    from maipp_bench.protocol.protocol import file_sha256, load_protocol

    source = results / SUITE / f"{METHOD}.jsonl"
    if not source.is_file():
        raise DrawError(f"{source} is missing: score the run first (benchmarks/score_draw.py)")
    policy = policy_file(run)
    digest = file_sha256(policy)
    setting = f"budget={PAIRED_BUDGET}"
    lines, episodes, versions = [], [], set()
    for number, line in enumerate(source.read_text().splitlines(), 1):
        try:
            row = json.loads(line)
            if row["setting"] == setting and row["checkpoint_sha256"] == digest:
                episodes.append((row["instance"], row["trial"]))
                versions.add(row["protocol_version"])
                lines.append(line)
        except (json.JSONDecodeError, KeyError, TypeError) as err:
            raise DrawError(f"{source}:{number} is not a result row ({err!r})") from None
    if len(versions) > 1:
        raise DrawError(f"{source}: {setting} rows of protocol versions {sorted(versions)}")
    suite = load_protocol(versions.pop() if versions else 1).suite(SUITE)
    wanted = set(itertools.product(suite.instance_seeds, suite.trial_seeds))
    if len(episodes) != len(wanted) or set(episodes) != wanted:
        raise DrawError(f"{source} holds {len(set(episodes) & wanted)} of the protocol's "
                        f"{len(wanted)} {setting} episodes of {policy} (sha256 "
                        f"{digest[:12]}; {len(episodes)} rows): score it in full first")
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path, help="train_2h.sh's OUT_DIR, finished")
    parser.add_argument("prefix", type=Path, help="card prefix, e.g. docs/cards/ours_2h_...")
    parser.add_argument("--board", type=Path, help="the --leaderboards folder that scored it")
    parser.add_argument("--results", type=Path, help="the --out folder of the per-episode "
                        f"results that scored it: ships the B = {PAIRED_BUDGET:g} episodes")
    parser.add_argument("--force", action="store_true", help="overwrite files under prefix")
    args = parser.parse_args(argv)
    try:
        if not args.prefix.parent.is_dir():
            raise DrawError(f"{args.prefix.parent} is not a folder")
        pairs = plan(args.run, args.prefix, args.board)
        episodes = episodes_file(args.prefix)
        lines = paired_episodes(args.run, args.results) if args.results else None
        destinations = [dst for _, dst in pairs] + ([episodes] if lines is not None else [])
        there = [str(dst) for dst in destinations if dst.exists()]
        if there and not args.force:
            raise DrawError(f"{len(there)} files are already there ({there[0]}, ...); "
                            "--force overwrites them")
    except DrawError as err:
        print(f"ship_draw.py: {err}", file=sys.stderr)
        return 2
    for source, destination in pairs:
        destination.parent.mkdir(exist_ok=True)
        shutil.copyfile(source, destination)
        print(destination)
    if lines is not None:
        episodes.parent.mkdir(parents=True, exist_ok=True)
        episodes.write_text("\n".join(lines) + "\n")
        print(f"{episodes} ({len(lines)} episodes)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
