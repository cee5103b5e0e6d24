"""benchmarks/draw_section.py: a two-hour draw's section and table row of docs/results.md,
rendered from the draw's committed cards, agree with what the docs say."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest

ROOT = Path(__file__).parents[1]
RESULTS = ROOT / "docs" / "results.md"
CARDS = "docs/cards/ours_2h_intent_seed{}_bf16_final_h2_pop2_wide8_fb245"


@pytest.fixture
def draw_section(monkeypatch):
    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))
    import draw_section

    return draw_section


def _args(draw: int, *extra: str) -> list[str]:
    """Draw N's command line: table draws 60-63 are seeds 57-60."""
    return [CARDS.format(draw - 3), "--draw", str(draw), "--previous",
            CARDS.format(draw - 4), *extra]


def _written(ordinal: str) -> str:
    """The hand-written section of a draw, from its bold title to the next one, its line
    breaks as spaces."""
    text = RESULTS.read_text()
    start = text.index(f"**A {ordinal} run:")
    return " ".join(text[start:text.index("\n\n**", start + 1)].split())


def test_ordinal_names_draws_as_the_docs_do(draw_section):
    words = {1: "first", 2: "second", 12: "twelfth", 20: "twentieth", 21: "twenty-first",
             40: "fortieth", 63: "sixty-third", 64: "sixty-fourth", 99: "ninety-ninth"}
    assert {n: draw_section.ordinal(n) for n in words} == words
    for bad in (0, 100):
        with pytest.raises(ValueError, match="1-99"):
            draw_section.ordinal(bad)


def test_row_reproduces_the_hand_written_row_of_the_sixty_third_draw(draw_section):
    rendered = draw_section.render(_args(63, "--row"))
    assert rendered.startswith("| 63 | ")
    assert rendered in RESULTS.read_text().splitlines()


@pytest.mark.parametrize("draw", [61, 62, 63])
def test_rows_carry_the_hand_written_rows_figures(draw_section, draw):
    """Every cell but the recipe's prose (whose speed words were judged by hand before the
    rule of draw_section.py) is the hand-written row's: scores, margins, verdict."""
    def cells(line: str) -> list[str]:
        return [c.strip() for c in line.strip().strip("|").split("|")]

    rendered = cells(draw_section.render(_args(draw, "--row")))
    written = next(cells(line) for line in RESULTS.read_text().splitlines()
                   if line.startswith(f"| {draw} | `"))
    assert rendered[:1] + rendered[2:] == written[:1] + written[2:]
    recipe = written[1].split(" min, ")[0]  # the switches, trimming and minutes
    assert rendered[1].startswith(recipe)


def test_machine_names_as_the_docs_write_them(draw_section):
    assert draw_section.machine_name("x86_64, AMD EPYC, 2 cores, native bf16: yes") == "AMD EPYC"
    assert draw_section.machine_name(
        "x86_64, Intel(R) Xeon(R) Processor, 2 cores, native bf16: no") == "Intel Xeon"


@pytest.mark.parametrize("draw, ordinal, figures", [
    # the final choice kept stage 3's average
    (63, "sixty-third", ["**116.0 minutes**", "**105 and 104**", "58.4 and 58.0",
                         "208 and 198", "113.7 and 103.1", "The start choice (414 s)",
                         "**seed 60's update 207**", "by 1.37 (score 49.75",
                         "led by 1.4 standard errors at B = 2 and by 0.5 at B = 5",
                         "84.4 minutes had passed",
                         "**trimmed stage 3 to 25.16 minutes**",
                         "105.0 frames/s over updates 1-60", "357 s, 1.06x its estimate",
                         "by 0.46 (held-out score 43.20", "+0.53 ± 0.61",
                         "12.9 ± 1.8", "11.4 ± 1.3", "**at B = 5 alone**",
                         "**115.5 / 53.7 / 33.4 / 24.3**",
                         "11:05:40-11:18:55 UTC", "1.37 ± 0.85 paired", "145 wins of 300",
                         "Its 187 untrapped episodes lead by 0.56 ± 0.44", "0.70 ± 0.52",
                         "--exclude 631268:712092", "`..._stage3_start.json`"]),
    # one episode decides the ranking at B = 5: without it the draw leads
    (62, "sixty-second", ["**115.6 minutes**", "**96 and 96**", "**seed 1059's update 189**",
                          "**trimmed stage 3 to 25.64 minutes**", "322 s, 0.98x its estimate",
                          "by 3.88 (held-out score 44.04", "**119.0 / 54.4 / 33.0 / 23.0**",
                          "0.05 ± 0.39 paired", "137 wins of 300", "0.15 ± 0.34 (z -0.4",
                          "79.2", "instance 379142, trial 344034", "`catnipp_ti` scored 21.0",
                          "**at B = 5 alone**"]),
    # the final choice kept stage 3's start: stage 3's curve is the set-aside average's card
    (61, "sixty-first", ["**116.2 minutes**", "**99 and 98**", "188 and 184",
                         "**seed 1058's update 183**", "by 0.56 (score 51.12",
                         "trailed by 1.9 standard errors at B = 2 and led by 4.1 at B = 5",
                         "85.2 minutes had passed", "**meets** the ranking **in the means**",
                         "**trimmed stage 3 to 23.73 minutes**", "Stage 3 made 55 updates",
                         "96.8 frames/s over updates 1-55", "kept **stage 3's start**",
                         "by 3.21", "-3.84 ± 2.31", "**123.0 / 53.5 / 31.4 / 22.3**",
                         "0.67 ± 0.78 paired", "184 wins of 300", "1.35 ± 0.38",
                         "(z -3.6", "`..._stage3_avg.json`"]),
])
def test_section_cites_the_figures_of_the_hand_written_section(draw_section, draw, ordinal,
                                                               figures):
    """Each figure the generator prints is the one the hand-written section cites."""
    rendered, written = draw_section.render(_args(draw)), _written(ordinal)
    assert [f for f in figures if f not in rendered] == []
    assert [f for f in figures if f not in written] == []
    # the counts are over the table's draws up to this one, so later rows leave them be
    assert re.search(rf"all draws 23 of {draw} \(\d+% to \d+%\), 22 within two hours",
                     rendered)


