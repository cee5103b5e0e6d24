"""Choose a network on held-out episodes: the selection steps of
``benchmarks/train_2h.sh`` with ``SELECT=1`` (docs/results.md, "An eighth run") and
``FINAL=1`` ("The final choice").

Every candidate plays ``--method`` on the same held-out episodes (training's held-out
seeds from the ``--first``-th on, never the protocol's) at each ``--budget``:
``--episodes`` of them, one count for every budget or one per budget in the order of
``--budget`` (a B = 5 episode costs about two B = 2 ones); the one with the lowest score is
chosen, ties going to the later candidate. The score is the
mean Tr(P_f) at one budget and, at several budgets, the geometric mean of their means
(training's ``eval/trace``). The candidates are either each ``--run``'s own
``checkpoint.pt`` and the snapshots of its ``snapshots/`` from update ``last - window`` on
(oldest first; several runs, as ``train_2h.sh``'s ``POP=2`` passes them, in the order
given), or the files named by ``--candidates`` in the order given; the last candidate is the
reference that the table's paired differences are taken against. Candidates are scored
in ``--workers`` processes of one thread each. The table goes to stderr and, with the
choice, to ``--out`` as JSON (each candidate's ``mean`` is its score; with several
budgets, ``mean_B<b>``, ``minus_end_B<b>`` and ``se_B<b>`` per budget); stdout is the
chosen path alone.

Usage:
    python benchmarks/select_snapshot.py --run outputs/h9/stage2 --window 15 \\
        --budget 2 --episodes 160 --workers 2 --out outputs/h9/select.json
    python benchmarks/select_snapshot.py --candidates start.pt late.pt avg.pt \\
        --budget 4 5 --episodes 64 --first 160 --workers 2 --out final_select.json
    python benchmarks/select_snapshot.py --run outputs/h9/stage2 --window 15 \\
        --budget 2 5 --episodes 160 64 --workers 2 --out outputs/h9/select.json
    python benchmarks/select_snapshot.py --show outputs/h9/select.json  # its margins again
"""

from __future__ import annotations

import argparse
import json
import math
import re
import statistics as st
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from pathlib import Path

import torch
from paired_subset import mean_se, z_text

from maipp_bench.heldout import add_heldout_argument


def candidates(run: Path, window: int) -> list[tuple[int, Path]]:
    """(update, path) of the run's final checkpoint and of its snapshots from update
    ``last - window`` on, oldest first; a run without a checkpoint is a clear error."""
    final = run / "checkpoint.pt"
    if not final.exists():
        raise FileNotFoundError(f"{final}: no training checkpoint in --run {run}")
    last = int(torch.load(final, map_location="cpu", weights_only=False)["update"])
    found = {last: final}
    for snap in sorted((run / "snapshots").glob("update_*.pt")):
        match = re.fullmatch(r"update_(\d+)\.pt", snap.name)
        if match and last - window <= int(match.group(1)) < last:
            found[int(match.group(1))] = snap
    return sorted(found.items())


def named(paths: list[Path]) -> list[tuple[int, Path]]:
    """(update, path) of each file of ``--candidates``, in the order given; a missing
    file is a clear error before any worker starts."""
    missing = [str(p) for p in paths if not p.exists()]
    if missing:
        raise FileNotFoundError(f"--candidates: no such file: {', '.join(missing)}")
    return [(int(torch.load(p, map_location="cpu", weights_only=False).get("update", -1)), p)
            for p in paths]


def _init_worker() -> None:
    torch.set_num_threads(1)


def _traces(path: str, method: str, budget: float, episodes: int, first: int,
            heldout: int) -> list[float]:
    """Tr(P_f) of each held-out episode for ``method`` played with ``path``'s network."""
    from maipp_bench.algos.checkpoint import load_core
    from maipp_bench.algos.registry import get_method
    from maipp_bench.envs.config import MAIPPConfig
    from maipp_bench.train import heldout_rows

    core, payload = load_core(path)
    rows = heldout_rows(core, MAIPPConfig.from_dict(payload["env"]), episodes, budget,
                        get_method(method), first=first, heldout=heldout)
    return [r["trace"] for r in rows]


def differences(row: dict) -> str:
    """A candidate's paired differences against the last candidate, one per budget, each
    with its z; empty for the last candidate itself (its errors are 0)."""
    # main() keys one budget as minus_end / se, several as minus_end_B<b> / se_B<b>.
    suffixes = [k.removeprefix("minus_end") for k in row if k.startswith("minus_end")]
    return "  ".join(f"{s.lstrip('_') or 'all'}: {row['minus_end' + s]:+.2f} ± "
                     f"{row['se' + s]:.2f}{z_text(row['minus_end' + s], row['se' + s])}"
                     for s in suffixes if row["se" + s] > 0)


