"""A two-hour draw's section of docs/results.md, its row of "All two-hour runs, one
table" and its rows of docs/performance.md, rendered from the draw's committed cards.

Every figure comes from the cards ``ship_draw.py`` writes under ``docs/cards/PREFIX*``
and the committed leaderboards, through the functions of the scripts that print them
(``train_throughput.py``, ``select_snapshot.py``, ``stage3_minutes.py``,
``board_diff.py``, ``paired_subset.py``, ``draw_rate.py``), so that the prose cannot
drift from the cards: ``tests/test_draw_section.py`` reruns the command of each
``<!-- draw_section.py ARGS -->`` marker in docs/results.md and checks that the text
after the marker is what it prints, that its ``--row`` is in the table and that its
``--performance`` rows are in docs/performance.md.

``--row`` prints the table row; add it to the table first, since the section's counts
(``draw_rate.py``'s) are taken over the table's draws up to this one, so that they do not
change as later draws are added. ``--performance`` prints the draw's five rows of
docs/performance.md's table of two-hour runs (each member's stages 1 and 2, then stage 3).

How fast the box ran against the draw before, in the mean frames/s of stage 1's two
members: "about as fast as" within 1%, "a little faster / slower than" within 3%,
"faster / slower than" beyond; the previous draw's box is named where it was another.

Usage:
    python benchmarks/draw_section.py docs/cards/PREFIX --draw 64 \\
        --previous docs/cards/PREVIOUS_PREFIX --row
    python benchmarks/draw_section.py docs/cards/PREFIX --draw 64 \\
        --previous docs/cards/PREVIOUS_PREFIX [--performance]
"""

from __future__ import annotations

import argparse
import json
import math
import re
import shlex
import statistics as st
import sys
from datetime import datetime, timedelta
from functools import cached_property
from pathlib import Path

import board_diff
import boards
from draw_rate import family, hits, rate
from draw_signals import outcomes, table_rows
from paired_subset import _rows, pair
from stage3_minutes import scaled_seconds, stamps
from train_throughput import card_segment, stage_cuts

from maipp_bench.curves import read_curve

ROOT = Path(__file__).resolve().parent.parent
SUITE, METHOD = "risk_aware", "ours_ti"
# Every baseline the ranking target names (draw_figures.sh's board_diff.py call, less the
# oracle, which is a bound and not a baseline); the table's cells take B = 2 against
# sga_rrt and B = 4-5 against catnipp_ti, B = 5 paired on the committed episodes.
BASELINES = ("sga_rrt_0.3_0.4", "greedy", "catnipp_ti", "catnipp_greedy")
SGA, TI = "sga_rrt_0.3_0.4", "catnipp_ti"
PAIRED_RESULTS = "docs/cards/catnipp_ti_risk_aware_b5_results"
BUDGETS = (2.0, 3.0, 4.0, 5.0)
RECIPE = 'WIDE=8 POP=2 SELECT=1 FINAL=1 FINAL_BUDGETS="2 4 5"'

_UNITS = ("", "first", "second", "third", "fourth", "fifth", "sixth", "seventh", "eighth",
          "ninth")
_TEENS = ("tenth", "eleventh", "twelfth", "thirteenth", "fourteenth", "fifteenth",
          "sixteenth", "seventeenth", "eighteenth", "nineteenth")
_TENS = ("", "", "twent", "thirt", "fort", "fift", "sixt", "sevent", "eight", "ninet")
_CARDINAL = ("no", "one", "two", "three", "four", "five", "six", "seven", "eight", "nine")


def ordinal(n: int) -> str:
    """1-99 in words, as the docs name draws: "sixty-fourth"."""
    if not 0 < n < 100:
        raise ValueError(f"ordinal() takes 1-99, got {n}")
    if n < 10:
        return _UNITS[n]
    if n < 20:
        return _TEENS[n - 10]
    tens, unit = divmod(n, 10)
    return f"{_TENS[tens]}ieth" if unit == 0 else f"{_TENS[tens]}y-{_UNITS[unit]}"


def _count(n: int, noun: str) -> str:
    """"one update", "3 traps"."""
    return f"{_CARDINAL[n] if n < len(_CARDINAL) else n} {noun}{'' if n == 1 else 's'}"


