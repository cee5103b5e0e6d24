"""What MKL's CPU-independent kernels (those ``python -m maipp_bench.eval`` pins) cost a
protocol run against MKL's default ones, and which episodes change between the two
(docs/performance.md, "Kernels of protocol runs"; docs/protocol.md, "Another CPU").

Each of ``--methods`` plays one chunk, the first trial of ``--setting`` over the suite's
first ``--episodes`` instances, in two child processes at once, one torch thread each: one
under MKL's default kernels, one under ``MKL_CBWR=COMPATIBLE``, so on a 2-core box both
see the same load; ``--repeats`` times. Each child reports the kernel mode it ran under
(checked); ``--branches`` also plays it alone under other ``MKL_CBWR`` branches. Reported
per method: the chunk's wall seconds (environment and planning) under each, their ratio per
repeat, the episodes whose Tr(P_f) differs beyond 1e-9 between the
two, and under each the episodes that differ from the committed board's spot check
(``leaderboards/<suite>.json``, the first trial, computed on the board's machine).

Usage:
    python benchmarks/kernels_cost.py --suite risk_aware --setting budget=3.0 \\
        --episodes 30 --methods greedy ours_greedy ours_ti sga_rrt_0.3_0.4 [--repeats 2]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from ti_cpu_rounding import KERNELS, child_env, differing, emit


def child(suite_name: str, method: str, setting_key: str, episodes: int) -> dict:
    """Play the chunk in this process (one torch thread): traces, wall seconds, kernels."""
    import torch

    from maipp_bench import algos
    from maipp_bench.kernels import kernel_mode
    from maipp_bench.protocol.protocol import load_protocol
    from maipp_bench.protocol.runner import run_chunk

    torch.set_num_threads(1)
    suite = load_protocol(1).suite(suite_name)
    setting = suite.setting(setting_key)
    spec = algos.get_method(method)
    kwargs = {"checkpoint": str(spec.checkpoint(None))} if spec.learned else {}
    start = time.perf_counter()
    with torch.inference_mode():
        rows = run_chunk(spec, suite.env_config(setting), list(suite.instance_seeds[:episodes]),
                         suite.trial_seeds[0], **kwargs)
    return {"instance": [r["instance"] for r in rows], "trace": [r["trace"] for r in rows],
            "wall_s": time.perf_counter() - start, "kernels": kernel_mode()}


def run_child(args: argparse.Namespace, method: str, kernels: str) -> dict:
    cmd = [sys.executable, __file__, "--child", method, "--suite", args.suite,
           "--setting", args.setting, "--episodes", str(args.episodes)]
    proc = subprocess.run(cmd, env=child_env(kernels), capture_output=True, text=True,
                          check=False)
    if proc.returncode != 0:
        raise SystemExit(f"{method} / {kernels} kernels failed:\n{proc.stderr[-3000:]}")
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    expected = {"default": "default", "cpu-independent": "COMPATIBLE"}.get(kernels)
    if expected is not None and out["kernels"] != expected:
        raise SystemExit(f"{method}: the {kernels} child ran MKL's {out['kernels']} kernels")
    return out


def differ_from_board(run: dict, spot: dict) -> list[int]:
    """The instances of a child's chunk whose Tr(P_f) differs from a board's spot check
    (same trial: the suite's first)."""
    board = dict(zip(spot["instances"], spot["trace"]))
    mine = [(i, t) for i, t in zip(run["instance"], run["trace"]) if i in board]
    return [mine[j][0] for j in differing([t for _, t in mine], [board[i] for i, _ in mine])]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--suite", default="risk_aware")
    p.add_argument("--setting", default="budget=3.0", help="a setting key of the suite")
    p.add_argument("--episodes", type=int, default=30)
    p.add_argument("--methods", nargs="+", default=["greedy", "ours_greedy", "ours_ti"])
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--branches", nargs="*", default=[], metavar="BRANCH",
                   help="also play each method alone under these MKL_CBWR branches (AUTO, "
                        "AVX2, ...), once each: their wall seconds and episodes differing "
                        "from the board")
    p.add_argument("--out", type=Path)
    p.add_argument("--child", help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.child:
        print(json.dumps(child(args.suite, args.child, args.setting, args.episodes)))
        return
    from maipp_bench import algos
    from maipp_bench.hardware import cpu_model
    from maipp_bench.kernels import kernel_mode
    from maipp_bench.protocol.protocol import load_protocol

    if kernel_mode() in ("unavailable", "unknown"):
        p.error(f"MKL's kernels are {kernel_mode()} in this torch build: nothing to compare")
    suite = load_protocol(1).suite(args.suite)  # bad names fail here, before any child
    keys = [s.key for s in suite.settings]
    if args.setting not in keys:
        p.error(f"--setting {args.setting!r} is not a setting of {args.suite}: {keys}")
    for method in args.methods:
        try:
            algos.get_method(method)
        except ValueError as err:
            p.error(str(err))
    if not 1 <= args.episodes <= len(suite.instance_seeds):
        p.error(f"--episodes must be 1-{len(suite.instance_seeds)}")
    if args.repeats < 1:
        p.error("--repeats must be at least 1")

    path = Path(__file__).resolve().parents[1] / "leaderboards" / f"{args.suite}.json"
    board = json.loads(path.read_text()) if path.exists() else {"rows": []}
    spots = {r["method"]: r["spot_check"] for r in board["rows"]
             if r["setting"] == args.setting}
    report = {"suite": args.suite, "setting": args.setting, "episodes": args.episodes,
              "cpu_model": cpu_model(), "methods": {}}
    for method in args.methods:
        runs = []
        for _ in range(args.repeats):  # the two kernel sets side by side, one core each
            with ThreadPoolExecutor(2) as pool:
                futures = {k: pool.submit(run_child, args, method, k) for k in KERNELS}
                runs.append({k: f.result() for k, f in futures.items()})
        default = [r["default"]["wall_s"] for r in runs]
        independent = [r["cpu-independent"]["wall_s"] for r in runs]
        report["methods"][method] = {
            "wall_s": {"default": default, "cpu-independent": independent},
            "independent_over_default": [c / d for c, d in zip(independent, default)],
            "episodes_differing": differing(runs[0]["default"]["trace"],
                                            runs[0]["cpu-independent"]["trace"]),
            "differ_from_board": None if method not in spots else {
                k: differ_from_board(run, spots[method]) for k, run in runs[0].items()},
        }
        for branch in args.branches:  # alone: their seconds compare with a lone run only
            run = run_child(args, method, branch)
            report["methods"][method][f"branch {branch}"] = {
                "kernels": run["kernels"], "wall_s": run["wall_s"],
                "differ_from_board": None if method not in spots
                else differ_from_board(run, spots[method])}
        print(f"{method}: " + json.dumps(report["methods"][method]), file=sys.stderr)
    emit(report, args.out)


if __name__ == "__main__":
    main()