@pytest.mark.parametrize("draw", [61, 63])
def test_performance_rows_carry_the_figures_of_docs_performance(draw_section, draw):
    """The five rows' figures (updates, frames, decisions, wall time, rates) are those
    docs/performance.md wrote up by hand for the draw, from train_throughput.py --card."""
    perf = [line.split(" | ")[1:] for line in
            (ROOT / "docs" / "performance.md").read_text().splitlines()]
    rows = draw_section.render(_args(draw, "--performance")).splitlines()
    assert len(rows) == 5
    assert [r for r in rows if r.split(" | ")[1:] not in perf] == []


def test_sections_marked_in_the_docs_are_what_the_cards_render(draw_section):
    """Every ``<!-- draw_section.py ARGS -->`` section of docs/results.md is the script's
    output for ARGS, its row is in the table and its rows in docs/performance.md: figures
    that drift from the cards, or a board rerun under them, fail here."""
    text = RESULTS.read_text()
    perf = (ROOT / "docs" / "performance.md").read_text().splitlines()
    markers = list(re.finditer(r"<!-- draw_section\.py (.+?) -->\n", text))
    assert markers, "docs/results.md marks no rendered section"
    for m in markers:
        args = shlex.split(m[1])
        assert text[m.end():].startswith(draw_section.render(args) + "\n"), args
        assert draw_section.render([*args, "--row"]) in text.splitlines(), args
        rows = draw_section.render([*args, "--performance"]).splitlines()
        assert [r for r in rows if r not in perf] == [], args


def test_counts_written_by_hand_are_draw_rates(draw_section):
    """The counts the status row, README and docs/training.md repeat after each draw are
    what ``benchmarks/draw_rate.py`` counts from the table (a draw added to the table
    without them fails here)."""
    from draw_rate import clopper_pearson, family, hits, minutes_span, missed_behind_ti, rate
    from draw_signals import outcomes

    draws = outcomes()
    everything = sorted(draws)
    done, timely = hits(everything, draws)
    (lo, hi), (lo2, hi2) = (clopper_pearson(len(k), len(everything), 0.95)
                            for k in (done, timely))
    newest = 'WIDE=8 FINAL_BUDGETS="2 4 5"'
    mine = [d for d, o in draws.items() if family(o["recipe"]) == newest]
    missed, behind = missed_behind_ti(draws)
    status = RESULTS.read_text().splitlines()[13]
    assert (f"met in the means in {len(done)} of {len(everything)} two-hour draws, "
            f"{len(timely)} of them within two hours** (`python benchmarks/draw_rate.py`; "
            f"exact 95% intervals {lo:.0%} to {hi:.0%} and {lo2:.0%} to {hi2:.0%})") in status
    family_rate = rate(len(hits(mine, draws)[0]), len(mine))
    assert '`FINAL_BUDGETS="2 4 5"`' in status and f"in {family_rate}," in status
    assert f"Most draws that missed ({len(behind)} of {len(missed)})" in status
    decided, either = draw_section.trailing_at_b5()

    def named(ns: list[int]) -> str:
        words = [draw_section.ordinal(n) for n in ns]
        return ", ".join(words[:-1]) + " and " + words[-1] if len(words) > 1 else words[0]

    assert (f"(the {named(decided)} draws trail `catnipp_ti` with theirs and lead without; "
            f"the {named(either)} trail either way;") in status
    timed = minutes_span(mine, draws).values()
    span = f"within {min(timed)} to {max(timed)} minutes"
    assert f"in {family_rate}, each {span}" in status
    assert f'to "A {draw_section.ordinal(max(everything))} run" |' in status
    of = family_rate.split(" (")[0]
    assert f"B = 2), {of}, each {span}" in (ROOT / "README.md").read_text()
    assert f'`FINAL_BUDGETS="2 4 5"` in {of}:' in (ROOT / "docs" / "training.md").read_text()


def test_bad_input_gets_a_clear_error(draw_section):
    with pytest.raises(SystemExit, match="no card docs/cards/no_seed1_draw.json"):
        draw_section.render(["docs/cards/no_seed1_draw", "--draw", "3", "--previous", "x"])
    with pytest.raises(SystemExit, match="draw 70 has no row"):
        draw_section.render([CARDS.format(60), "--draw", "70", "--previous", CARDS.format(59)])
    with pytest.raises(SystemExit):  # argparse's error: the section needs a draw before
        draw_section.render([CARDS.format(60), "--draw", "1", "--previous", CARDS.format(59)])