def _pm(diff: float, se: float, digits: int) -> str:
    return f"{diff:+.{digits}f} ± {se:.{digits}f}"


def _lead(diff: float, third_person: bool = True) -> str:
    """A difference of Tr(P_f) (lower is better) as the docs word it."""
    word = "lead" if diff < 0 else "trail" if diff > 0 else "tie"
    return word + ("s" if third_person else "")


def _budgets(budgets: list[float]) -> str:
    """"B = 5 alone", "B = 2 and 5"."""
    if len(budgets) == 1:
        return f"B = {budgets[0]:g} alone"
    return "B = " + ", ".join(f"{b:g}" for b in budgets[:-1]) + f" and {budgets[-1]:g}"


def machine_name(card_machine: str) -> str:
    """The CPU as the docs name it, from a card's ``machine`` ("x86_64, Intel(R) Xeon(R)
    Processor, 2 cores, ...": "Intel Xeon")."""
    cpu = re.sub(r"\((R|TM)\)|\bProcessor\b|\bCPU\b|@.*", "", card_machine.split(", ")[1])
    return " ".join(cpu.split())


class Draw:
    """One shipped draw's cards, and the figures its section cites."""

    def __init__(self, prefix: str, number: int, aside: str = "") -> None:
        self.prefix, self.number = prefix, number
        # what else ran on the box during the draw ("" for a draw that ran alone)
        self.aside = aside
        self.path = ROOT / prefix
        if not self.file(".json").exists():
            raise SystemExit(f"draw_section.py: no card {prefix}.json (ship the draw first)")
        seed = re.search(r"_seed(\d+)_", Path(prefix).name)
        if seed is None:
            raise SystemExit(f"draw_section.py: {prefix}: no _seedN_ in the prefix")
        self.seed = int(seed[1])
        self.card = self.read(".json")
        # the recipe's OVERRIDES, as stage 3's command (the card's) carries them
        self.precision = "bf16" if "algo.precision=bf16" in self.card["command"] else "float32"
        self.machine = machine_name(self.card["machine"])
        self.native = ("native bf16" if "native bf16: yes" in self.card["machine"]
                       else "without native bf16")
        wall = self.file("_wall.txt")
        self.wall = stamps(wall)
        # the run folder, as the wall stamps name it ("stage1 done <time> outputs/h63")
        self.out = next((line.split()[-1] for line in wall.read_text().splitlines()
                         if line.startswith("stage1 done") and not line.endswith("/m1")), None)
        if self.out is None or "end" not in self.wall:
            raise SystemExit(f"draw_section.py: {wall} lacks a 'stage1 done' or 'end' stamp")
        # a kept start's card holds stages 1-2; stage 3's is then the set-aside average's
        self.kept_start = self.file("_stage3_avg.json").exists()
        self.stage3 = self.read("_stage3_avg.json") if self.kept_start else self.card
        self.set_aside = "_stage3_avg.json" if self.kept_start else "_stage3_start.json"
        self.select = self.read("_start_choice.json")
        self.final = self.read("_choice.json")
        self.plan = self.read("_deadline.json")

    def file(self, suffix: str) -> Path:
        """The card file ``PREFIX + suffix``."""
        return Path(f"{self.path}{suffix}")

    def read(self, suffix: str) -> dict:
        """The JSON card ``PREFIX + suffix``."""
        return json.loads(self.file(suffix).read_text())

    @property
    def box_shared(self) -> str:
        """", not alone: ..." after the box's name for a draw that shared it, else ""."""
        return f", not alone: {self.aside}" if self.aside else ""

    @property
    def minutes(self) -> float:
        """The run's wall clock, start to end stamp, in minutes to one decimal (half up,
        as the docs round them)."""
        seconds = (self.wall["end"] - self.wall["start"]).total_seconds()
        return math.floor(seconds / 6 + 0.5) / 10

    def score_stamps(self) -> dict[str, datetime]:
        """score_draw.py's stamps: "score_start", then "B45" and "B23" for its passes."""
        found = {}
        for line in self.file("_score.txt").read_text().splitlines():
            words = line.split()
            key = {"scored B=5,4": "B45", "scored B=2,3": "B23"}.get(" ".join(words[:2]),
                                                                     words[0])
            found[key] = datetime.fromisoformat(words[-1].replace("Z", "+00:00"))
        return found

    @cached_property
    def members(self) -> list[dict]:
        """Per member of stages 1-2 (seed, then seed + 1000): its seed, stage 1's and 2's
        ``card_segment`` and the last update of each."""
        out = []
        for suffix, seed in (("_stages12.jsonl", self.seed),
                             ("_m1_stages12.jsonl", self.seed + 1000)):
            curve = read_curve(self.file(suffix))  # as train_throughput.py --card reads it
            cut = stage_cuts(curve)[0]
            out.append({"seed": seed, "stage1": cut, "stage2": len(curve),
                        "seg1": card_segment(curve, 0, cut),
                        "seg2": card_segment(curve, cut, len(curve))})
        return out

    @cached_property
    def stage3_segment(self) -> dict:
        """Stage 3's throughput over its card's updates."""
        curve = self.stage3["curve"]
        return card_segment(curve, 0, len(curve))

    @cached_property
    def board(self) -> dict:
        """The committed risk_aware board with this draw's ``ours_ti`` rows in place of
        the shipped network's (``board_diff.py --method-from``)."""
        return board_diff.with_rows_from(boards.load(SUITE, ROOT / "leaderboards"), METHOD,
                                         f"{self.path}_board")

    @cached_property
    def scores(self) -> dict[float, float]:
        """The draw's mean Tr(P_f) per budget under the protocol."""
        rows = boards.keyed(self.board, [METHOD])
        return {b: rows[METHOD, f"budget={b}"]["trace_mean"] for b in BUDGETS}

    @cached_property
    def differences(self) -> dict[float, dict[str, tuple[float, float]]]:
        """Per budget, each baseline's unpaired (difference, standard error)."""
        return {float(e["setting"].removeprefix("budget=")): e["diff"]
                for e in board_diff.differences(self.board, METHOD, list(BASELINES))}

    def paired(self, exclude: tuple[tuple[int, int], ...] = ()) -> dict:
        """B = 5 against ``catnipp_ti``, episode by episode (``paired_subset.py``); its
        ``costliest`` episode as (instance, trial) with its Tr(P_f), traps and
        ``catnipp_ti``'s Tr(P_f) there."""
        mine = _rows(self.file("_b5_results") / SUITE / f"{METHOD}.jsonl")
        ref = _rows(ROOT / PAIRED_RESULTS / SUITE / f"{TI}.jsonl")
        keys = [k for k in mine if k[0] == "budget=5.0" and k[1:] not in exclude]
        found = pair(mine, ref, keys)
        k = found["costliest"]
        found["costliest"] = {"episode": k[1:], "trace": mine[k]["trace"],
                              "traps": mine[k]["traps"], "against": ref[k]["trace"]}
        return found

    @cached_property
    def b5(self) -> dict:
        """:meth:`paired` over all 300 episodes."""
        return self.paired()


