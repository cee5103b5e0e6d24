"""Paired comparisons of checkpoints and methods: the paired differences of
docs/results.md (the suite tables and "How `ours.pt` was chosen").

* ``--heldout CKPT ...``: training's model-selection score (greedy episodes on held-out
  seeds, never the protocol's; ``maipp_bench.train.evaluate``) for each checkpoint, on
  the same episodes, at ``--budgets``; with ``--heldout-method ours_ti [...]``, those
  methods run with each checkpoint instead (model selection for the method the
  leaderboard ranks; or a method against a diagnostic variant), with paired differences
  to the first (checkpoint, method).
* ``--subset DIR --method M``: rows kept apart from ``--results`` (a quick subset,
  ``eval --episodes N --out D`` then ``D/subset-N``; or a full run of another checkpoint,
  ``eval --checkpoint M=PATH --out DIR``) paired episode by episode with the full rows of
  ``--against`` methods in ``--results``: mean
  Tr(P_f), traps, and the mean paired difference to the first ``--against`` method with
  its standard error.

Usage:
    python benchmarks/paired_subset.py --heldout maipp_bench/checkpoints/ours_v1.pt \\
        maipp_bench/checkpoints/ours.pt
    python benchmarks/paired_subset.py --heldout maipp_bench/checkpoints/ours_v1.pt \\
        maipp_bench/checkpoints/ours.pt --heldout-method ours_ti --budgets 2 3 4 5
    python benchmarks/paired_subset.py --heldout A.pt B.pt --heldout-method ours_ti \\
        --budgets 2 --episodes 96 --cache outputs/heldout   # one process per budget, then
    python benchmarks/paired_subset.py --heldout A.pt B.pt --heldout-method ours_ti \\
        --budgets 2 3 4 5 --episodes 96 --cache outputs/heldout   # prints from the cache
    python benchmarks/paired_subset.py --heldout maipp_bench/checkpoints/ours.pt \\
        --heldout-method ours_ti ours_ti_no_intent --budgets 2 5   # what intents are worth
    python benchmarks/paired_subset.py --heldout maipp_bench/checkpoints/ours.pt \\
        --heldout-method ours_ti --budgets 5 --episodes 96 --cache outputs/heldout \\
        --reference catnipp_ti=maipp_bench/checkpoints/catnipp.pt   # against a baseline
    python benchmarks/paired_subset.py --subset out/subset-60 --method ours_ti \\
        --against ours_ti catnipp_ti sga_rrt_0.3_0.4 oracle
    python benchmarks/paired_subset.py --subset outputs/h10_results --method ours_ti \\
        --against catnipp_ti --exclude 86171:155871   # without one episode
    python benchmarks/paired_subset.py --subset outputs/h14_results --method ours_ti \\
        --results outputs/h13_results --against ours_ti   # two draws, episode by episode
"""

from __future__ import annotations

import argparse
import itertools
import json
import statistics as st
from pathlib import Path

import torch

from maipp_bench.allocator import keep_freed_memory
from maipp_bench.heldout import add_heldout_argument


def mean_se(values: list[float]) -> tuple[float, float]:
    """Mean and its standard error (nan for a single value)."""
    se = st.stdev(values) / len(values) ** 0.5 if len(values) > 1 else float("nan")
    return st.mean(values), se


def z_text(diff: float, se: float) -> str:
    """A paired difference in standard errors, as the docs quote it: " (z -1.1)"; empty
    where the error is 0 (a run against itself) or undefined (one episode)."""
    return f" (z {diff / se:+.1f})" if se > 0 else ""


