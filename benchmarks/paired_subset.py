"""Compare a checkpoint with the shipped one before shipping it: the figures of
docs/results.md ("Fine-tuning", "Traps against catnipp_ti").

* ``--heldout CKPT ...``: training's model-selection score (greedy episodes on held-out
  seeds, never the protocol's; ``maipp_bench.train.evaluate``) for each checkpoint, on
  the same episodes, at ``--budgets``; with ``--heldout-method ours_ti``, that method run
  with each checkpoint instead (model selection for the method the leaderboard ranks),
  with paired differences to the first checkpoint.
* ``--subset DIR --method M``: a quick-subset run (``eval --episodes N --out DIR``) paired
  episode by episode with the full rows of ``--against`` methods in ``--results``: mean
  Tr(P_f), traps, and the mean paired difference to the first ``--against`` method with
  its standard error.

Usage:
    python benchmarks/paired_subset.py --heldout maipp_bench/checkpoints/ours.pt \\
        maipp_bench/checkpoints/ours_v2ft.pt
    python benchmarks/paired_subset.py --heldout maipp_bench/checkpoints/ours.pt \\
        maipp_bench/checkpoints/ours_v2ft.pt --heldout-method ours_ti --budgets 2 3 4 5
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


def heldout(paths: list[str], episodes: int, budgets: list[float], method: str | None) -> None:
    """Each checkpoint on the same held-out episodes per budget: training's model-selection
    score (greedy) when ``method`` is None, else that registered method (e.g. ``ours_ti``)
    run with each checkpoint; paired differences to the first checkpoint."""
    from maipp_bench.algos.checkpoint import load_core
    from maipp_bench.algos.registry import get_method
    from maipp_bench.envs.config import MAIPPConfig
    from maipp_bench.protocol.runner import run_chunk
    from maipp_bench.train import HELDOUT_SEED_BASE, evaluate

    seeds = [HELDOUT_SEED_BASE + i for i in range(episodes)]
    for budget in budgets:
        print(f"budget {budget}: {episodes} held-out episodes, "
              + ("greedy (training's model selection)" if method is None else method))
        first: list[float] | None = None
        for path in paths:
            core, payload = load_core(path)
            env_cfg = MAIPPConfig.from_dict(payload["env"])
            if method is None:
                cfg = SimpleNamespace(eval_episodes=episodes, eval_budget=budget,
                                      algo=SimpleNamespace(name="heldout"))
                score = evaluate(SimpleNamespace(core=core), env_cfg, cfg)
                print(f"  {path} (update {payload.get('update')}): "
                      + ", ".join(f"{k} {v:.2f}" for k, v in score.items()))
                continue
            eval_cfg = env_cfg.replace(budget=budget, budget_min=0.0, node_encoding_dim=0)
            rows = run_chunk(get_method(method), eval_cfg, seeds, trial_seed=HELDOUT_SEED_BASE,
                             core=core)
            trace = [r["trace"] for r in rows]
            first = first or trace
            diff = [t - f for t, f in zip(trace, first)]
            se = st.stdev(diff) / len(diff) ** 0.5 if len(diff) > 1 else float("nan")
            print(f"  {path} (update {payload.get('update')}): Tr(P_f) {st.mean(trace):7.2f}"
                  f"  traps {st.mean(r['traps'] for r in rows):.2f}"
                  f"  minus first {st.mean(diff):+6.2f} ± {se:.2f}", flush=True)


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
    p.add_argument("--budgets", type=float, nargs="+", default=[3.0],
                   help="--heldout: budgets to score (training selects at 3)")
    p.add_argument("--heldout-method", metavar="METHOD",
                   help="--heldout: run this registered method (e.g. ours_ti) with each "
                        "checkpoint instead of training's greedy score")
    p.add_argument("--subset", type=Path, help="an eval --out folder's subset-N folder")
    p.add_argument("--suite", default="risk_aware")
    p.add_argument("--method")
    p.add_argument("--results", type=Path, default=Path("results"))
    p.add_argument("--against", nargs="+", default=[])
    args = p.parse_args()
    torch.set_num_threads(1)
    if args.heldout:
        heldout(args.heldout, args.episodes, args.budgets, args.heldout_method)
    if args.subset:
        if not (args.method and args.against):
            p.error("--subset needs --method and --against")
        paired(args.subset, args.suite, args.method, args.results, args.against)


if __name__ == "__main__":
    main()