def trailing_at_b5(first: int = 60) -> tuple[list[int], list[int]]:
    """Of the table's draws from ``first`` on that trail ``catnipp_ti`` at B = 5 in the mean
    and ship their B = 5 episodes (``docs/cards/..._seedS_..._b5_results``, found by the
    row's seed): those that lead without their costliest episode, and those that trail
    either way (the status row's "trail ... with theirs and lead without")."""
    decided, either = [], []
    draws = outcomes()
    for n, cells in table_rows().items():
        if n < first or draws[n]["B5_minus_ti"] <= 0:
            continue
        seed = cells[2].strip()
        found = sorted((ROOT / "docs" / "cards").glob(f"ours_2h_intent_seed{seed}_*_b5_results"))
        if len(found) != 1:
            raise SystemExit(f"draw {n}: {len(found)} B = 5 episode folders for its seed")
        draw = Draw(str(found[0]).removesuffix("_b5_results"), n)
        without = draw.paired((draw.b5["costliest"]["episode"],))
        (decided if without["diff"] < 0 else either).append(n)
    return decided, either


def verdict(draw: Draw) -> tuple[str, list[float]]:
    """"by a margin" (ahead of every baseline at every budget in the means, and the
    table's three deciding margins each by two standard errors), "in the means" or
    "missed"; and the budgets at which a baseline is ahead in the mean."""
    behind = [b for b, diffs in draw.differences.items()
              if any(d >= 0 for d, _ in diffs.values())]
    if behind:
        return "missed", behind
    deciding = [draw.differences[2.0][SGA], draw.differences[4.0][TI],
                (draw.b5["diff"], draw.b5["se"])]
    return ("by a margin" if all(d + 2 * se < 0 for d, se in deciding) else "in the means"), []


