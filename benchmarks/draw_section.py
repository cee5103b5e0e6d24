"""A two-hour draw's section of docs/results.md, and its row of "All two-hour runs, one
table", rendered from the draw's committed cards.

Every figure comes from the cards ``ship_draw.py`` writes under ``docs/cards/PREFIX*``
and the committed leaderboards, through the functions of the scripts that print them
(``train_throughput.py``, ``select_snapshot.py``, ``stage3_minutes.py``,
``board_diff.py``, ``paired_subset.py``, ``draw_rate.py``), so that the prose cannot
drift from the cards: ``tests/test_draw_section.py`` reruns the command of each
``<!-- draw_section.py ARGS -->`` marker in docs/results.md and checks that the text
after the marker is what it prints.

``--row`` prints the table row; add it to the table first, since the section's counts
(``draw_rate.py``'s) are taken over the table's draws up to this one, so that they do not
change as later draws are added. ``--performance`` prints the draw's five rows of
docs/performance.md's table of two-hour runs (each member's stages 1 and 2, then stage 3),
which the test also finds there.

Usage:
    python benchmarks/draw_section.py docs/cards/PREFIX --draw 64 \\
        --previous docs/cards/PREVIOUS_PREFIX --row
    python benchmarks/draw_section.py docs/cards/PREFIX --draw 64 \\
        --previous docs/cards/PREVIOUS_PREFIX
"""

from __future__ import annotations

import argparse
import json
import re
import statistics as st
import sys
from datetime import datetime
from pathlib import Path

import board_diff
import boards
from draw_rate import clopper_pearson, family, met
from draw_signals import outcomes
from paired_subset import _rows, mean_se
from stage3_minutes import stamps, work
from train_throughput import card_segment, stage_cuts

ROOT = Path(__file__).resolve().parent.parent
SUITE, METHOD = "risk_aware", "ours_ti"
# Every baseline the ranking target names (draw_figures.sh's board_diff.py call, less the
# oracle, which is a bound and not a baseline), and the one each budget's table cell and
# the paired comparison take.
BASELINES = ("sga_rrt_0.3_0.4", "greedy", "catnipp_ti", "catnipp_greedy")
PAIRED_AGAINST = "catnipp_ti"
PAIRED_RESULTS = "docs/cards/catnipp_ti_risk_aware_b5_results"
BUDGETS = (2.0, 3.0, 4.0, 5.0)
RECIPE = 'WIDE=8 POP=2 SELECT=1 FINAL=1 FINAL_BUDGETS="2 4 5"'

_UNITS = ("", "first", "second", "third", "fourth", "fifth", "sixth", "seventh", "eighth",
          "ninth")
_TEENS = ("tenth", "eleventh", "twelfth", "thirteenth", "fourteenth", "fifteenth",
          "sixteenth", "seventeenth", "eighteenth", "nineteenth")
_TENS = ("", "", "twent", "thirt", "fort", "fift", "sixt", "sevent", "eight", "ninet")
_CARDINAL = ("", "one", "two", "three", "four", "five", "six", "seven", "eight", "nine")


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


def _signed(diff: float, se: float, digits: int) -> str:
    return f"{diff:+.{digits}f} ± {se:.{digits}f}"


def _both(members: list[dict], key: str) -> str:
    """The members' frames/s, "58.4 and 58.0"."""
    return " and ".join(f"{m[key]:.1f}" for m in members)


def _lead(diff: float) -> str:
    """A difference of Tr(P_f) (lower is better) as the docs word it."""
    return "leads" if diff < 0 else "trails"


def pair(rows: dict[tuple, dict], ref: dict[tuple, dict], keys: list[tuple]) -> dict:
    """``rows`` against ``ref`` on the episodes ``keys``: the mean paired difference and
    its standard error, wins, mean Tr(P_f) and traps, the same split by whether ``rows``'
    episode was trapped (count, mean, se), and the episode with the worst Tr(P_f)."""
    d = {k: rows[k]["trace"] - ref[k]["trace"] for k in keys}
    diff, se = mean_se(list(d.values()))
    split = {}
    for tag, trapped in (("untrapped", False), ("trapped", True)):
        v = [x for k, x in d.items() if (rows[k]["traps"] > 0) == trapped]
        split[tag] = (len(v), *mean_se(v)) if v else (0, float("nan"), float("nan"))
    worst = max(keys, key=lambda k: rows[k]["trace"])
    return {"n": len(keys), "diff": diff, "se": se, "wins": sum(v < 0 for v in d.values()),
            "trace": st.mean(rows[k]["trace"] for k in keys),
            "median": st.median(rows[k]["trace"] for k in keys),
            "traps": st.mean(rows[k]["traps"] for k in keys), **split, "worst": worst}


