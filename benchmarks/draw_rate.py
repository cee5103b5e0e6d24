"""How often does a two-hour draw meet the ranking target, per recipe?

Reads docs/results.md's table "All two-hour runs, one table" (the same rows as
``draw_signals.py``) and counts, per recipe family, the draws that met the target in the
means ("in the means" or "by a margin") and those that also stayed within two hours (not
"over 2 h"), each with an exact (Clopper-Pearson) 95% interval for the rate: with a
handful of draws per recipe, the interval says how little the count alone pins down.
Then how many of the draws that missed were behind ``catnipp_ti`` at B = 5 in the mean,
and, per family, at which of the table's deciding budgets (B = 2, 4, 5) each missed draw
was behind,
which draws have the three lowest scores at each budget, each family's shortest and longest run
(where the recipe cell states its minutes), and how often the ``FINAL=1`` draws' final
choice kept stage 3's start over its average (the cells' "(start kept)" / "(average kept)").
With ``--plot PATH``, a figure of every draw's two deciding margins, the table's B = 2
minus ``sga_rrt_0.3_0.4`` and B = 5 minus ``catnipp_ti`` (each with two standard errors),
coloured by whether the draw met the target: where the draws miss, at a glance.

Families, from the switches in the table's recipe cell (its first code span):
``WIDE=8 FINAL_BUDGETS="2 4 5"`` (``WIDE=8`` whose final choice scores B = 2 as well),
``WIDE=8`` (every stage's frames as 8x the envs for 1/8 of the steps), ``STAGE3=0``
(no stage 3: its minutes go to stage 2), ``POP=2`` (two seeds side by side, the better kept
on held-out episodes), ``SELECT=1 FINAL=1``, ``SELECT=1`` and ``fixed`` (no switches, the
first draws); "all" pools them. A family whose draws trained in both precisions (the
recipe cell has a field starting "bf16" or not: float32) gets a line for each under its own.

Usage:
    python benchmarks/draw_rate.py [--level 0.95] [--plot docs/img/draws_2h_margins.png]
"""

from __future__ import annotations

import argparse
from pathlib import Path

from draw_signals import outcomes, switches
from scipy.stats import beta

# tested in order: WIDE=8 (every stage 8x the envs for 1/8 of the steps) is a family of
# its own, not counted with the POP=2 draws whose switches it also has, and the WIDE=8
# draws whose final choice also scored B = 2 are one of theirs, not counted with WIDE=8's
FAMILIES = ('WIDE=8 FINAL_BUDGETS="2 4 5"', "WIDE=8", "STAGE3=0", "POP=2",
            "SELECT=1 FINAL=1", "SELECT=1")
# each family's switches, split once as a recipe cell's are
FAMILY_SWITCHES = {f: switches(f"`{f}`") for f in FAMILIES}


def family(recipe: str) -> str:
    """The first family whose switches all appear in the recipe cell's first code span;
    "fixed" when none does."""
    found = switches(recipe)
    return next((f for f in FAMILIES if FAMILY_SWITCHES[f] <= found), "fixed")


def clopper_pearson(k: int, n: int, level: float) -> tuple[float, float]:
    """Exact two-sided interval for a binomial rate with ``k`` successes of ``n``."""
    a = (1 - level) / 2
    lo = 0.0 if k == 0 else float(beta.ppf(a, k, n - k + 1))
    hi = 1.0 if k == n else float(beta.ppf(1 - a, k + 1, n - k))
    return lo, hi


def precision(recipe: str) -> str:
    """The training precision a recipe cell lists: "bf16" when one of its comma-separated
    fields starts with it (a box's "without native bf16" does not count), else float32."""
    return "bf16" if any(f.strip().startswith("bf16") for f in recipe.split(",")) else "float32"


def met(outcome: dict) -> bool:
    """Whether a draw met the ranking target in the means (its "met" cell)."""
    return outcome["met"].startswith(("in the means", "by a margin"))


def hits(ds: list[int], draws: dict[int, dict]) -> tuple[list[int], list[int]]:
    """The draws of ``ds`` that met the target in the means, and of them those within two
    hours."""
    done = [d for d in ds if met(draws[d])]
    return done, [d for d in done if "over 2 h" not in draws[d]["met"]]


def missed_behind_ti(draws: dict[int, dict]) -> tuple[list[int], list[int]]:
    """The draws that missed, and of them those behind ``catnipp_ti`` at B = 5 in the
    mean."""
    missed = [d for d, o in draws.items() if not met(o)]
    return missed, [d for d in missed if draws[d]["B5_minus_ti"] > 0]


def minutes_span(ds: list[int], draws: dict[int, dict]) -> dict[int, float]:
    """The minutes of the draws in ``ds`` whose recipe cell states them (the docs write
    their span, "within LO to HI minutes")."""
    return {d: draws[d]["minutes"] for d in ds if draws[d]["minutes"] is not None}


def rate(k: int, n: int, level: float = 0.95) -> str:
    """"k of n (lo% to hi%)", the docs' way of writing a rate with its exact interval."""
    lo, hi = clopper_pearson(k, n, level)
    return f"{k} of {n} ({lo:.0%} to {hi:.0%})"


def print_rate(name: str, ds: list[int], draws: dict[int, dict], level: float,
               width: int = 18) -> None:
    """One line of the table: the draws met in the means, and of them within two hours."""
    hits_, timely = hits(ds, draws)
    cells = []
    for k in (len(hits_), len(timely)):
        lo, hi = clopper_pearson(k, len(ds), level)
        cells.append(f"{k:2d} ({lo:4.0%} to {hi:4.0%})")
    print(f"{name:{width}} {len(ds):5d}  {cells[0]:18}  {cells[1]:18}  "
          f"{', '.join(map(str, hits_))}")