def sga_version() -> int:
    """The version of ``sga_rrt``'s algorithm in the registry (its rows on the committed
    board are of it: eval never reuses rows of another fingerprint)."""
    from maipp_bench.algos.registry import POLICIES, get_method

    return getattr(POLICIES[get_method(SGA).policy], "version", 1)


def pace(draw: Draw, previous: Draw) -> str:
    """How stage 1 ran against the previous draw's (the module docstring's rule)."""
    ratio = (st.mean(m["seg1"]["frames_per_s"] for m in draw.members)
             / st.mean(m["seg1"]["frames_per_s"] for m in previous.members))
    word = "faster" if ratio > 1 else "slower"
    speed = ("about as fast as" if abs(ratio - 1) < 0.01 else
             f"a little {word} than" if abs(ratio - 1) < 0.03 else f"{word} than")
    box = "" if previous.machine == draw.machine else f" {previous.machine}"
    return f"{speed} the {ordinal(previous.number)}'s{box}"


def final_estimate_ratio(draw: Draw) -> float:
    """The final choice's seconds over their estimate from the start choice's
    (``stage3_minutes.py --calibrate``)."""
    return draw.final["seconds"] / scaled_seconds(draw.select, draw.final)


def _member(path: str, draw: Draw) -> str:
    """"seed 60" or "seed 1060" for a candidate of the start choice."""
    return f"seed {draw.seed + 1000 if '/m1/' in path else draw.seed}"


def start_choice_text(draw: Draw) -> str:
    """The start choice: what it kept, by how much, and against the last candidate."""
    cands, chosen = draw.select["candidates"], draw.select["chosen"]
    who = _member(chosen["path"], draw)
    ends = {_member(c["path"], draw): c for c in cands if c["path"].endswith("checkpoint.pt")}
    gap = ends[who]["update"] - chosen["update"]
    where = "its end" if gap == 0 else f"a snapshot {_count(gap, 'update')} before its end"
    others = [c for c in cands if c["position"] != chosen["position"]]
    parts = []
    for member in dict.fromkeys([who, *(_member(c["path"], draw) for c in cands)]):
        own = [c for c in others if _member(c["path"], draw) == member]
        if not own:
            continue
        best, end = min(own, key=lambda c: c["mean"]), ends[member]
        text = (f"{member}'s end, update {end['update']}, {end['mean']:.2f}" if best is end else
                f"{member}'s update {best['update']}, {best['mean']:.2f}")
        if best is not end and end in own:
            text += f", and its end, update {end['update']}, {end['mean']:.2f}"
        parts.append(text)
    budgets = draw.select["budget"]
    held = " and ".join(f"B = {b:g} {chosen[f'mean_B{b:g}']:.2f}" for b in budgets)
    runner_up = min(c["mean"] for c in others)
    text = (f"The start choice ({draw.select['seconds']:.0f} s) kept **{who}'s update "
            f"{chosen['update']}**, {where}, by {runner_up - chosen['mean']:.2f} (score "
            f"{chosen['mean']:.2f}: held-out {held}; the best of the others: "
            f"{'; '.join(parts)}; `..._start_choice.json`, `select_snapshot.py --show`)")
    last = cands[-1]
    if chosen["position"] != last["position"]:
        zs = [(b, chosen[f"minus_end_B{b:g}"] / chosen[f"se_B{b:g}"]) for b in budgets]
        words = [f"{'led' if z < 0 else 'trailed'} by {abs(z):.1f}" for _, z in zs]
        # "led by 1.4 standard errors at B = 2 and by 0.5 at B = 5"
        same = len({w.split()[0] for w in words}) == 1
        text += (f"; against the last candidate, {_member(last['path'], draw)}'s end, the "
                 "chosen snapshot " + " and ".join(
                     (w.split(" ", 1)[1] if same and i else w)
                     + (" standard errors" if i == 0 else "") + f" at B = {b:g}"
                     for i, (w, (b, _)) in enumerate(zip(words, zs))))
    return text + "."