def _jsonl(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


class Draw:
    """One shipped draw's cards, and the figures its section cites."""

    def __init__(self, prefix: str, number: int) -> None:
        self.prefix, self.number = prefix, number
        self.path = ROOT / prefix
        if not Path(f"{self.path}.json").exists():
            raise SystemExit(f"draw_section.py: no card {prefix}.json (ship the draw first)")
        seed = re.search(r"_seed(\d+)_", Path(prefix).name)
        if seed is None:
            raise SystemExit(f"draw_section.py: {prefix}: no _seedN_ in the prefix")
        self.seed = int(seed[1])
        self.card = self.json(".json")
        # the recipe's OVERRIDES, as stage 3's command (the card's) carries them
        self.precision = "bf16" if "algo.precision=bf16" in self.card["command"] else "float32"
        # "x86_64, AMD EPYC, 2 cores, native bf16: yes, ..." (maipp_bench.hardware)
        self.machine = self.card["machine"].split(", ")[1]
        self.native = ("native bf16" if "native bf16: yes" in self.card["machine"]
                       else "no native bf16")
        self.wall = stamps(self.file("_wall.txt"))
        # the run folder, as the wall stamps name it ("stage1 done <time> outputs/h63")
        self.out = next(line.split()[-1] for line in self.file("_wall.txt").read_text()
                        .splitlines() if line.startswith("stage1 done")
                        and not line.rstrip().endswith("/m1"))
        # a kept start's card holds stages 1-2; stage 3's is then the set-aside average's
        kept_start = self.file("_stage3_avg.json").exists()
        self.stage3 = self.json("_stage3_avg.json") if kept_start else self.card
        self.set_aside = "_stage3_avg.json" if kept_start else "_stage3_start.json"

    def score_stamps(self) -> dict[str, datetime]:
        """score_draw.py's stamps: "score_start", then "B45" and "B23" for its passes."""
        found = {}
        for line in self.file("_score.txt").read_text().splitlines():
            word, *_, time = line.split()
            key = {"scored B=5,4": "B45", "scored B=2,3": "B23"}.get(" ".join(line.split()[:2]),
                                                                     word)
            found[key] = datetime.fromisoformat(time.replace("Z", "+00:00"))
        return found

    def file(self, suffix: str) -> Path:
        return Path(f"{self.path}{suffix}")

    def json(self, suffix: str) -> dict:
        return json.loads(self.file(suffix).read_text())

    def minutes(self) -> float:
        return (self.wall["end"] - self.wall["start"]).total_seconds() / 60

    def members(self) -> list[dict]:
        """Per member of stages 1-2 (seed, then seed + 1000): the last update of stage 1
        and 2 and each stage's frames/s."""
        out = []
        for suffix, seed in (("_stages12.jsonl", self.seed), ("_m1_stages12.jsonl",
                                                               self.seed + 1000)):
            curve = _jsonl(self.file(suffix))
            cut = stage_cuts(curve)[0]
            out.append({"seed": seed, "stage1": cut, "stage2": len(curve),
                        "fps1": card_segment(curve, 0, cut)["frames_per_s"],
                        "fps2": card_segment(curve, cut, len(curve))["frames_per_s"]})
        return out

    def stage3_fps(self) -> float:
        curve = self.stage3["curve"]
        return card_segment(curve, 0, len(curve))["frames_per_s"]

    def board(self) -> dict:
        """The committed risk_aware board with this draw's ``ours_ti`` rows in place of
        the shipped network's (as ``board_diff.py --method-from`` reads it)."""
        board = boards.load(SUITE, ROOT / "leaderboards")
        mine = [r for r in boards.load(SUITE, f"{self.path}_board")["rows"]
                if r["method"] == METHOD]
        board["rows"] = [r for r in board["rows"] if r["method"] != METHOD] + mine
        return board

    def paired(self, exclude: tuple[tuple[int, int], ...] = ()) -> dict:
        """B = 5 against ``catnipp_ti``, episode by episode (``paired_subset.py``), with
        ``worst``: the worst episode's (instance, trial), its Tr(P_f) and traps, and
        ``catnipp_ti``'s Tr(P_f) there."""
        mine = _rows(self.file("_b5_results") / SUITE / f"{METHOD}.jsonl")
        ref = _rows(ROOT / PAIRED_RESULTS / SUITE / f"{PAIRED_AGAINST}.jsonl")
        keys = [k for k in mine if k[0] == "budget=5.0" and k[1:] not in exclude]
        found = pair(mine, ref, keys)
        k = found["worst"]
        found["worst"] = {"episode": k[1:], "trace": mine[k]["trace"],
                          "traps": mine[k]["traps"], "against": ref[k]["trace"]}
        return found


def scores(draw: Draw) -> dict[float, float]:
    rows = boards.keyed(boards.load(SUITE, f"{draw.path}_board"), [METHOD])
    return {b: rows[METHOD, f"budget={b}"]["trace_mean"] for b in BUDGETS}


def margins(draw: Draw) -> dict[float, tuple[str, float, float]]:
    """Per budget, the closest baseline and the unpaired difference to it."""
    found = {}
    for entry in board_diff.differences(draw.board(), METHOD, list(BASELINES)):
        name, (diff, se) = max(entry["diff"].items(), key=lambda kv: kv[1][0])
        found[float(entry["setting"].removeprefix("budget="))] = (name, diff, se)
    return dict(sorted(found.items()))


def table_margin(draw: Draw, budget: float, against: str) -> tuple[float, float]:
    entry = next(e for e in board_diff.differences(draw.board(), METHOD, [against])
                 if e["setting"] == f"budget={budget}")
    return entry["diff"][against]


def verdict(draw: Draw) -> tuple[str, list[float]]:
    """"by a margin" (ahead of every baseline at every budget, the table's three deciding
    margins each by two standard errors), "in the means", or "missed"; and the budgets at
    which a baseline is ahead in the mean."""
    diffs = board_diff.differences(draw.board(), METHOD, list(BASELINES))
    behind = [float(e["setting"].removeprefix("budget=")) for e in diffs
              if any(d >= 0 for d, _ in e["diff"].values())]
    if behind:
        return "missed", behind
    p = draw.paired()
    deciding = [table_margin(draw, 2.0, "sga_rrt_0.3_0.4"), table_margin(draw, 4.0, "catnipp_ti"),
                (p["diff"], p["se"])]
    return ("by a margin" if all(d + 2 * se < 0 for d, se in deciding) else "in the means"), []


def sga_version() -> int:
    from maipp_bench.algos.registry import POLICIES, get_method

    return getattr(POLICIES[get_method("sga_rrt_0.3_0.4").policy], "version", 1)


def pace(now: list[dict], before: list[dict], key: str) -> str:
    """How the members' frames/s compare with the previous draw's: "faster", "slower"
    or "about as fast as" (within 2% in the mean)."""
    ratio = st.mean(m[key] for m in now) / st.mean(m[key] for m in before)
    return "faster than" if ratio > 1.02 else "slower than" if ratio < 0.98 else \
        "about as fast as"


def final_choice(draw: Draw) -> dict:
    """FINAL=1's choice: which candidate was kept and its margins."""
    choice = draw.json("_choice.json")
    start, avg = choice["candidates"]  # final_choice.sh passes start.pt, then avg.pt
    kept_start = choice["chosen"]["position"] == start["position"]
    budgets = choice["budget"] if isinstance(choice["budget"], list) else [choice["budget"]]
    select = draw.json("_start_choice.json")
    return {"choice": choice, "start": start, "avg": avg, "kept_start": kept_start,
            "budgets": budgets,
            "ratio": choice["seconds"] / (select["seconds"] * work(choice) / work(select))}


def _member(path: str, draw: Draw) -> str:
    """"seed 60" or "seed 1060" for a candidate of the start choice."""
    return f"seed {draw.seed + 1000 if '/m1/' in path else draw.seed}"


def start_choice_text(draw: Draw) -> str:
    select = draw.json("_start_choice.json")
    cands, chosen = select["candidates"], select["chosen"]
    who = _member(chosen["path"], draw)
    ends = {_member(c["path"], draw): c for c in cands if c["path"].endswith("checkpoint.pt")}
    gap = ends[who]["update"] - chosen["update"]
    count = _CARDINAL[gap] if gap < len(_CARDINAL) else str(gap)
    where = ("its end" if gap == 0 else
             f"a snapshot {count} update{'s' if gap > 1 else ''} before its end")
    others = [c for c in cands if c["position"] != chosen["position"]]
    runner = min(c["mean"] for c in others)
    parts = []
    for member in dict.fromkeys(_member(c["path"], draw) for c in cands):
        own = [c for c in others if _member(c["path"], draw) == member]
        best = min(own, key=lambda c: c["mean"])
        text = (f"{member}'s end, update {best['update']}, {best['mean']:.2f}"
                if best is ends[member] else
                f"{member}'s update {best['update']}, {best['mean']:.2f}")
        if best is not ends[member] and ends[member] in own:
            text += f", and its end, update {ends[member]['update']}, {ends[member]['mean']:.2f}"
        parts.append(text)
    held = " and ".join(f"B = {b:g} {chosen[f'mean_B{b:g}']:.2f}" for b in select["budget"])
    last = cands[-1]
    text = (f"The start choice ({select['seconds']:.0f} s) kept **{who}'s update "
            f"{chosen['update']}**, {where}, by {runner - chosen['mean']:.2f} (score "
            f"{chosen['mean']:.2f}: held-out {held}; the best of the others: "
            f"{'; '.join(parts)}; `..._start_choice.json`, `select_snapshot.py --show`)")
    if chosen["position"] != last["position"]:
        zs = [(b, chosen[f"minus_end_B{b:g}"] / chosen[f"se_B{b:g}"]) for b in select["budget"]]
        text += (f"; against the last candidate, {_member(last['path'], draw)}'s end, the "
                 "chosen snapshot " + " and ".join(
                     f"{'led' if z < 0 else 'trailed'} by {abs(z):.1f} standard errors at "
                     f"B = {b:g}" for b, z in zs))
    return text + "."


def stage3_text(draw: Draw, previous: Draw) -> str:
    plan = draw.json("_deadline.json")
    if plan["minutes"] < plan["typed"]:
        given = f"`DEADLINE` **trimmed stage 3 to {plan['minutes']:g} minutes**"
    else:
        given = f"`DEADLINE` left stage 3 its {plan['typed']:g} minutes"
    s3 = draw.stage3
    f = final_choice(draw)
    updates = s3["averaged_updates"]
    kept, other = (("stage 3's start", "average") if f["kept_start"] else
                   ("the average", "start"))
    chosen, rest = (f["start"], f["avg"]) if f["kept_start"] else (f["avg"], f["start"])
    diffs = ", ".join(
        f"at B = {b:g} {_signed(f['start'][f'minus_end_B{b:g}'], f['start'][f'se_B{b:g}'], 2)}"
        f" ({abs(f['start'][f'minus_end_B{b:g}']) / f['start'][f'se_B{b:g}']:.1f} standard "
        "errors)" for b in f["budgets"])
    over = (f"over the average of its snapshots (updates {updates[0]}-{updates[-1]})"
            if f["kept_start"] else
            f"of stage 3's snapshots (updates {updates[0]}-{updates[-1]}) over its start")
    return (f"At stage 3's start {plan['elapsed']:g} minutes had passed; with the final "
            f"choice's reserve of {plan['final_estimate']:g} minutes, {given} "
            f"(`..._deadline.json`). Stage 3 made {s3['run_continued_to']} updates "
            f"(snapshots to {s3['updates']}; {draw.stage3_fps():.1f} frames/s over updates "
            f"1-{s3['updates']}, against the {ordinal(previous.number)}'s "
            f"{previous.stage3_fps():.1f}; `python benchmarks/train_throughput.py --card "
            f"{draw.prefix}{'_stage3_avg' if f['kept_start'] else ''}.json`) and the final "
            f"choice ({f['choice']['seconds']:.0f} s, {f['ratio']:.2f}x its estimate; "
            f"`stage3_minutes.py --calibrate`) kept **{kept}** {over}, by "
            f"{rest['mean'] - chosen['mean']:.2f} (held-out score {chosen['mean']:.2f} against "
            f"the {other}'s {rest['mean']:.2f}; start minus average {diffs}; "
            f"`..._choice.json`, `select_snapshot.py --show`; the set-aside {other}'s card is "
            f"`...{draw.set_aside}`).")


def protocol_text(draw: Draw) -> str:
    s = scores(draw)
    shipped = {b: r["trace_mean"] for (m, k), r in
               boards.keyed(boards.load(SUITE, ROOT / "leaderboards"), [METHOD]).items()
               if m == METHOD for b in BUDGETS if k == f"budget={b}"}
    ahead = [b for b in BUDGETS if round(s[b], 1) < round(shipped[b], 1)]
    versus = ("lower at every budget" if len(ahead) == len(BUDGETS) else
              "lower at none" if not ahead else
              "lower at B = " + ", ".join(f"{b:g}" for b in ahead) + " alone")
    at = draw.score_stamps()
    m = margins(draw)
    cells = "; ".join(f"B = {b:g} `{name}` {_signed(d, se, 1)}" for b, (name, d, se) in m.items()
                      if b != 5.0)
    return (f"Under the protocol it scores **{' / '.join(f'{s[b]:.1f}' for b in BUDGETS)}** "
            f"(`python benchmarks/board_table.py --suite risk_aware --leaderboards "
            f"{draw.prefix}_board`; evaluation {at['score_start']:%H:%M:%S}-"
            f"{at['B45']:%H:%M:%S} UTC for B = 4-5 and to {at['B23']:%H:%M:%S} for B = 2-3, "
            f"`..._score.txt`), beside the shipped `ours.pt`'s "
            f"{' / '.join(f'{shipped[b]:.1f}' for b in BUDGETS)} ({versus}). "
            f"Its margin to the closest baseline at each budget (this minus it, unpaired; "
            f"`board_diff.py --method ours_ti --method-from {draw.prefix}_board --against` "
            f"every baseline): {cells}.")


def paired_text(draw: Draw) -> str:
    p = draw.paired()
    worst = p["worst"]
    without = draw.paired((worst["episode"],))
    decides = (p["diff"] < 0) != (without["diff"] < 0)
    untrapped, trapped = p["untrapped"], p["trapped"]
    return (f"At **B = 5 it {_lead(p['diff'])} `catnipp_ti` by {abs(p['diff']):.2f} ± "
            f"{p['se']:.2f} paired** (z {p['diff'] / p['se']:+.1f}, {p['wins']} wins of "
            f"{p['n']}; traps {p['traps']:.2f} per episode). Its {untrapped[0]} untrapped "
            f"episodes {_lead(untrapped[1])[:-1]} by {abs(untrapped[1]):.2f} ± "
            f"{untrapped[2]:.2f} and its {trapped[0]} trapped ones "
            f"{_lead(trapped[1])[:-1]} by {abs(trapped[1]):.2f} ± {trapped[2]:.2f}; its worst "
            f"episode, {worst['trace']:.1f} "
            f"({worst['traps']} traps; instance {worst['episode'][0]}, trial "
            f"{worst['episode'][1]}, where `catnipp_ti` scored {worst['against']:.1f}), left "
            f"out, it {_lead(without['diff'])} by {abs(without['diff']):.2f} ± "
            f"{without['se']:.2f} (z {without['diff'] / without['se']:+.1f}; the second "
            f"command below): that one episode "
            f"{'decides' if decides else 'does not decide'} the ranking at B = 5.")


def counts_text(draw: Draw, minutes: float, level: float = 0.95) -> str:
    table = outcomes()
    if draw.number not in table:
        raise SystemExit(f"draw_section.py: draw {draw.number} has no row in docs/results.md's "
                         "table of draws; add the row (--row) first")
    draws = {d: o for d, o in table.items() if d <= draw.number}
    mine = family(draws[draw.number]["recipe"])
    same = [d for d, o in draws.items() if family(o["recipe"]) == mine]

    def rate(ds: list[int]) -> tuple[int, str]:
        k = sum(met(draws[d]) for d in ds)
        lo, hi = clopper_pearson(k, len(ds), level)
        return k, f"{k} of {len(ds)} ({lo:.0%} to {hi:.0%})"

    timely = sum(met(o) and "over 2 h" not in o["met"] for o in draws.values())
    name, behind = verdict(draw)
    words = (f"**misses** the ranking at B = {', '.join(f'{b:g}' for b in behind)}"
             if name == "missed" else f"**meets** the ranking **{name}**")
    return (f"So it {words}, {'within' if minutes <= 120 else 'over'} the compute goal "
            f"({minutes:.1f} minutes). Counts over the table's draws 1-{draw.number} "
            f"(`python benchmarks/draw_rate.py`; exact {level:.0%} intervals): `{mine}` "
            f"{rate(same)[1]}; all draws {rate(sorted(draws))[1]}, {timely} within two hours.")


def section(draw: Draw, previous: Draw, recipe: str) -> str:
    now, before = draw.members(), previous.members()
    minutes = draw.minutes()
    start, end = draw.wall["start"], draw.wall["end"]
    seeds = " and ".join(str(m["seed"]) for m in now)
    overrides = "OVERRIDES=algo.precision=bf16 " if draw.precision == "bf16" else ""
    cmd = (f"{draw.prefix}_b5_results --results {PAIRED_RESULTS} --method {METHOD} "
           f"--against {PAIRED_AGAINST}")
    worst = draw.paired()["worst"]["episode"]
    args = f"{draw.prefix} --draw {draw.number} --previous {previous.prefix}"
    return "\n".join([
        f"**A {ordinal(draw.number)} run: seed {draw.seed}, `{recipe}` with "
        f"{draw.precision}, under `DEADLINE`** ({start:%Y-%m-%d}).",
        f"On a 2-core {draw.machine} box with {draw.native} (the cards name commit "
        f"{draw.card['commit'][:7]}), scored by `benchmarks/score_draw.py` launched beside "
        "it; this section is rendered from the cards by `benchmarks/draw_section.py` (the "
        "last command):",
        "",
        "```bash",
        f"{recipe} {overrides}bash benchmarks/train_2h.sh {draw.out} "
        f"{draw.seed}",
        f"python benchmarks/score_draw.py {draw.out} --wait  # beside it: B = 5 and 4, then 2 "
        "and 3",
        f"python benchmarks/ship_draw.py {draw.out} {draw.prefix} --board {draw.out}_boards "
        f"--results {draw.out}_results",
        f"bash benchmarks/draw_figures.sh {draw.prefix} {previous.prefix}  # every figure below",
        f"python benchmarks/draw_section.py {args}",
        "```",
        "",
        f"{start:%Y-%m-%d %H:%M:%S} to {end:%H:%M:%S} UTC: **{minutes:.1f} minutes** "
        f"(`{draw.prefix}_wall.txt`). The members (seeds {seeds}) made **"
        f"{' and '.join(str(m['stage1']) for m in now)}** updates in stage 1 ("
        f"{_both(now, 'fps1')} frames/s, "
        f"{pace(now, before, 'fps1')} the {ordinal(previous.number)}'s "
        f"{_both(before, 'fps1')}) and "
        f"{' and '.join(str(m['stage2']) for m in now)} by the end of stage 2 ("
        f"{_both(now, 'fps2')} frames/s there, against "
        f"{_both(before, 'fps2')}; `python "
        f"benchmarks/train_throughput.py --card {draw.prefix}_stages12.jsonl --split stages`, "
        f"and the same for `..._m1_stages12.jsonl`). {start_choice_text(draw)} "
        f"{stage3_text(draw, previous)}",
        f"{protocol_text(draw)} {paired_text(draw)} {counts_text(draw, minutes)}",
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
    return (f"| {label} | {_updates(seg)} | "
            f"{seg['frames']:,} | {seg['decisions']:,} | {seg['wall_s']:,.0f} s | "
            f"{seg['frames_per_s']:.1f} | {seg['decisions_per_s']:.1f} |")


def performance(draw: Draw, previous: Draw, recipe: str) -> str:
    """The draw's rows of docs/performance.md: ``train_throughput.py --card``'s segments."""
    plan = draw.json("_deadline.json")
    start, end = draw.wall["start"], draw.wall["end"]
    steps = int(re.search(r"steps_per_batch=(\d+)", draw.card["command"])[1])
    seconds = [d.json(f)["seconds"] for d in (draw, previous)
               for f in ("_start_choice.json", "_choice.json")]
    chosen = draw.json("_start_choice.json")["chosen"]
    rows = []
    for i, (suffix, member) in enumerate((("_stages12.jsonl", draw.seed),
                                           ("_m1_stages12.jsonl", draw.seed + 1000))):
        curve = _jsonl(draw.file(suffix))
        cut = stage_cuts(curve)[0]
        one, two = card_segment(curve, 0, cut), card_segment(curve, cut, len(curve))
        envs = [seg["frames"] // _updates(seg) // steps for seg in (one, two)]
        first = (f"the same script and fields with `{recipe}`, {draw.precision}, seed "
                 f"{draw.seed} ({start:%Y-%m-%d, %H:%M}-{end:%H:%M} UTC, a 2-core {draw.machine} "
                 f"box with {draw.native}; the cards name commit {draw.card['commit'][:7]}; "
                 f"`DEADLINE={plan['deadline']:g}` gave stage 3 {plan['minutes']:g} minutes; "
                 f"its held-out choices took {seconds[0]:.0f} s and {seconds[1]:.0f} s against "
                 f"the {ordinal(previous.number)}'s {seconds[2]:.0f} s and {seconds[3]:.0f} s; "
                 f"docs/results.md \"A {ordinal(draw.number)} run\"), member seed {member}"
                 if i == 0 else f"the same, member seed {member} (beside it)")
        started = (f" (stage 3 started from update {chosen['update']})"
                   if _member(chosen["path"], draw) == f"seed {member}" else "")
        rows += [_perf_row(f"{first}, stage 1 ({envs[0]} envs x {steps} steps), updates "
                           f"{one['updates']}", one),
                 _perf_row(f"the same, member seed {member}, stage 2 ({envs[1]} envs x "
                           f"{steps} steps), updates {two['updates']}{started}", two)]
    curve = draw.stage3["curve"]
    kept = "start" if final_choice(draw)["kept_start"] else "average"
    other = "average" if kept == "start" else "start"
    rows.append(_perf_row(
        f"the same, stage 3 ({plan['minutes']:g} minutes, both threads), updates "
        f"1-{len(curve)} ({draw.stage3['run_continued_to']} made; the final choice kept the "
        f"{kept}; the set-aside {other}'s card, `...{draw.set_aside}`)",
        card_segment(curve, 0, len(curve))))
    return "\n".join(rows)


def row(draw: Draw, previous: Draw, recipe: str) -> str:
    plan = draw.json("_deadline.json")
    trimmed = (f"stage 3 trimmed to {plan['minutes']:.1f} min" if plan["minutes"] < plan["typed"]
               else "stage 3 not trimmed")
    held = draw.json("_start_choice.json")["heldout_set"]
    kept = "start" if final_choice(draw)["kept_start"] else "average"
    speed = pace(draw.members(), previous.members(), "fps1")
    s = scores(draw)
    b2, b4, p = (table_margin(draw, 2.0, "sga_rrt_0.3_0.4"), table_margin(draw, 4.0, "catnipp_ti"),
                 draw.paired())
    name, _ = verdict(draw)
    cells = [str(draw.number),
             f"`{recipe}`, {draw.precision}, held-out set {held}, cut defaults, under "
             f"`DEADLINE={plan['deadline']:g}` ({trimmed}), {draw.minutes():.1f} min, "
             f"{draw.machine}, {speed} the {ordinal(previous.number)}'s in stage 1 ({kept} kept)"
             + ("" if draw.minutes() <= 120 else ", over 2 h"),
             str(draw.seed), *(f"{s[b]:.1f}" for b in BUDGETS),
             f"{_signed(*b2, 1)} (v{sga_version()})", f"{_signed(*b4, 1)} (unpaired)",
             _signed(p["diff"], p["se"], 2), name]
    return "| " + " | ".join(cells) + " |"


def render(argv: list[str]) -> str:
    """The section (or with ``--row`` the table row) for command-line ``argv``."""
    p = argparse.ArgumentParser(prog="draw_section.py", description=__doc__.split("\n\n")[0])
    p.add_argument("prefix", help="the draw's card prefix, docs/cards/ours_2h_intent_...")
    p.add_argument("--draw", type=int, required=True, help="its number in the table")
    p.add_argument("--previous", required=True, help="the card prefix of the draw before")
    p.add_argument("--recipe", default=RECIPE, help="train_2h.sh's switches for the draw")
    what = p.add_mutually_exclusive_group()
    what.add_argument("--row", action="store_true", help="print the table row instead")
    what.add_argument("--performance", action="store_true",
                      help="print the draw's rows of docs/performance.md instead")
    args = p.parse_args(argv)
    if not 1 < args.draw < 100:
        p.error("--draw must be 2-99 (the section compares with the draw before)")
    draw, previous = Draw(args.prefix, args.draw), Draw(args.previous, args.draw - 1)
    render_ = row if args.row else performance if args.performance else section
    return render_(draw, previous, args.recipe)


def main() -> None:
    print(render(sys.argv[1:]))


if __name__ == "__main__":
    main()
