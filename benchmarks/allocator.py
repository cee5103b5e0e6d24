"""What :func:`maipp_bench.allocator.keep_freed_memory` buys the CLIs, side by side.

Runs each workload as its user types it, alternately with glibc's default allocator
(``MALLOC_MMAP_MAX_=65536`` in the environment, the documented opt-out) and with the
CLIs' setting, ``--repeats`` times, and reports the medians of wall, user and system
seconds (``getrusage`` of the child) and of the per-pair wall ratios. The TI evaluation's
episodes must be bit-identical between the two (every stored field but the timings).

Workloads:

* ``ti``: ``python -m maipp_bench.eval --suite risk_aware --methods ours_ti --budgets 3
  --episodes 30 --workers 1`` (one trial of 30 instances batched in one env);
* ``train``: ``python -m maipp_bench.train algo=ours total_updates=2 eval_every=0``.

Usage:
    python benchmarks/allocator.py                      # both workloads, 2 repeats
    python benchmarks/allocator.py --workloads ti --repeats 3 --out allocator.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

DEFAULT_MMAP_MAX = "65536"  # glibc's default M_MMAP_MAX: setting it opts the CLIs out
TIMING_FIELDS = {"planning_s"}


def workload(name: str, out: Path) -> list[str]:
    py = [sys.executable, "-m"]
    if name == "ti":
        return py + ["maipp_bench.eval", "--suite", "risk_aware", "--methods", "ours_ti",
                     "--budgets", "3", "--episodes", "30", "--workers", "1", "--no-progress",
                     "--out", str(out)]
    return py + ["maipp_bench.train", "algo=ours", "total_updates=2", "eval_every=0",
                 "checkpoint_every=100", "progress=false", f"hydra.run.dir={out}"]


def timed(cmd: list[str], env: dict[str, str]) -> dict[str, float]:
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    subprocess.run(cmd, env=env, check=True, stdout=subprocess.DEVNULL,
                   stderr=subprocess.DEVNULL)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return {"wall_s": wall, "user_s": after.ru_utime - before.ru_utime,
            "sys_s": after.ru_stime - before.ru_stime}


def episodes(out: Path) -> list[dict]:
    rows = [json.loads(line) for f in sorted(out.rglob("*.jsonl")) for line in open(f)]
    return [{k: v for k, v in r.items() if k not in TIMING_FIELDS} for r in rows]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--workloads", nargs="+", choices=["ti", "train"], default=["ti", "train"])
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--out")
    args = p.parse_args()
    base = {k: v for k, v in os.environ.items() if k != "MALLOC_MMAP_MAX_"}
    variants = {"glibc default": {**base, "MALLOC_MMAP_MAX_": DEFAULT_MMAP_MAX},
                "keep_freed_memory": base}
    report: dict = {"machine": {"platform": platform.platform(), "cpu_count": os.cpu_count(),
                                "processor": platform.processor()}, "workloads": {}}
    for name in args.workloads:
        runs: dict[str, list[dict]] = {v: [] for v in variants}
        results: dict[str, list[dict]] = {}
        for _ in range(args.repeats):
            for variant, env in variants.items():  # interleaved: drifts hit both alike
                with tempfile.TemporaryDirectory() as tmp:
                    runs[variant].append(timed(workload(name, Path(tmp)), env))
                    if name == "ti":
                        results.setdefault(variant, episodes(Path(tmp)))
        med = {v: {k: statistics.median(r[k] for r in rs) for k in rs[0]}
               for v, rs in runs.items()}
        ratios = [a["wall_s"] / b["wall_s"]
                  for a, b in zip(runs["glibc default"], runs["keep_freed_memory"])]
        entry = {"median": med, "wall_ratio_median": statistics.median(ratios),
                 "runs": runs}
        if name == "ti":
            entry["identical_episodes"] = (results["glibc default"]
                                           == results["keep_freed_memory"])
        report["workloads"][name] = entry
        print(f"{name}: " + "; ".join(
            f"{v} wall {m['wall_s']:.1f} s (user {m['user_s']:.1f}, sys {m['sys_s']:.1f})"
            for v, m in med.items()) + f"; speed-up {entry['wall_ratio_median']:.2f}x"
            + (f"; identical episodes: {entry['identical_episodes']}" if name == "ti" else ""))
    if args.out:
        Path(args.out).write_text(json.dumps(report, indent=1) + "\n")


if __name__ == "__main__":
    main()