def stage3_text(draw: Draw, previous: Draw) -> str:
    """DEADLINE's minutes, stage 3's updates and pace, and the final choice."""
    plan = draw.plan
    given = (f"`DEADLINE` **trimmed stage 3 to {plan['minutes']:g} minutes**"
             if plan["minutes"] < plan["typed"] else
             f"`DEADLINE` left stage 3 its {plan['typed']:g} minutes")
    start, avg = draw.final["candidates"]  # final_choice.sh passes start.pt, then avg.pt
    chosen, other = (start, avg) if draw.kept_start else (avg, start)
    kept, other_name = ("stage 3's start", "average") if draw.kept_start else \
        ("the average", "start")
    updates = draw.stage3["averaged_updates"]
    span = f"updates {updates[0]}-{updates[-1]}"
    over = (f"over the average of its snapshots ({span})" if draw.kept_start else
            f"of stage 3's snapshots ({span}) over its start")
    budgets = draw.final["budget"]
    diffs = ", ".join(
        f"at B = {b:g} {_pm(start[f'minus_end_B{b:g}'], start[f'se_B{b:g}'], 2)} "
        f"({abs(start[f'minus_end_B{b:g}']) / start[f'se_B{b:g}']:.1f} standard errors)"
        for b in budgets)
    s3 = draw.stage3
    return (f"At stage 3's start {plan['elapsed']:.1f} minutes had passed; with the final "
            f"choice's reserve of {plan['final_estimate']:g} minutes, {given} "
            f"(`..._deadline.json`). Stage 3 made {s3['run_continued_to']} updates "
            f"(snapshots to {s3['updates']}; {draw.stage3_segment['frames_per_s']:.1f} "
            f"frames/s over updates 1-{s3['updates']}, against the "
            f"{ordinal(previous.number)}'s {previous.stage3_segment['frames_per_s']:.1f}; "
            f"`python benchmarks/train_throughput.py --card "
            f"{draw.prefix}{'_stage3_avg' if draw.kept_start else ''}.json`) and the final "
            f"choice ({draw.final['seconds']:.0f} s, {final_estimate_ratio(draw):.2f}x its "
            f"estimate; `stage3_minutes.py --calibrate`) kept **{kept}** {over}, by "
            f"{other['mean'] - chosen['mean']:.2f} (held-out score {chosen['mean']:.2f} "
            f"against the {other_name}'s {other['mean']:.2f}; start minus average {diffs}; "
            f"`..._choice.json`, `select_snapshot.py --show`; the set-aside {other_name}'s "
            f"card is `...{draw.set_aside}`).")


def protocol_text(draw: Draw) -> str:
    """The protocol's scores, against the shipped network and the closest baselines."""
    s = draw.scores
    board = boards.keyed(boards.load(SUITE, ROOT / "leaderboards"), [METHOD])
    shipped = {b: board[METHOD, f"budget={b}"]["trace_mean"] for b in BUDGETS}
    ahead = [b for b in BUDGETS if s[b] < shipped[b]]
    versus = ("ahead of" if ahead else "behind") + " the shipped `ours.pt`'s " + " / ".join(
        f"{shipped[b]:.1f}" for b in BUDGETS) + " in the mean " + (
        "at every budget" if len(ahead) in (0, len(BUDGETS)) else "at " + _budgets(ahead))
    at = draw.score_stamps()
    closest = {b: max(d.items(), key=lambda kv: kv[1][0]) for b, d in
               sorted(draw.differences.items()) if b != 5.0}
    cells = "; ".join(f"B = {b:g} `{name}` {_pm(d, se, 1)}"
                      for b, (name, (d, se)) in closest.items())
    return (f"Under the protocol it scores **{' / '.join(f'{s[b]:.1f}' for b in BUDGETS)}** "
            f"(`python benchmarks/board_table.py --suite risk_aware --leaderboards "
            f"{draw.prefix}_board`; evaluation {at['score_start']:%H:%M:%S}-"
            f"{at['B45']:%H:%M:%S} UTC for B = 4-5 and to {at['B23']:%H:%M:%S} for B = 2-3, "
            f"`..._score.txt`), {versus}. Its margin to the closest baseline at each budget "
            f"(this minus it, unpaired; `board_diff.py --method ours_ti --method-from "
            f"{draw.prefix}_board --against` every baseline): {cells}.")