def plot_margins(draws: dict[int, dict], out: Path) -> None:
    """Each draw's B = 2 and B = 5 margins (negative: ahead of the baseline) with two
    standard errors, coloured by met / missed, marked by training precision."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = (("B = 2 minus sga_rrt_0.3_0.4 (v2's row to draw 28, v3's after)",
               "B2_minus_sga_mean_se"),
              ("B = 5 minus catnipp_ti (paired)", "B5_minus_ti_mean_se"))
    fig, axes = plt.subplots(2, 1, figsize=(10, 6.5), sharex=True)
    for ax, (title, key) in zip(axes, panels):
        for d in sorted(draws):
            mean, se = draws[d][key]
            ax.errorbar(d, mean, yerr=2 * se, color="tab:green" if met(draws[d]) else "tab:red",
                        marker="s" if precision(draws[d]["recipe"]) == "bf16" else "o",
                        ms=5, capsize=2, lw=1)
        ax.axhline(0, color="k", lw=0.8)
        ax.set_title(title, fontsize=10)
        ax.set_ylabel("Tr(P) difference")
        ax.grid(alpha=0.3)
    axes[-1].set_xlabel("draw (docs/results.md, 'All two-hour runs, one table')")
    handles = [plt.Line2D([], [], color=c, marker=m, ls="", label=lab)
               for c, m, lab in (("tab:green", "o", "met in the means"),
                                 ("tab:red", "o", "missed"),
                                 ("gray", "o", "float32"), ("gray", "s", "bf16"))]
    axes[0].legend(handles=handles, fontsize=8, ncol=4, loc="upper left")
    fig.suptitle("Two-hour draws: margins below 0 are ahead of the baseline "
                 "(bars: two standard errors)", fontsize=11)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    print(f"wrote {out}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--level", type=float, default=0.95)
    parser.add_argument("--plot", type=Path, default=None,
                        help="write a figure of every draw's B = 2 and B = 5 margins here")
    args = parser.parse_args()
    if not 0 < args.level < 1:
        raise SystemExit(f"--level must be in (0, 1), got {args.level}")
    draws = outcomes()
    groups: dict[str, list[int]] = {}
    for d, o in sorted(draws.items()):
        groups.setdefault(family(o["recipe"]), []).append(d)
    groups["all"] = sorted(draws)
    width = max(18, *map(len, groups))
    print(f"{'family':{width}} {'draws':>5}  {'met':18}  {'met within 2 h':18}  draws met")
    for name, ds in groups.items():
        print_rate(name, ds, draws, args.level, width)
        by_precision: dict[str, list[int]] = {}
        for d in ds:
            by_precision.setdefault(precision(draws[d]["recipe"]), []).append(d)
        if name != "all" and len(by_precision) > 1:  # a family that mixes precisions
            for prec, pds in sorted(by_precision.items()):
                print_rate(f"  {prec}", pds, draws, args.level, width)
    print(f"(exact {args.level:.0%} intervals for each rate)")
    missed, behind = missed_behind_ti(draws)
    print(f"missed: {len(missed)}, of them behind catnipp_ti at B = 5 in the mean: "
          f"{len(behind)} ({', '.join(map(str, sorted(behind)))})")
    from draw_section import trailing_at_b5  # it imports this module: import it late

    decided, either = trailing_at_b5()
    print(f"behind catnipp_ti at B = 5 from draw 60 on, ahead without their costliest "
          f"episode: {', '.join(map(str, decided))}; behind either way: "
          f"{', '.join(map(str, either))}")
    deciding = {2: "B2_minus_sga_mean_se", 4: "B4_minus_ti_mean_se", 5: "B5_minus_ti_mean_se"}
    for name, ds in groups.items():
        behind_at = {d: [b for b, key in deciding.items() if draws[d][key][0] > 0]
                     for d in ds if d in missed}
        if behind_at and name != "all":  # the families' lines already list every draw
            print(f"missed, {name}, behind at (of the table's B = 2, 4, 5): " + ", ".join(
                f"{d} B = {'/'.join(map(str, bs)) or 'none'}" for d, bs in behind_at.items()))
    for budget in (2, 3, 4, 5):  # the lowest, then the next two (where a draw ranks)
        low = sorted(draws, key=lambda d: draws[d]["scores"][budget])[:3]
        print(f"lowest B = {budget}: " + ", ".join(
            f"{draws[d]['scores'][budget]} (draw {d})" for d in low))
    for name, ds in groups.items():
        timed = minutes_span(ds, draws)
        if timed:
            print(f"minutes, {name}: {min(timed.values())} to {max(timed.values())} "
                  f"(shortest draw {min(timed, key=timed.get)}; {len(timed)} of "
                  f"{len(ds)} draws state them)")
    final = [d for d in draws if "FINAL=1" in draws[d]["recipe"]]
    kept = {which: [d for d in final if f"({which} kept" in draws[d]["recipe"]]
            for which in ("start", "average")}
    if len(kept["start"]) + len(kept["average"]) != len(final):
        raise SystemExit(f"FINAL=1 draws without a '(start kept)' / '(average kept)' cell: "
                         f"{sorted(set(final) - set(kept['start']) - set(kept['average']))}")
    print(f"FINAL=1 draws: {len(final)}, the final choice kept stage 3's start in "
          f"{len(kept['start'])} ({', '.join(map(str, kept['start']))}), its average in "
          f"{len(kept['average'])} ({', '.join(map(str, kept['average']))})")
    if args.plot is not None:
        plot_margins(draws, args.plot)

if __name__ == "__main__":
    main()