def heldout(paths: list[str], episodes: int, budgets: list[float], methods: list[str],
            cache: Path | None = None, first: int = 0,
            reference: tuple[str, str] | None = None, heldout_set: int = 2) -> None:
    """Each checkpoint played by each of ``methods`` (empty: training's model selection,
    greedy decoding) on the same held-out episodes per budget; paired differences to the
    first (checkpoint, method), or to ``reference`` ``(method, checkpoint)`` played first
    (a baseline of another network, e.g. ``catnipp_ti`` with ``catnipp.pt``). With
    ``cache``, each (checkpoint, method, budget, episodes)'s rows are kept there and
    reused: budgets can run in separate processes. ``first``: the held-out episodes from
    this one on (fresh episodes for a candidate chosen on the earlier ones).
    ``heldout_set``: training's held-out episode set (``HELDOUT_SETS``)."""
    from maipp_bench.algos.checkpoint import load_core
    from maipp_bench.algos.registry import get_method
    from maipp_bench.envs.config import MAIPPConfig
    from maipp_bench.protocol.protocol import file_sha256
    from maipp_bench.train import greedy_method, heldout_rows

    specs = [get_method(m) for m in methods] or [greedy_method("heldout")]
    pairs = list(itertools.product(paths, specs))
    if reference:
        pairs.insert(0, (reference[1], get_method(reference[0])))
    nets = {path: load_core(path) for path, _ in pairs}
    shas = {path: file_sha256(Path(path))[:12] for path in nets}
    for budget in budgets:
        print(f"budget {budget}: {episodes} held-out episodes (set {heldout_set}) "
              f"from #{first}")
        ref: list[float] | None = None
        for path, spec in pairs:
            core, payload = nets[path]
            span = f"{episodes}" if first == 0 else f"{first}+{episodes}"
            span += "" if heldout_set == 1 else f"_h{heldout_set}"  # set 1's files predate sets
            file = cache and cache / f"{shas[path]}_{spec.name}_B{budget:g}_{span}.json"
            if file and file.exists():
                rows = json.loads(file.read_text())
            else:
                rows = heldout_rows(core, MAIPPConfig.from_dict(payload["env"]), episodes,
                                    budget, spec, first, heldout=heldout_set)
                if file:
                    file.parent.mkdir(parents=True, exist_ok=True)
                    file.write_text(json.dumps(rows))
            trace = [r["trace"] for r in rows]
            ref = ref or trace
            diff, se = mean_se([t - f for t, f in zip(trace, ref)])
            wins = sum(t < f for t, f in zip(trace, ref))
            print(f"  {path} (update {payload.get('update')}), {spec.name}: "
                  f"Tr(P_f) {st.mean(trace):7.2f}  rmse {st.mean(r['rmse'] for r in rows):.3f}"
                  f"  traps {st.mean(r['traps'] for r in rows):.2f}"
                  f"  minus first {diff:+6.2f} ± {se:.2f}  wins {wins}", flush=True)


def _rows(path: Path, sha: str = "") -> dict[tuple, dict]:
    """Rows by episode; with ``sha``, only those of the checkpoint whose sha256 starts so
    (a results file keeps the rows of every checkpoint that was run)."""
    return {(r["setting"], r["instance"], r["trial"]): r for r in map(json.loads, open(path))
            if r.get("checkpoint_sha256", "").startswith(sha)}


def _episode(text: str) -> tuple[int, int]:
    """``--exclude``'s INSTANCE:TRIAL as a pair of integers."""
    instance, sep, trial = text.partition(":")
    if not (sep and instance.isdigit() and trial.isdigit()):
        raise argparse.ArgumentTypeError(f"{text!r}: expected INSTANCE:TRIAL integers")
    return int(instance), int(trial)


def pair(rows: dict[tuple, dict], ref: dict[tuple, dict], keys: list[tuple]) -> dict:
    """``rows`` against ``ref`` on the episodes ``keys``: the mean paired difference and
    its standard error, wins, mean and median Tr(P_f) and mean traps; the same difference
    split by whether ``rows``' episode was trapped (``untrapped`` / ``trapped``: count,
    mean, se), which says where it comes from; the episode of the worst Tr(P_f)
    (``worst``) and the one that costs the most against ``ref`` (``costliest``)."""
    d = {k: rows[k]["trace"] - ref[k]["trace"] for k in keys}
    diff, se = mean_se(list(d.values()))
    split = {}
    for tag, trapped in (("untrapped", False), ("trapped", True)):
        v = [x for k, x in d.items() if (rows[k]["traps"] > 0) == trapped]
        split[tag] = (len(v), *mean_se(v)) if v else (0, float("nan"), float("nan"))
    return {"n": len(keys), "diff": diff, "se": se, "wins": sum(v < 0 for v in d.values()),
            "trace": st.mean(rows[k]["trace"] for k in keys),
            "median": st.median(rows[k]["trace"] for k in keys),
            "traps": st.mean(rows[k]["traps"] for k in keys), **split,
            "worst": max(keys, key=lambda k: rows[k]["trace"]),
            "costliest": max(keys, key=d.get)}