def paired_text(draw: Draw) -> str:
    """B = 5 against catnipp_ti, paired: trapped and untrapped episodes, and without the
    episode that costs the most."""
    p = draw.b5
    worst = p["costliest"]
    without = draw.paired((worst["episode"],))
    decides = (p["diff"] < 0) != (without["diff"] < 0)
    groups = " and ".join(
        f"its {n} {tag} {'episodes' if tag == 'untrapped' else 'ones'} "
        f"{_lead(m, third_person=False)} by {abs(m):.2f} ± {e:.2f}"
        for tag in ("untrapped", "trapped") for n, m, e in [p[tag]] if n)
    return (f"At **B = 5 it {_lead(p['diff'])} `catnipp_ti` by {abs(p['diff']):.2f} ± "
            f"{p['se']:.2f} paired** (z {p['diff'] / p['se']:+.1f}, {p['wins']} wins of "
            f"{p['n']}; traps {p['traps']:.2f} per episode). {groups[0].upper()}{groups[1:]}; "
            f"its costliest episode against `catnipp_ti`, {worst['trace']:.1f} "
            f"({_count(worst['traps'], 'trap')}; instance {worst['episode'][0]}, trial "
            f"{worst['episode'][1]}, where `catnipp_ti` scored {worst['against']:.1f}), left "
            f"out, it {_lead(without['diff'])} by {abs(without['diff']):.2f} ± "
            f"{without['se']:.2f} (z {without['diff'] / without['se']:+.1f}; the second "
            f"command below): that one episode {'decides' if decides else 'does not decide'} "
            "the ranking at B = 5.")


def counts_text(draw: Draw, level: float = 0.95) -> str:
    """The verdict, and draw_rate.py's counts over the table's draws up to this one."""
    table = outcomes()
    if draw.number not in table:
        raise SystemExit(f"draw_section.py: draw {draw.number} has no row in docs/results.md's "
                         "table of draws; add the row (--row) first")
    draws = {d: o for d, o in table.items() if d <= draw.number}
    mine = family(draws[draw.number]["recipe"])

    def of(ds: list[int]) -> str:
        return rate(len(hits(ds, draws)[0]), len(ds), level)

    timely = len(hits(sorted(draws), draws)[1])
    name, behind = verdict(draw)
    words = (f"**misses** the ranking **at {_budgets(behind)}**" if name == "missed" else
             f"**meets** the ranking **{name}**")
    return (f"So it {words}, {'within' if draw.minutes <= 120 else 'over'} the compute goal "
            f"({draw.minutes:.1f} minutes). Counts over the table's draws 1-{draw.number} "
            f"(`python benchmarks/draw_rate.py`; exact {level:.0%} intervals): `{mine}` "
            f"{of([d for d, o in draws.items() if family(o['recipe']) == mine])}; all "
            f"draws {of(sorted(draws))}, {timely} within two hours.")


def _fps(draw: Draw, stage: str) -> str:
    """The two members' frames/s in a stage ("seg1" / "seg2"): "58.4 and 58.0"."""
    return " and ".join(f"{m[stage]['frames_per_s']:.1f}" for m in draw.members)


def _last(draw: Draw, stage: str) -> str:
    """The two members' last update of a stage ("stage1" / "stage2"): "105 and 104"."""
    return " and ".join(str(m[stage]) for m in draw.members)


