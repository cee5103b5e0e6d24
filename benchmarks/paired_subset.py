"""Compare a checkpoint with the shipped one before shipping it: the figures of
docs/results.md ("Fine-tuning", "Traps against catnipp_ti").

* ``--heldout CKPT ...``: training's model-selection score (greedy episodes on held-out
  seeds, never the protocol's; ``maipp_bench.train.evaluate``) for each checkpoint, on
  the same episodes.
* ``--subset DIR --method M``: a quick-subset run (``eval --episodes N --out DIR``) paired
  episode by episode with the full rows of ``--against`` methods in ``--results``: mean
  Tr(P_f), traps, and the mean paired difference to the first ``--against`` method with
  its standard error.

Usage:
    python benchmarks/paired_subset.py --heldout maipp_bench/checkpoints/ours.pt \
        maipp_bench/checkpoints/ours_v2ft.pt
    python benchmarks/paired_subset.py --subset out/subset-60 --method ours_ti \\
        --against ours_ti catnipp_ti sga_rrt_0.3_0.4 oracle
"""

from __future__ import annotations

import argparse
import json
import statistics as st
from pathlib import Path
from types import SimpleNamespace

import torch


def heldout(paths: list[str], episodes: int, budget: float) -> None:
    from maipp_bench.algos.checkpoint import load_core
    from maipp_bench.envs.config import MAIPPConfig
    from maipp_bench.train import evaluate

    cfg = SimpleNamespace(eval_episodes=episodes, eval_budget=budget,
                          algo=SimpleNamespace(name="heldout"))
    for path in paths:
        core, payload = load_core(path)
        score = evaluate(SimpleNamespace(core=core), MAIPPConfig.from_dict(payload["env"]), cfg)
        print(f"{path} (update {payload.get('update')}): "
              + ", ".join(f"{k} {v:.2f}" for k, v in score.items()))


def _rows(path: Path) -> dict[tuple, dict]:
    return {(r["setting"], r["instance"], r["trial"]): r for r in map(json.loads, open(path))}


def paired(subset: Path, suite: str, method: str, results: Path, against: list[str]) -> None:
    runs = {f"{method} (subset)": _rows(subset / suite / f"{method}.jsonl")}
    runs |= {f"{m} (full)": _rows(results / suite / f"{m}.jsonl") for m in against}
    ref = runs[f"{against[0]} (full)"]
    for setting in sorted({k[0] for k in runs[f"{method} (subset)"]}):
        keys = [k for k in runs[f"{method} (subset)"] if k[0] == setting]
        print(f"{setting}: {len(keys)} episodes")
        for name, rows in runs.items():
            diff = [rows[k]["trace"] - ref[k]["trace"] for k in keys]
            se = st.stdev(diff) / len(diff) ** 0.5
            print(f"  {name:32s} Tr(P_f) {st.mean(rows[k]['trace'] for k in keys):7.1f}"
                  f"  traps {st.mean(rows[k]['traps'] for k in keys):.2f}"
                  f"  minus {against[0]} {st.mean(diff):+6.2f} ± {se:.2f}")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--heldout", nargs="+", metavar="CKPT")
    p.add_argument("--episodes", type=int, default=48)
    p.add_argument("--budget", type=float, default=3.0)
    p.add_argument("--subset", type=Path, help="an eval --out folder's subset-N folder")
    p.add_argument("--suite", default="risk_aware")
    p.add_argument("--method")
    p.add_argument("--results", type=Path, default=Path("results"))
    p.add_argument("--against", nargs="+", default=[])
    args = p.parse_args()
    torch.set_num_threads(1)
    if args.heldout:
        heldout(args.heldout, args.episodes, args.budget)
    if args.subset:
        if not (args.method and args.against):
            p.error("--subset needs --method and --against")
        paired(args.subset, args.suite, args.method, args.results, args.against)


if __name__ == "__main__":
    main()
