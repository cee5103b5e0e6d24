"""Does anything early in a two-hour draw's training curve predict how it scores?

For each draw of ``benchmarks/train_2h.sh`` in docs/results.md's table "All two-hour
runs, one table" (its outcomes: the B = 2 score and B = 5 minus ``catnipp_ti``, paired),
reads the draw's training curves from ``docs/cards/`` (stages 1-2, then stage 3) and
computes curve features over windows of updates: mean reward per decision and mean
final Tr(P) of the training episodes (weighted by the episodes ending in each update).
Prints Spearman's rho of each feature with each outcome, with a two-sided permutation
p-value, over all draws and over the ``SELECT=1`` draws (8 on), and how often choosing
the draw with the better feature of two would have chosen the better outcome: whether
a recipe could spend its two hours on the more promising of two seeds.

Usage:
    python benchmarks/draw_signals.py [--permutations 5000] [--out signals.json]
"""

from __future__ import annotations

import argparse
import itertools
import json
import re
import shlex
from pathlib import Path

import numpy as np
from scipy.stats import rankdata

ROOT = Path(__file__).resolve().parent.parent
CARDS = ROOT / "docs" / "cards"
# draw -> the prefix of its cards under docs/cards/ours_2h_intent_*, from the sections of
# docs/results.md that report each draw ("The whole recipe in two hours on both cores"
# to "A twentieth run"). Draw 7 continued draw 6's stages 1-2 and draws 3-4 share seed
# 2's first 96 updates. Which card holds which stages: see `stage_cards`.
DRAWS = {
    1: "seed0",
    2: "seed1",
    3: "seed2",
    4: "seed2_lr3e-5",
    5: "seed3_lr3e-5",
    6: "seed4_lr3e-5",
    7: "seed4_m38-55-18",
    8: "seed5_select",
    9: "seed6_select",
    10: "seed7_select",
    11: "seed8_bf16_select",
    12: "seed9_bf16_select",
    13: "seed10_bf16_lr1e-4_select",
    14: "seed11_bf16_lr1e-4_select",
    15: "seed12_bf16_final",
    16: "seed13_bf16_final",
    17: "seed14_bf16_final",
    18: "seed15_bf16_final_h2",
    19: "seed16_bf16_final_h2",
    20: "seed17_bf16_final_h2",
}
# Draws of another shape are left out, read from the table's recipe cell: POP=2 trains two
# members side by side in stages 1-2, one thread each (half the updates), so their early
# curves are not one run's at one pace.
LEFT_OUT_SWITCH = "POP=2"
STAGE1_FRAMES = 1280  # 8 envs x 160 steps per stage-1 update; 16 envs after


def stage_cards(prefix: str) -> tuple[str, str]:
    """(stages 1-2 curve, stage 3 card) of a draw: a draw whose final choice kept stage 3's
    start has that start's card (holding stages 1-2) and its set-aside average
    (``_stage3_avg.json``); the others a curve file of stages 1-2 and the policy's card."""
    if (CARDS / f"ours_2h_intent_{prefix}_stage3_avg.json").exists():
        return f"{prefix}.json", f"{prefix}_stage3_avg.json"
    return f"{prefix}_stages12.jsonl", f"{prefix}.json"


def curve(name: str) -> list[dict]:
    """A card's per-update rows (``.jsonl``: one row a line; ``.json``: its curve)."""
    path = CARDS / f"ours_2h_intent_{name}"
    if path.suffix == ".jsonl":
        return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    return json.loads(path.read_text())["curve"]


def table_rows() -> dict[int, list[str]]:
    """The cells of each draw's row of the docs' table "All two-hour runs, one table"."""
    text = (ROOT / "docs" / "results.md").read_text()
    table = text[text.index("**All two-hour runs, one table.**"):]
    found = {}
    for line in table.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) == 11 and cells[0].isdigit():
            found[int(cells[0])] = cells
        elif found and not line.startswith("|"):
            break
    return found


def margin(cell: str) -> tuple[float, float]:
    """A margin cell of the table ("-3.7 ± 2.2 (v3)") as (mean, standard error)."""
    m = re.match(r"\s*([+-]?[0-9.]+)\s*±\s*([0-9.]+)", cell)
    if m is None:
        raise SystemExit(f"not a margin cell 'mean ± se': {cell!r}")
    return float(m.group(1)), float(m.group(2))


def run_minutes(recipe: str) -> float | None:
    """The whole run's minutes where the recipe cell states them (", 116.0 min"); a stage
    split ("33 / 30 / 48 min") or stage 3's share ("trimmed to 24.9 min") is not the run's
    total and gives None, as does no figure."""
    m = re.search(r", (\d+(?:\.\d+)?) min\b", recipe)
    return float(m.group(1)) if m else None


def outcomes() -> dict[int, dict]:
    """Each draw's scores at B = 2-5 (``scores``; B = 2's also as ``B2``), its margins
    (mean, standard error) at B = 2 against ``sga_rrt_0.3_0.4`` and at B = 4 and 5 against
    ``catnipp_ti``, B = 5's mean alone as ``B5_minus_ti``, its minutes where the recipe
    cell states them, and its recipe and "met" cells, from the docs' table."""
    out = {}
    for draw, cells in table_rows().items():
        b2, b4, b5 = margin(cells[7]), margin(cells[8]), margin(cells[9])
        scores = dict(zip((2, 3, 4, 5), map(float, cells[3:7])))
        out[draw] = {"B2": scores[2], "scores": scores, "B2_minus_sga_mean_se": b2,
                     "B4_minus_ti_mean_se": b4, "B5_minus_ti_mean_se": b5, "B5_minus_ti": b5[0],
                     "minutes": run_minutes(cells[1]), "recipe": cells[1], "met": cells[10]}
    return out


