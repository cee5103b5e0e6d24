"""TI's fantasy beliefs in float32 and float64 under two sets of float kernels: how often
another CPU's rounding changes an episode, and what float64 costs (docs/protocol.md,
"Another CPU").

One machine stands in for two CPUs: MKL's default kernels (this CPU's fastest) and its
CPU-independent ones (``MKL_CBWR=COMPATIBLE``), which round float32 and float64 products
differently, as another CPU does. A learned TI method (``--method``, its registered
params, with ``fantasy_dtype`` set to each of float32 and float64) plays the suite's
first ``--episodes`` instances of its first trial in ``--setting`` four times, in child
processes of one thread each, two at a time (the two dtypes side by side, so their
planning seconds compare): float32 and float64 with the default kernels, then both with
the CPU-independent ones. Reported: the episodes whose Tr(P_f) differs (beyond 1e-9
relative) between the kernels, per dtype; between the dtypes; against the committed
board's spot check (float32, computed on the board's CPU); and the planning seconds.

``--trace-instance I`` then replays the I-th of those episodes in float32 under both
kernel sets, recording every TI decision's rollouts (first slots, Tr(P)), and reports the
first decision whose chosen slot differs: its rollouts under each, and how far the
rollouts' Tr(P) had drifted apart before it.

Usage:
    python benchmarks/ti_cpu_rounding.py --suite risk_aware --method ours_ti \\
        --setting budget=5.0 --episodes 30 [--out rounding.json]
    python benchmarks/ti_cpu_rounding.py --suite agents10 --method ours_ti \\
        --setting budget=2.0 --episodes 10 --trace-instance 1
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
KERNELS = {"default": None, "cpu-independent": "COMPATIBLE"}  # MKL_CBWR (None: unset)


def child_env(kernels: str) -> dict[str, str]:
    """The environment of a one-thread child running MKL's ``kernels``: a KERNELS key, or
    an ``MKL_CBWR`` branch (``AUTO``, ``AVX2``, ...)."""
    env = {k: v for k, v in os.environ.items() if k != "MKL_CBWR"}
    env |= {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    if KERNELS.get(kernels, kernels) is not None:
        env["MKL_CBWR"] = KERNELS.get(kernels, kernels)
    return env


def emit(report: dict, out: Path | None) -> None:
    """Print the report as JSON, and write it to ``out`` when given."""
    text = json.dumps(report, indent=1)
    print(text)
    if out:
        out.write_text(text + "\n")


def child(suite_name: str, method: str, setting_key: str, episodes: int, dtype: str,
          trace: int | None = None) -> dict:
    """Play the episodes in this process: traces and planning seconds; with ``trace``, that
    one episode alone, with every TI decision's rollouts."""
    import torch

    from maipp_bench import algos
    from maipp_bench.algos.rollouts import Rollouts
    from maipp_bench.protocol.protocol import load_protocol
    from maipp_bench.protocol.runner import run_chunk

    torch.set_num_threads(1)
    suite = load_protocol(1).suite(suite_name)
    setting = suite.setting(setting_key)
    spec = algos.get_method(method)
    spec = dataclasses.replace(spec, params={**spec.params, "fantasy_dtype": dtype})
    instances = list(suite.instance_seeds[:episodes] if trace is None
                     else suite.instance_seeds[trace:trace + 1])
    decisions = []
    best_first = Rollouts.best_first

    def recorded(self: Rollouts) -> torch.Tensor:
        decisions.append({"first": self.first.tolist(), "trace": self.trace.tolist()})
        return best_first(self)

    Rollouts.best_first = recorded
    start = time.perf_counter()
    with torch.inference_mode():
        rows = run_chunk(spec, suite.env_config(setting), instances, suite.trial_seeds[0],
                         checkpoint=str(spec.checkpoint(None)))
    return {"trace": [r["trace"] for r in rows],
            "planning_s": sum(r["planning_s"] for r in rows),
            "wall_s": time.perf_counter() - start,
            "decisions": decisions if trace is not None else None}


def first_split(a: list[dict], b: list[dict]) -> dict | None:
    """The first TI decision whose chosen slots differ between two replays of an episode:
    its index, each replay's rollouts of the deciding agent whose slot differs, and the
    largest relative difference of the rollouts' Tr(P) at the decisions before it."""
    drift = 0.0
    for i, (x, y) in enumerate(zip(a, b)):
        chosen = [[f[t.index(min(t))] for f, t in zip(d["first"], d["trace"])] for d in (x, y)]
        if chosen[0] != chosen[1]:
            row = next(r for r, (p, q) in enumerate(zip(*chosen)) if p != q)
            return {"decision": i, "agent_row": row, "drift_before": drift,
                    "first": x["first"][row], "trace": [x["trace"][row], y["trace"][row]]}
        drift = max([drift, *(abs(p - q) / abs(q) for tx, ty in zip(x["trace"], y["trace"])
                              for p, q in zip(tx, ty))])
    return None