def paired(subset: Path, suite: str, method: str, results: Path, against: list[str],
           sha: str = "", exclude: tuple[tuple[int, int], ...] = ()) -> None:
    """Print, per setting, each run's mean on ``subset``'s episodes and its paired
    difference to the first of ``against``; ``exclude`` (instance, trial) pairs are left
    out of every setting, their own rows printed apart."""
    runs = {f"{method} ({subset.name})": _rows(subset / suite / f"{method}.jsonl", sha)}
    runs |= {f"{m} (full)": _rows(results / suite / f"{m}.jsonl") for m in against}
    ref = runs[f"{against[0]} (full)"]
    mine = next(iter(runs.values()))
    # Settings every run has (baselines may have been rerun at some budgets only).
    settings = {name: {k[0] for k in r} for name, r in runs.items()}
    common = sorted(set.intersection(*settings.values()))
    if not common:
        raise SystemExit("no setting has rows of every run; settings per run: "
                         + "; ".join(f"{n}: {sorted(v)}" for n, v in settings.items())
                         + " (pair with one --against method at a time)")
    for setting in common:
        keys = [k for k in mine if k[0] == setting and k[1:] not in exclude]
        print(f"{setting}: {len(keys)} episodes")
        for name, rows in runs.items():
            for k in (k for k in mine if k[0] == setting and k[1:] in exclude):
                r = rows[k]
                print(f"  {name:32s} left out: instance {k[1]} trial {k[2]}: Tr(P_f) "
                      f"{r['trace']:.1f}  traps {r['traps']}  distance {r['distance']:.2f}")
            s = pair(rows, ref, keys)
            parts = "  ".join(f"{tag} {n} eps {m:+.2f} ± {e:.2f}"
                              for tag in ("untrapped", "trapped") for n, m, e in [s[tag]] if n)
            worst = s["worst"]  # what a large std comes from
            print(f"  {name:32s} Tr(P_f) {s['trace']:7.1f} (median {s['median']:.1f})"
                  f"  traps {s['traps']:.2f}  minus {against[0]} {s['diff']:+6.2f} ± "
                  f"{s['se']:.2f}" + z_text(s["diff"], s["se"]) + f"  wins {s['wins']}  {parts}"
                  f"  worst {rows[worst]['trace']:.1f} (instance {worst[1]} trial {worst[2]})")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--heldout", nargs="+", metavar="CKPT")
    p.add_argument("--episodes", type=int, default=48)
    p.add_argument("--first", type=int, default=0, metavar="I",
                   help="--heldout: score held-out episodes I .. I+episodes-1")
    p.add_argument("--budgets", type=float, nargs="+", default=[3.0],
                   help="--heldout: budgets to score (training selects at 3)")
    p.add_argument("--heldout-method", metavar="METHOD", nargs="+", default=[],
                   help="--heldout: run these registered methods (e.g. ours_ti "
                        "ours_ti_no_intent) with each checkpoint instead of training's "
                        "greedy score")
    add_heldout_argument(p)
    p.add_argument("--reference", metavar="METHOD=CKPT",
                   help="--heldout: play this (method, checkpoint) first and pair every row "
                        "with it, e.g. catnipp_ti=maipp_bench/checkpoints/catnipp.pt")
    p.add_argument("--cache", type=Path, metavar="DIR",
                   help="--heldout: keep each checkpoint's rows per budget here and reuse them")
    p.add_argument("--subset", type=Path,
                   help="rows kept apart: an eval --out folder (or its subset-N folder)")
    p.add_argument("--suite", default="risk_aware")
    p.add_argument("--method")
    p.add_argument("--method-sha", default="", metavar="PREFIX",
                   help="--subset: only --method's rows of the checkpoint whose sha256 "
                        "starts so (e.g. --subset results and a candidate's rows)")
    p.add_argument("--results", type=Path, default=Path("results"))
    p.add_argument("--against", nargs="+", default=[])
    p.add_argument("--exclude", nargs="+", default=[], type=_episode, metavar="INSTANCE:TRIAL",
                   help="--subset: leave these episodes out of every setting (their rows "
                        "are printed apart)")
    args = p.parse_args()
    keep_freed_memory()  # as the CLIs do (maipp_bench/allocator.py)
    torch.set_num_threads(1)
    reference = None
    if args.reference:
        method, sep, path = args.reference.partition("=")
        if not (sep and method and path):
            p.error(f"--reference {args.reference!r}: expected METHOD=CKPT")
        reference = (method, path)
    if args.heldout:
        heldout(args.heldout, args.episodes, args.budgets, args.heldout_method, args.cache,
                args.first, reference, args.heldout_set)
    if args.subset:
        if not (args.method and args.against):
            p.error("--subset needs --method and --against")
        paired(args.subset, args.suite, args.method, args.results, args.against,
               args.method_sha, tuple(args.exclude))


if __name__ == "__main__":
    main()