def section(draw: Draw, previous: Draw, recipe: str) -> str:
    """The draw's section of docs/results.md."""
    start, end = draw.wall["start"], draw.wall["end"]
    overrides = "OVERRIDES=algo.precision=bf16 " if draw.precision == "bf16" else ""
    cmd = (f"{draw.prefix}_b5_results --results {PAIRED_RESULTS} --method {METHOD} "
           f"--against {TI}")
    worst = draw.b5["costliest"]["episode"]
    seeds = " and ".join(str(m["seed"]) for m in draw.members)
    return "\n".join([
        f"**A {ordinal(draw.number)} run: seed {draw.seed}, `{recipe}` with "
        f"{draw.precision}, under `DEADLINE`** ({start:%Y-%m-%d}).",
        f"On a 2-core {draw.machine} box with {draw.native}{draw.box_shared} (the cards "
        f"name commit {draw.card['commit'][:7]}), scored by `benchmarks/score_draw.py` "
        "launched beside it; this section is rendered from the cards by "
        "`benchmarks/draw_section.py` (the last command):",
        "",
        "```bash",
        f"{recipe} {overrides}bash benchmarks/train_2h.sh {draw.out} {draw.seed}",
        f"python benchmarks/score_draw.py {draw.out} --wait  # beside it: B = 5 and 4, then 2 "
        "and 3",
        f"python benchmarks/ship_draw.py {draw.out} {draw.prefix} --board {draw.out}_boards "
        f"--results {draw.out}_results",
        f"bash benchmarks/draw_figures.sh {draw.prefix} {previous.prefix}  # every figure below",
        f"python benchmarks/draw_section.py {draw.prefix} --draw {draw.number} --previous "
        f"{previous.prefix}" + (f" --aside {shlex.quote(draw.aside)}" if draw.aside else ""),
        "```",
        "",
        f"{start:%Y-%m-%d %H:%M:%S} to {end:%H:%M:%S} UTC: **{draw.minutes:.1f} minutes** "
        f"(`{draw.prefix}_wall.txt`). The members (seeds {seeds}) made "
        f"**{_last(draw, 'stage1')}** updates in stage 1 ({_fps(draw, 'seg1')} frames/s, "
        f"{pace(draw, previous)} {_fps(previous, 'seg1')}) and {_last(draw, 'stage2')} "
        f"by the end of stage 2 ({_fps(draw, 'seg2')} frames/s there, against "
        f"{_fps(previous, 'seg2')}; `python benchmarks/train_throughput.py --card "
        f"{draw.prefix}_stages12.jsonl --split stages`, and the same for "
        f"`..._m1_stages12.jsonl`). {start_choice_text(draw)} {stage3_text(draw, previous)}",
        f"{protocol_text(draw)} {paired_text(draw)} {counts_text(draw)}",
        "",
        "```bash",
        f"python benchmarks/paired_subset.py --subset {cmd}",
        f"python benchmarks/paired_subset.py --subset {cmd} --exclude {worst[0]}:{worst[1]}",
        "```",
    ])


def _updates(seg: dict) -> int:
    """How many updates a ``card_segment`` spans ("106-208": 103)."""
    first, last = map(int, seg["updates"].split("-"))
    return last - first + 1


def _perf_row(label: str, seg: dict) -> str:
    return (f"| {label} | {_updates(seg)} | {seg['frames']:,} | {seg['decisions']:,} | "
            f"{seg['wall_s']:,.0f} s | {seg['frames_per_s']:.1f} | "
            f"{seg['decisions_per_s']:.1f} |")


