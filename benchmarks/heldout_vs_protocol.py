"""Do held-out scores rank networks as the protocol does? The check behind training's
held-out episode sets (maipp_bench/heldout.py ``HELDOUT_SETS``; docs/results.md, "Held-out
episodes share one roadmap").

Each network (a policy file or checkpoint whose protocol rows are in one of ``--results``,
found by its sha256) plays ``--method`` on ``--episodes`` held-out episodes of each set at
each budget. Per (set, budget): Spearman's rho between the networks' held-out means and
their protocol means (with a permutation p), and, over every pair of networks, the share
the held-out episodes order as the protocol does. Episodes run in chunks of ``--chunk``
(an episode's row depends on its own seeds only, so chunking changes no row) over
``--workers`` processes of one thread; each chunk's rows are kept in ``--cache`` as soon
as they are done, so a run cut short keeps its work, and ``--cached-only`` reports from
the cache alone (e.g. rows computed on another machine).

Usage:
    python benchmarks/heldout_vs_protocol.py --nets outputs/h1[2-8]/final.pt \\
        --results outputs/h1[2-8]_results --budgets 2 5 --sets 1 2 --episodes 160 \\
        --workers 16 --cache outputs/hvp --out outputs/hvp.json
"""

from __future__ import annotations

import argparse
import itertools
import json
import statistics as st
import sys
import tempfile
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from pathlib import Path

import numpy as np
from paired_subset import mean_se

from maipp_bench.heldout import HELDOUT_SETS
from maipp_bench.protocol.protocol import file_sha256


def _cache_file(cache: Path, sha: str, method: str, budget: float, first: int, n: int,
                heldout: int) -> Path:
    return cache / f"{sha[:12]}_{method}_B{budget:g}_E{first}-{first + n}_h{heldout}.json"


def _init_worker() -> None:
    import torch

    torch.set_num_threads(1)


def _play(path: str, method: str, budget: float, first: int, n: int, heldout: int,
          out: str) -> str:
    """One chunk of held-out episodes; its rows go to ``out`` (written whole or not at
    all, so a killed run leaves no half file)."""
    from maipp_bench.algos.checkpoint import load_core
    from maipp_bench.algos.registry import get_method
    from maipp_bench.envs.config import MAIPPConfig
    from maipp_bench.train import heldout_rows

    core, payload = load_core(path)
    rows = heldout_rows(core, MAIPPConfig.from_dict(payload["env"]), n, budget,
                        get_method(method), first=first, heldout=heldout)
    with tempfile.NamedTemporaryFile("w", dir=Path(out).parent, suffix=".tmp",
                                     delete=False) as tmp:  # unique: runs may share a cache
        json.dump([{"instance": r["instance"], "trial": r["trial"], "trace": r["trace"]}
                   for r in rows], tmp)
    Path(tmp.name).replace(out)
    return out


def protocol_means(results: list[Path], suite: str, method: str
                   ) -> dict[str, dict[float, float]]:
    """Mean protocol Tr(P_f) per checkpoint sha256 and budget, from the ``suite`` rows of
    eval --out folders; a budget with fewer rows than the suite's episodes is a warning."""
    from maipp_bench.protocol.protocol import load_protocol

    spec = load_protocol(1).suites[suite]
    budgets = {s.key: float(dict(s.values)["budget"]) for s in spec.settings
               if dict(s.values).keys() == {"budget"}}  # settings that vary the budget alone
    traces: dict[str, dict[float, list[float]]] = {}
    for folder in results:
        file = folder / suite / f"{method}.jsonl"
        if not file.exists():
            continue
        with open(file) as rows:
            for row in map(json.loads, rows):
                if row["setting"] in budgets:
                    traces.setdefault(row["checkpoint_sha256"], {}).setdefault(
                        budgets[row["setting"]], []).append(row["trace"])
    for sha, per in traces.items():
        for b, v in per.items():
            if len(v) < spec.n_episodes:
                print(f"warning: {sha[:12]} at B = {b:g}: {len(v)} protocol rows of "
                      f"{spec.n_episodes}", file=sys.stderr)
    return {sha: {b: st.mean(v) for b, v in per.items()} for sha, per in traces.items()}


def pair_agreement(held: list[float], proto: list[float]) -> tuple[int, int]:
    """Pairs of networks that the held-out means order as the protocol means do, and the
    pairs compared (a tie on either side orders nothing and is left out)."""
    same = total = 0
    for i, j in itertools.combinations(range(len(held)), 2):
        if held[i] != held[j] and proto[i] != proto[j]:
            total += 1
            same += (held[i] < held[j]) == (proto[i] < proto[j])
    return same, total