def switches(recipe: str) -> set[str]:
    """The switches of a recipe cell: the words of its first code span (none: "fixed"), as
    the shell splits them (``FINAL_BUDGETS="2 4 5"`` is one switch, ``FINAL_BUDGETS=2 4 5``)."""
    span = re.search(r"`([^`]*)`", recipe)
    return set(shlex.split(span.group(1))) if span else set()


def window_mean(rows: list[dict], key: str) -> float:
    """Mean of ``key``; final traces weighted by the episodes that ended in each update
    (``ended``: the curve's cumulative ``episodes`` differenced, so windows need no row
    before them)."""
    v = np.array([r.get(key, np.nan) for r in rows], float)
    w = np.array([r["ended"] for r in rows], float) if key == "trace_final" \
        else np.ones(len(v))
    ok = np.isfinite(v) & (w > 0)
    return float((v[ok] * w[ok]).sum() / w[ok].sum()) if ok.any() else float("nan")


def features(draw: int) -> dict[str, float]:
    s12, s3 = (curve(name) for name in stage_cards(DRAWS[draw]))
    for rows in (s12, s3):
        ended = np.diff([0] + [r["episodes"] for r in rows])
        rows[:] = [{**r, "ended": int(n)} for r, n in zip(rows, ended)]
    frames = np.diff([0] + [r["frames"] for r in s12])
    stage1_end = int(np.nonzero(frames == STAGE1_FRAMES)[0].max()) + 1
    stage2 = s12[stage1_end:]
    windows = {"u1-40": s12[:40], "u41-80": s12[40:80], "u1-80": s12[:80],
               "first20min": [r for r in s12 if r["wall_s"] <= 1200],
               "s1last40": s12[:stage1_end][-40:], "s2last40": stage2[-40:], "s3": s3}
    out = {f"{short}_{w}": window_mean(rows, key) for w, rows in windows.items()
           for key, short in (("reward_per_decision", "rpd"), ("trace_final", "trace"))}
    out["stage1_updates"] = float(stage1_end)
    return out


def spearman_perm(x: list[float], y: list[float], n: int, rng: np.random.Generator
                  ) -> tuple[float, float]:
    """Spearman's rho and its two-sided permutation p-value."""
    rx, ry = (rankdata(v) for v in (x, y))
    rx, ry = (rx - rx.mean()) / rx.std(), (ry - ry.mean()) / ry.std()
    rho = float((rx * ry).mean())
    null = (np.stack([rng.permutation(ry) for _ in range(n)]) * rx).mean(1)
    return rho, float((np.sum(np.abs(null) >= abs(rho) - 1e-12) + 1) / (n + 1))


def pick_rate(feats: dict, outs: dict, draws: list[int], name: str, outcome: str
              ) -> tuple[int, int]:
    """Pairs of draws in which the one with the better feature (higher reward, lower
    trace) also has the better (lower) outcome, and the pairs compared."""
    higher_better = name.startswith(("rpd", "stage1"))
    good = total = 0
    for i, j in itertools.combinations(draws, 2):
        fi, fj = feats[i][name], feats[j][name]
        if fi == fj or outs[i][outcome] == outs[j][outcome]:
            continue
        pick, other = (i, j) if (fi > fj) == higher_better else (j, i)
        total += 1
        good += outs[pick][outcome] < outs[other][outcome]
    return good, total


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--permutations", type=int, default=5000)
    parser.add_argument("--out", type=Path, help="write every correlation as JSON")
    args = parser.parse_args()
    outs = {d: o for d, o in outcomes().items() if LEFT_OUT_SWITCH not in switches(o["recipe"])}
    if sorted(outs) != sorted(DRAWS):
        raise SystemExit(f"docs table draws {sorted(outs)} != mapped draws {sorted(DRAWS)}")
    feats = {d: features(d) for d in DRAWS}
    rng = np.random.default_rng(0)
    subsets = {"all": sorted(DRAWS), "SELECT=1": [d for d in DRAWS if d >= 8]}
    rows = []
    for subset, draws in subsets.items():
        for outcome in ("B5_minus_ti", "B2"):
            for name in feats[1]:
                rho, p = spearman_perm([feats[d][name] for d in draws],
                                       [outs[d][outcome] for d in draws],
                                       args.permutations, rng)
                good, total = pick_rate(feats, outs, draws, name, outcome)
                rows.append({"subset": subset, "outcome": outcome, "feature": name,
                             "n": len(draws), "rho": rho, "p": p, "picks_better": good,
                             "pairs": total})
    print(f"{'subset':9} {'outcome':12} {'feature':18} {'n':>3} {'rho':>6} {'p':>6}  "
          "better pick")
    for r in rows:
        print(f"{r['subset']:9} {r['outcome']:12} {r['feature']:18} {r['n']:3d} "
              f"{r['rho']:+6.2f} {r['p']:6.3f}  {r['picks_better']}/{r['pairs']}")
    if args.out:
        args.out.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