def performance(draw: Draw, previous: Draw, recipe: str) -> str:
    """The draw's rows of docs/performance.md: ``train_throughput.py --card``'s segments."""
    start, end = (t + timedelta(seconds=30) for t in (draw.wall["start"], draw.wall["end"]))
    steps = int(re.search(r"steps_per_batch=(\d+)", draw.card["command"])[1])
    took = [d.select["seconds"] for d in (draw, previous)] + \
        [d.final["seconds"] for d in (draw, previous)]
    chosen = draw.select["chosen"]
    rows = []
    for i, m in enumerate(draw.members):
        envs = [m[s]["frames"] // _updates(m[s]) // steps for s in ("seg1", "seg2")]
        label = (f"the same script and fields with `{recipe}`, {draw.precision}, seed "
                 f"{draw.seed} ({start:%Y-%m-%d, %H:%M}-{end:%H:%M} UTC, a 2-core "
                 f"{draw.machine} box with {draw.native}{draw.box_shared}; the cards name "
                 f"commit {draw.card['commit'][:7]}; `DEADLINE={draw.plan['deadline']:g}` gave "
                 f"stage 3 {draw.plan['minutes']:g} minutes; its held-out choices took "
                 f"{took[0]:.0f} s and {took[2]:.0f} s against the "
                 f"{ordinal(previous.number)}'s {took[1]:.0f} s and {took[3]:.0f} s; "
                 f"docs/results.md \"A {ordinal(draw.number)} run\"), member seed {m['seed']}"
                 if i == 0 else f"the same, member seed {m['seed']} (beside it)")
        started = (f" (stage 3 started from update {chosen['update']})"
                   if _member(chosen["path"], draw) == f"seed {m['seed']}" else "")
        rows += [_perf_row(f"{label}, stage 1 ({envs[0]} envs x {steps} steps), updates "
                           f"{m['seg1']['updates']}", m["seg1"]),
                 _perf_row(f"the same, member seed {m['seed']}, stage 2 ({envs[1]} envs x "
                           f"{steps} steps), updates {m['seg2']['updates']}{started}",
                           m["seg2"])]
    kept, other = ("start", "average") if draw.kept_start else ("average", "start")
    rows.append(_perf_row(
        f"the same, stage 3 ({draw.plan['minutes']:g} minutes, both threads), updates "
        f"{draw.stage3_segment['updates']} ({draw.stage3['run_continued_to']} made; the final "
        f"choice kept the {kept}; the set-aside {other}'s card, `...{draw.set_aside}`)",
        draw.stage3_segment))
    return "\n".join(rows)


def row(draw: Draw, previous: Draw, recipe: str) -> str:
    """The draw's row of docs/results.md's "All two-hour runs, one table"."""
    plan = draw.plan
    trimmed = (f"stage 3 trimmed to {plan['minutes']:.1f} min" if plan["minutes"] < plan["typed"]
               else "stage 3 not trimmed")
    held = draw.select["heldout_set"]
    kept = "start" if draw.kept_start else "average"
    name, _ = verdict(draw)
    cells = [str(draw.number),
             f"`{recipe}`, {draw.precision}, held-out set {held}, cut defaults, under "
             f"`DEADLINE={plan['deadline']:g}` ({trimmed}), {draw.minutes:.1f} min, "
             f"{draw.machine}, {pace(draw, previous)} in stage 1{draw.box_shared} "
             f"({kept} kept)",
             str(draw.seed), *(f"{draw.scores[b]:.1f}" for b in BUDGETS),
             f"{_pm(*draw.differences[2.0][SGA], 1)} (v{sga_version()})",
             f"{_pm(*draw.differences[4.0][TI], 1)} (unpaired)",
             _pm(draw.b5["diff"], draw.b5["se"], 2),
             name + ("" if draw.minutes <= 120 else ", over 2 h")]
    return "| " + " | ".join(cells) + " |"


def render(argv: list[str]) -> str:
    """What ``draw_section.py ARGV`` prints."""
    parser = argparse.ArgumentParser(prog="draw_section.py",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("prefix", help="the draw's card prefix, docs/cards/ours_2h_intent_...")
    parser.add_argument("--draw", type=int, required=True, help="its number in the table")
    parser.add_argument("--previous", required=True, help="the card prefix of the draw before")
    parser.add_argument("--recipe", default=RECIPE, help="train_2h.sh's switches for the draw")
    parser.add_argument("--aside", default="", metavar="TEXT",
                        help="what else ran on the box during the draw (a draw not run alone "
                             "says so in its section and rows)")
    what = parser.add_mutually_exclusive_group()
    what.add_argument("--row", action="store_true", help="print the table row instead")
    what.add_argument("--performance", action="store_true",
                      help="print the draw's rows of docs/performance.md instead")
    args = parser.parse_args(argv)
    if not 1 < args.draw < 100:
        parser.error("--draw must be 2-99 (the section compares with the draw before)")
    draw = Draw(args.prefix, args.draw, args.aside)
    previous = Draw(args.previous, args.draw - 1)
    renderer = row if args.row else performance if args.performance else section
    return renderer(draw, previous, args.recipe)


def main() -> None:
    print(render(sys.argv[1:]))


if __name__ == "__main__":
    main()