def main() -> None:
    """Compute the missing held-out rows, then rank (see the module's docstring)."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--nets", type=Path, nargs="+", required=True)
    p.add_argument("--results", type=Path, nargs="+", required=True,
                   help="eval --out folders holding the networks' protocol rows")
    p.add_argument("--suite", default="risk_aware", help="the protocol rows' suite")
    p.add_argument("--method", default="ours_ti")
    p.add_argument("--budgets", type=float, nargs="+", default=[2.0])
    p.add_argument("--sets", type=int, nargs="+", choices=HELDOUT_SETS,
                   default=list(HELDOUT_SETS))
    p.add_argument("--episodes", type=int, default=160)
    p.add_argument("--chunk", type=int, default=32)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--cache", type=Path, required=True)
    p.add_argument("--cached-only", action="store_true",
                   help="compute nothing: report the networks whose rows are all cached")
    p.add_argument("--permutations", type=int, default=5000)
    p.add_argument("--out", type=Path, help="the report as JSON")
    args = p.parse_args()
    if args.episodes < 2 or args.chunk < 1 or args.workers < 1 or args.permutations < 1:
        p.error("--episodes must be >= 2, --chunk >= 1, --workers >= 1, --permutations >= 1")
    missing = [str(n) for n in args.nets if not n.exists()]
    if missing:
        p.error(f"--nets: no such file: {', '.join(missing)}")

    shas = {net: file_sha256(net) for net in args.nets}
    means = protocol_means(args.results, args.suite, args.method)
    args.cache.mkdir(parents=True, exist_ok=True)
    firsts = range(0, args.episodes, args.chunk)
    for b in args.budgets:
        for net in args.nets:
            if b not in means.get(shas[net], {}):
                print(f"{net} (sha256 {shas[net][:12]}): no {args.suite} protocol rows of "
                      f"{args.method} at B = {b:g}; left out", file=sys.stderr)
    plan = {(net, b, h): [_cache_file(args.cache, shas[net], args.method, b, f,
                                      min(args.chunk, args.episodes - f), h) for f in firsts]
            for b in args.budgets for net in args.nets for h in args.sets  # a network's
            if b in means.get(shas[net], {})}  # sets together; only where the protocol scored
    if not args.cached_only:
        jobs = [(str(net), args.method, b, f, min(args.chunk, args.episodes - f), h, str(file))
                for (net, b, h), files in plan.items() for f, file in zip(firsts, files)
                if not file.exists()]
        with ProcessPoolExecutor(args.workers, mp_context=get_context("spawn"),
                                 initializer=_init_worker) as pool:
            for i, done in enumerate(pool.map(_play, *zip(*jobs)) if jobs else []):
                print(f"[{i + 1}/{len(jobs)}] {done}", file=sys.stderr, flush=True)

    report = []
    for b in args.budgets:
        for h in args.sets:
            rng = np.random.default_rng(0)  # each p-value its own permutations
            nets, held, proto, ses = [], [], [], []
            for net in args.nets:
                files = plan.get((net, b, h), [])
                if not files or not all(f.exists() for f in files):
                    continue
                trace = [r["trace"] for f in files for r in json.loads(f.read_text())]
                mean, se = mean_se(trace)
                nets.append(str(net))
                held.append(mean)
                ses.append(se)
                proto.append(means[shas[net]][b])
            if len(nets) < 3:
                print(f"B = {b:g}, set {h}: {len(nets)} networks with every row; "
                      "no ranking", flush=True)
                continue
            from draw_signals import spearman_perm  # scipy: only the report needs it

            rho, pval = spearman_perm(held, proto, args.permutations, rng)
            same, pairs = pair_agreement(held, proto)
            report.append({"budget": b, "heldout_set": h, "episodes": args.episodes,
                           "rho": rho, "p": pval, "pairs_same": same, "pairs": pairs,
                           "networks": [{"net": n, "heldout": m, "se": s, "protocol": q}
                                        for n, m, s, q in zip(nets, held, ses, proto)]})
            print(f"B = {b:g}, set {h}: {len(nets)} networks, rho {rho:+.2f} (p {pval:.3f}),"
                  f" pairs ordered as the protocol {same}/{pairs}", flush=True)
            for n, m, s, q in zip(nets, held, ses, proto):
                print(f"    held out {m:7.2f} ± {s:5.2f}   protocol {q:7.2f}   {n}")
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        tmp = args.out.with_name(args.out.name + ".tmp")
        tmp.write_text(json.dumps({"suite": args.suite, "method": args.method,
                                   "report": report}, indent=2) + "\n")
        tmp.replace(args.out)


if __name__ == "__main__":
    main()