def run_child(args: argparse.Namespace, dtype: str, kernels: str,
              trace: int | None = None) -> dict:
    cmd = [sys.executable, __file__, "--child", dtype, "--suite", args.suite, "--method",
           args.method, "--setting", args.setting, "--episodes", str(args.episodes)]
    if trace is not None:
        cmd += ["--trace-instance", str(trace)]
    proc = subprocess.run(cmd, env=child_env(kernels), capture_output=True, text=True,
                          check=False)
    if proc.returncode != 0:
        raise SystemExit(f"{dtype} / {kernels} kernels failed:\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def differing(a: list[float], b: list[float]) -> list[int]:
    """Indices of the episodes whose Tr(P_f) differs beyond 1e-9 (relative or absolute)."""
    return [i for i, (x, y) in enumerate(zip(a, b))
            if not math.isclose(x, y, rel_tol=1e-9, abs_tol=1e-9)]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--suite", default="risk_aware")
    p.add_argument("--method", default="ours_ti")
    p.add_argument("--setting", default="budget=5.0", help="a setting key of the suite")
    p.add_argument("--episodes", type=int, default=30)
    p.add_argument("--trace-instance", type=int, metavar="I",
                   help="also replay the I-th episode (0-based) in float32 under both kernel "
                        "sets and report the first decision that differs")
    p.add_argument("--out", type=Path)
    p.add_argument("--child", choices=["float32", "float64"], help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.child:
        print(json.dumps(child(args.suite, args.method, args.setting, args.episodes,
                               args.child, args.trace_instance)))
        return
    from maipp_bench import algos
    from maipp_bench.hardware import cpu_model
    from maipp_bench.protocol.protocol import load_protocol

    suite = load_protocol(1).suite(args.suite)  # bad names fail here, before any child
    keys = [s.key for s in suite.settings]
    if args.setting not in keys:
        p.error(f"--setting {args.setting!r} is not a setting of {args.suite}: {keys}")
    if algos.get_method(args.method).params.get("mode") != "ti":
        p.error(f"--method {args.method}: not a TI method")
    if not 1 <= args.episodes <= len(suite.instance_seeds):
        p.error(f"--episodes must be 1-{len(suite.instance_seeds)}")
    if args.trace_instance is not None and not 0 <= args.trace_instance < args.episodes:
        p.error(f"--trace-instance must be 0-{args.episodes - 1}")
    path = ROOT / "leaderboards" / f"{args.suite}.json"
    board = json.loads(path.read_text()) if path.exists() else {"rows": []}

    runs: dict[str, dict[str, dict]] = {}
    for kernels in KERNELS:  # the two dtypes side by side, one core each
        with ThreadPoolExecutor(2) as pool:
            futures = {d: pool.submit(run_child, args, d, kernels)
                       for d in ("float32", "float64")}
            runs[kernels] = {d: f.result() for d, f in futures.items()}
    row = next((r for r in board["rows"] if r["method"] == args.method
                and r["setting"] == args.setting), None)
    committed = row["spot_check"]["trace"][:args.episodes] if row else None

    d32, d64 = runs["default"]["float32"], runs["default"]["float64"]
    c32, c64 = runs["cpu-independent"]["float32"], runs["cpu-independent"]["float64"]
    report = {
        "suite": args.suite, "method": args.method, "setting": args.setting,
        "episodes": args.episodes, "cpu_model": cpu_model(),
        "differ_between_kernels": {"float32": differing(d32["trace"], c32["trace"]),
                                   "float64": differing(d64["trace"], c64["trace"])},
        "differ_between_dtypes": differing(d32["trace"], d64["trace"]),
        "float32_differs_from_board": None if committed is None
        else differing(d32["trace"], committed),
        "mean": {f"{d}/{k}": sum(r["trace"]) / len(r["trace"])
                 for k, by in runs.items() for d, r in by.items()},
        "planning_s": {f"{d}/{k}": r["planning_s"] for k, by in runs.items()
                       for d, r in by.items()},
        "float64_over_float32_planning": {k: by["float64"]["planning_s"]
                                          / by["float32"]["planning_s"]
                                          for k, by in runs.items()},
    }
    if args.trace_instance is not None:
        with ThreadPoolExecutor(2) as pool:
            replays = [pool.submit(run_child, args, "float32", k, args.trace_instance)
                       for k in KERNELS]
            default, independent = (f.result()["decisions"] for f in replays)
        report["trace_instance"] = {"instance": args.trace_instance,
                                    "first_split": first_split(default, independent)}
    emit(report, args.out)


if __name__ == "__main__":
    main()
