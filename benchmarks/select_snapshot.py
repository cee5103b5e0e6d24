"""Choose a training snapshot on held-out episodes: the selection step of
``benchmarks/train_2h.sh`` with ``SELECT=1`` (docs/results.md, "An eighth run").

Every candidate (the snapshots of ``--run``'s ``snapshots/`` from update ``last - window``
on, and the run's own ``checkpoint.pt``) plays ``--method`` on the same ``--episodes``
held-out episodes (training's held-out seeds, never the protocol's) at ``--budget``; the
one with the lowest mean Tr(P_f) is chosen (ties: the later update). Candidates are
scored in ``--workers`` processes of one thread each. The table goes to stderr and, with
the choice, to ``--out`` as JSON; stdout is the chosen path alone.

Usage:
    python benchmarks/select_snapshot.py --run outputs/h9/stage2 --window 15 \\
        --budget 2 --episodes 160 --workers 2 --out outputs/h9/select.json
"""

from __future__ import annotations

import argparse
import json
import re
import statistics as st
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from pathlib import Path

import torch
from paired_subset import mean_se


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


def _init_worker() -> None:
    torch.set_num_threads(1)


def _score(path: str, method: str, budget: float, episodes: int) -> list[float]:
    """Tr(P_f) of each held-out episode for ``method`` played with ``path``'s network."""
    from maipp_bench.algos.checkpoint import load_core
    from maipp_bench.algos.registry import get_method
    from maipp_bench.envs.config import MAIPPConfig
    from maipp_bench.train import heldout_rows

    core, payload = load_core(path)
    rows = heldout_rows(core, MAIPPConfig.from_dict(payload["env"]), episodes, budget,
                        get_method(method))
    return [r["trace"] for r in rows]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--run", type=Path, required=True, help="a training run's directory")
    p.add_argument("--window", type=int, default=15, metavar="UPDATES",
                   help="snapshots from update (last - UPDATES) on are candidates")
    p.add_argument("--method", default="ours_ti")
    p.add_argument("--budget", type=float, default=2.0)
    p.add_argument("--episodes", type=int, default=160)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--out", type=Path, help="write the scores and the choice here (JSON)")
    args = p.parse_args()
    if args.window < 0 or args.episodes < 2 or args.workers < 1 or args.budget <= 0:
        p.error("--window must be >= 0, --episodes >= 2, --workers >= 1, --budget > 0")

    from maipp_bench.algos.registry import get_method
    get_method(args.method)  # an unknown method fails here, before any worker starts

    found = candidates(args.run, args.window)
    start = time.perf_counter()
    with ProcessPoolExecutor(args.workers, mp_context=get_context("spawn"),
                             initializer=_init_worker) as pool:
        futures = [pool.submit(_score, str(path), args.method, args.budget, args.episodes)
                   for _, path in found]
        traces = [f.result() for f in futures]
    seconds = time.perf_counter() - start

    ref = traces[-1]  # the run's own end: what train_2h.sh without SELECT continues from
    table = []
    for (update, path), trace in zip(found, traces):
        diff, se = mean_se([t - r for t, r in zip(trace, ref)])
        table.append({"update": update, "path": str(path), "mean": st.mean(trace),
                      "minus_end": diff, "se": se})
        print(f"update {update:4d}: Tr(P_f) {st.mean(trace):7.2f}  minus the end "
              f"{diff:+6.2f} ± {se:.2f}  ({path})", file=sys.stderr, flush=True)
    best = min(table, key=lambda row: (row["mean"], -row["update"]))
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps({
            "method": args.method, "budget": args.budget, "episodes": args.episodes,
            "window": args.window, "seconds": round(seconds, 1), "candidates": table,
            "chosen": best}, indent=2) + "\n")
    print(f"chosen: update {best['update']} in {seconds:.0f} s", file=sys.stderr)
    print(best["path"])


if __name__ == "__main__":
    main()