def margins(choice: dict) -> list[str]:
    """A written choice's margins, as the docs quote them ("kept X by D", "N standard
    errors"): each other candidate's score minus the chosen one's (lower is better) and
    the paired differences of every candidate, the chosen one included, against the last."""
    best = choice["chosen"]
    own = differences(best)
    lines = [f"chosen: update {best['update']} ({best['path']}), score {best['mean']:.2f}"
             + (f"; minus the last candidate: {own}" if own else "")]
    for row in choice["candidates"]:
        if row["position"] == best["position"]:
            continue
        lines.append(f"  update {row['update']} ({row['path']}): {row['mean']:.2f}, "
                     f"{row['mean'] - best['mean']:+.2f} behind the chosen; "
                     f"minus the last candidate: {differences(row) or 'none (it is the last)'}")
    return lines


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    source = p.add_mutually_exclusive_group(required=True)
    source.add_argument("--show", type=Path, metavar="JSON",
                        help="print the margins of a choice written by --out; scores nothing")
    source.add_argument("--run", type=Path, nargs="+",
                        help="one or more training runs' directories")
    source.add_argument("--candidates", type=Path, nargs="+", metavar="FILE",
                        help="checkpoints or policy files (the last is the reference)")
    p.add_argument("--window", type=int, default=15, metavar="UPDATES",
                   help="with --run: snapshots from update (last - UPDATES) on are candidates")
    p.add_argument("--method", default="ours_ti")
    p.add_argument("--budget", type=float, nargs="+", default=[2.0],
                   help="one or more budgets (several: geometric mean of the means)")
    p.add_argument("--episodes", type=int, nargs="+", default=[160],
                   help="held-out episodes per budget: one count, or one per --budget")
    p.add_argument("--first", type=int, default=0, metavar="N",
                   help="start at the N-th held-out seed (e.g. after those of an earlier "
                        "choice, so that the two choices see different worlds)")
    add_heldout_argument(p)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--out", type=Path, help="write the scores and the choice here (JSON)")
    args = p.parse_args()
    if args.show is not None:
        print("\n".join(margins(json.loads(args.show.read_text()))))
        return
    budgets = sorted(set(args.budget))
    typed = " ".join(f"{b:g}" for b in args.budget)
    if len(budgets) != len(args.budget):
        p.error(f"--budget takes each budget once, got {typed}")
    if len(args.episodes) not in (1, len(args.budget)):
        p.error(f"--episodes takes one count or one per budget, got --budget {typed} "
                f"--episodes {' '.join(map(str, args.episodes))}")
    episodes_at = dict(zip(args.budget, args.episodes * len(args.budget)
                          if len(args.episodes) == 1 else args.episodes))
    if (args.window < 0 or min(args.episodes) < 2 or args.workers < 1 or args.first < 0
            or not all(math.isfinite(b) and b > 0 for b in budgets)):
        p.error("--window must be >= 0, --episodes >= 2, --workers >= 1, --first >= 0, "
                "budgets > 0")

    from maipp_bench.algos.registry import get_method
    from maipp_bench.train import trace_score
    get_method(args.method)  # an unknown method fails here, before any worker starts

    found = ([c for run in args.run for c in candidates(run, args.window)]
             if args.run is not None else named(args.candidates))
    start = time.perf_counter()
    with ProcessPoolExecutor(args.workers, mp_context=get_context("spawn"),
                             initializer=_init_worker) as pool:
        futures = [[pool.submit(_traces, str(path), args.method, b, episodes_at[b], args.first,
                                args.heldout_set)
                    for b in budgets] for _, path in found]
        traces = [[f.result() for f in per_budget] for per_budget in futures]
    seconds = time.perf_counter() - start

    # The last candidate is the reference: with --run, the (last) run's own end (what
    # train_2h.sh without SELECT continues from); with --candidates, the file named last.
    ref = traces[-1]
    table = []
    for i, ((update, path), per_budget) in enumerate(zip(found, traces)):
        means = [st.mean(t) for t in per_budget]
        row = {"update": update, "path": str(path), "mean": trace_score(means)}
        line = f"update {update:4d}: score {row['mean']:7.2f}"
        for b, mean, t, r in zip(budgets, means, per_budget, ref):
            diff, se = mean_se([x - y for x, y in zip(t, r)])
            suffix = "" if len(budgets) == 1 else f"_B{b:g}"
            row |= {f"mean{suffix}": mean, f"minus_end{suffix}": diff, f"se{suffix}": se}
            line += (f"  B = {b:g}: {mean:7.2f}, minus the last candidate "
                     f"{diff:+6.2f} ± {se:.2f}")
        row["position"] = i
        table.append(row)
        print(f"{line}  ({path})", file=sys.stderr, flush=True)
    best = min(table, key=lambda row: (row["mean"], -row["position"]))
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps({
            "method": args.method, "budget": budgets[0] if len(budgets) == 1 else budgets,
            "episodes": (args.episodes[0] if len(set(episodes_at.values())) == 1
                         else [episodes_at[b] for b in budgets]),  # as "budget" lists them
            "first": args.first, "heldout_set": args.heldout_set,
            "window": args.window if args.run is not None else None,
            "seconds": round(seconds, 1), "candidates": table, "chosen": best},
            indent=2) + "\n")
    print(f"chosen: {best['path']} (update {best['update']}) in {seconds:.0f} s",
          file=sys.stderr)
    print(best["path"])


if __name__ == "__main__":
    main()
