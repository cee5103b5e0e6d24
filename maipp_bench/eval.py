"""``python -m maipp_bench.eval --suite risk_aware``: score methods under the protocol.

Every (method, setting) is run on the suite's instances x trials, one chunk (a trial over
all instances, batched in one env) at a time; each finished chunk is stored at once, so an
interrupted run loses at most one chunk and a rerun continues where it stopped (a finished
suite recomputes nothing). The leaderboard (JSON, markdown, PNG) is then rebuilt from the
stored episodes.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import shlex
import sys
from collections import Counter
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

import torch
from tqdm import tqdm

from maipp_bench.kernels import kernel_mode, pin_cpu_kernels, require_pinned_kernels

# MKL's CPU-independent kernels, asked for before tensordict's import (below) makes MKL's
# first call and so fixes its code path: rows then reproduce on other CPUs.
pin_cpu_kernels()

from maipp_bench import algos  # noqa: E402
from maipp_bench.allocator import keep_freed_memory  # noqa: E402
from maipp_bench.envs.config import check_device  # noqa: E402
from maipp_bench.protocol import leaderboard  # noqa: E402
from maipp_bench.protocol.protocol import file_sha256, load_protocol  # noqa: E402
from maipp_bench.protocol.runner import run_chunk  # noqa: E402
from maipp_bench.protocol.store import ResultStore  # noqa: E402

# Test hook: exit hard (as if killed) after this many stored chunks.
_STOP_AFTER_ENV = "MAIPP_EVAL_STOP_AFTER_CHUNKS"


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="python -m maipp_bench.eval", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--suite", required=True, help="suite name of the protocol (e.g. risk_aware)")
    p.add_argument("--methods", nargs="+", help="methods to run (default: the suite's "
                   "methods that are available here)")
    p.add_argument("--budgets", nargs="+", type=float, help="only settings with these budgets")
    p.add_argument("--episodes", type=int, help="quick subset: this many episodes per "
                   "setting (stored and reported apart from full runs)")
    p.add_argument("--checkpoint", action="append", default=[], metavar="METHOD=PATH",
                   help="checkpoint of a learned method (repeatable); passed to its policy")
    p.add_argument("--device", default="cpu")
    p.add_argument("--out", default="results", help="directory of per-episode results")
    p.add_argument("--leaderboards", default="leaderboards",
                   help="directory of leaderboards (full runs only; subsets go under --out)")
    p.add_argument("--protocol-version", type=int, default=1)
    p.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1),
                   help="processes running chunks in parallel (default: min(2, cores))")
    p.add_argument("--threads", type=int, default=1,
                   help="torch threads per process (default 1: the batched tensors are small, "
                        "and contended OpenMP threads slow them down many times)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--fresh-board", action="store_true",
                   help="full runs: write a board of this run's rows only (default: keep the "
                        "other rows of the board found there that still belong to this code, "
                        "each with the provenance of its run)")
    args = p.parse_args(argv)
    try:
        check_device(args.device, "--device")
    except ValueError as err:
        p.error(str(err))
    return args


def _run_chunk(method: str, cfg, insts: list[int], trial: int, device: str,
               threads: int, policy_kwargs: dict, kernels: str) -> list[dict]:
    if kernel_mode() != kernels:  # a worker runs the kernels its parent runs
        raise RuntimeError(f"eval worker runs MKL's {kernel_mode()} kernels, not {kernels}")
    torch.set_num_threads(threads)
    with torch.inference_mode():
        return run_chunk(algos.get_method(method), cfg, insts, trial, device=device,
                         **policy_kwargs)


def _checkpoints(pairs: list[str], methods: list[str]) -> dict[str, dict]:
    """``["ours_ti=path.pt"]`` -> ``{"ours_ti": {"checkpoint": "path.pt"}}`` (checked)."""
    out: dict[str, dict] = {}
    for pair in pairs:
        name, sep, path = pair.partition("=")
        if not sep or not path:
            raise SystemExit(f"error: --checkpoint expects METHOD=PATH, got {pair!r}")
        if name not in methods:
            raise SystemExit(f"error: --checkpoint for {name!r}, which is not among the "
                             f"methods being run: {methods}")
        if not algos.get_method(name).learned:
            raise SystemExit(f"error: --checkpoint for {name!r}, which is not a learned method")
        if not Path(path).exists():
            raise SystemExit(f"error: checkpoint {path!r} for {name!r} does not exist")
        out[name] = {"checkpoint": path}
    return out


def main(argv: list[str] | None = None) -> dict:
    args = parse_args(argv)
    try:
        kernels = require_pinned_kernels()
    except RuntimeError as err:
        raise SystemExit(f"error: {err}") from None
    keep_freed_memory()
    commit = leaderboard.git_commit()  # the code that computes this run's rows
    protocol = load_protocol(args.protocol_version)
    try:
        suite = protocol.suite(args.suite)
    except ValueError as err:
        raise SystemExit(f"error: {err}") from None
    available = algos.method_names()
    if args.methods:
        methods = list(args.methods)
        for name in methods:
            try:
                algos.get_method(name)
            except ValueError as err:
                raise SystemExit(f"error: {err}") from None
    else:
        methods = [m for m in suite.methods if m in available]
        missing = [m for m in suite.methods if m not in available]
        if missing:
            print(f"note: suite methods not available in this build, skipped: {missing}",
                  file=sys.stderr)
    policy_kwargs = _checkpoints(args.checkpoint, methods)
    # Learned methods: the checkpoint each runs, recorded with every row (rows of another
    # checkpoint are neither reused nor reported). Suite defaults without a shipped
    # checkpoint are skipped with a note; asked-for ones are an error.
    checkpoints: dict[str, dict[str, str]] = {}
    for name in list(methods):
        try:
            path = algos.get_method(name).checkpoint(policy_kwargs.get(name, {}).get("checkpoint"))
        except FileNotFoundError as err:
            if args.methods:
                raise SystemExit(f"error: {name}: {err}") from None
            print(f"note: {name} skipped: {err}", file=sys.stderr)
            methods.remove(name)
            continue
        if path is not None:
            shown = path.resolve()
            try:  # shipped files by their place in the repo, not this machine's path
                shown = shown.relative_to(Path.cwd().resolve())
            except ValueError:
                pass
            checkpoints[name] = {"path": str(shown), "sha256": file_sha256(path)}
            policy_kwargs.setdefault(name, {})["checkpoint"] = str(path)
    # Every row records the method's fingerprint (and a learned method's checkpoint) and
    # MKL's kernels: rows of another algorithm version, params, checkpoint or kernels are
    # neither reused nor reported.
    fingerprints = {m: algos.get_method(m).fingerprint() for m in methods}
    match = {m: {"method_sha256": fingerprints[m], "mkl_kernels": kernels,
                 **({"checkpoint_sha256": checkpoints[m]["sha256"]} if m in checkpoints else {})}
             for m in methods}
    settings = list(suite.settings)
    if args.budgets:
        budgets = set(args.budgets)
        settings = [s for s in settings if suite.env_config(s).budget in budgets]
        if not settings:
            raise SystemExit(f"error: no setting of suite {suite.name!r} has budget in "
                             f"{sorted(budgets)}")
    instances, trials = list(suite.instance_seeds), list(suite.trial_seeds)
    subset = None
    out_root = Path(args.out)
    if args.episodes is not None:
        if not 1 <= args.episodes <= suite.n_episodes:
            raise SystemExit(f"error: --episodes must be in [1, {suite.n_episodes}]")
        subset = args.episodes
        # Trial-major order: the first trials over (up to) all instances.
        per_trial = min(len(instances), subset)
        instances = instances[:per_trial]
        trials = trials[: -(-subset // per_trial)]
        out_root = out_root / f"subset-{subset}"
    store = ResultStore(out_root, suite.name)

    chunks = []
    for method in methods:
        done = store.done(method, **match.get(method, {}))
        for setting in settings:
            for t_idx, trial in enumerate(trials):
                insts = instances
                if subset is not None:
                    left = subset - t_idx * len(instances)
                    insts = instances[: max(0, min(len(instances), left))]
                if insts and not all((setting.key, i, trial) in done for i in insts):
                    chunks.append((method, setting, trial, insts))
    total = sum(len(c[3]) for c in chunks)
    stop_after = int(os.environ.get(_STOP_AFTER_ENV, "0") or 0)
    bar = tqdm(total=total, unit="ep", desc=f"{suite.name}", disable=args.no_progress,
               dynamic_ncols=True)
    def store_chunk(method: str, setting_key: str, rows: list[dict]) -> None:
        for r in rows:
            r.update(method=method, setting=setting_key, protocol_version=protocol.version,
                     protocol_sha256=protocol.sha256, **match.get(method, {}))
        store.append(method, rows)
        bar.update(len(rows))

    jobs = [(m, suite.env_config(s), insts, trial, args.device, args.threads,
             policy_kwargs.get(m, {}), kernels) for m, s, trial, insts in chunks]
    if args.workers <= 1 or len(jobs) <= 1:
        torch.set_num_threads(args.threads)
        for n_done, ((method, setting, trial, _), job) in enumerate(zip(chunks, jobs), 1):
            bar.set_postfix_str(f"{method} {setting.key} trial {trial}")
            store_chunk(method, setting.key, _run_chunk(*job))
            if stop_after and n_done >= stop_after:
                bar.close()
                os._exit(3)  # simulate a hard kill (tests of resumption)
    else:
        # CUDA cannot be used in forked children once a parent touched it: spawn them.
        spawn = torch.device(args.device).type == "cuda"
        # A spawned worker starts with glibc's defaults: each sets the allocator once.
        with ProcessPoolExecutor(max_workers=args.workers, initializer=keep_freed_memory,
                                 mp_context=multiprocessing.get_context("spawn") if spawn
                                 else None) as pool:
            futures = {pool.submit(_run_chunk, *job): chunk for chunk, job in zip(chunks, jobs)}
            for n_done, fut in enumerate(as_completed(futures), 1):
                method, setting, trial, _ = futures[fut]
                bar.set_postfix_str(f"{method} {setting.key} trial {trial}")
                store_chunk(method, setting.key, fut.result())
                if stop_after and n_done >= stop_after:
                    bar.close()
                    for proc in list(pool._processes.values()):  # die with the workers
                        proc.kill()
                    os._exit(3)
    bar.close()

    rows_by_method = {m: [r for r in store.rows(m) if r["protocol_sha256"] == protocol.sha256
                          and all(r.get(k) == v for k, v in match.get(m, {}).items())]
                      for m in methods}
    command = "python -m maipp_bench.eval " + " ".join(shlex.quote(a) for a in (argv or
                                                                             sys.argv[1:]))
    board = leaderboard.build(protocol, suite, settings, methods, rows_by_method, command,
                              subset, commit)
    board["checkpoints"] = checkpoints
    board["method_sha256"] = fingerprints
    committed_path = Path(args.leaderboards) / f"{suite.name}.json"
    try:
        committed = json.loads(committed_path.read_text()) if committed_path.exists() else None
    except (OSError, ValueError) as err:  # the new board is written all the same
        print(f"note: {committed_path} unreadable ({err}); not compared", file=sys.stderr)
        committed = None
    target = Path(args.leaderboards) if subset is None else out_root / "leaderboards"
    if committed is not None:
        try:
            _report_reproduction(board, committed, committed_path)
        except (KeyError, TypeError) as err:  # a board of an older format
            print(f"note: {committed_path} not compared (missing {err})", file=sys.stderr)
        if subset is None and committed.get("subset") is None and not args.fresh_board:
            _keep_other_rows(board, committed)
    paths = leaderboard.write(board, target)
    print(f"wrote {', '.join(str(p) for p in paths)}")
    return board


def _identity(method: str, checkpoint: str | None) -> tuple | None:
    """This code's (fingerprint, checkpoint sha256) of a method whose checkpoint a board
    recorded at ``checkpoint`` (a repo path for shipped files); None if unknown."""
    try:
        fingerprint = algos.get_method(method).fingerprint()
    except ValueError:
        return None
    if checkpoint is None:
        return fingerprint, None
    found = [p for p in (Path(checkpoint), Path(algos.__file__).parents[2] / checkpoint)
             if p.is_file()]
    return fingerprint, file_sha256(found[0]) if found else None


def _keep_other_rows(board: dict, committed: dict) -> None:
    """Keep the found board's rows this run did not recompute (leaderboard.keep_rows)."""
    kept, dropped = leaderboard.keep_rows(board, committed, _identity)
    if kept:
        methods = list(dict.fromkeys(m for m, _ in kept))
        print(f"kept {len(kept)} rows of the board found there ({', '.join(methods)}); "
              "--fresh-board drops them")
    if dropped:
        print(f"note: dropped {len(dropped)} rows of the board found there that no longer "
              f"belong to this code (method version, checkpoint or protocol changed): "
              f"{dropped}", file=sys.stderr)


def _report_reproduction(board: dict, committed: dict, path: Path) -> None:
    """Say whether this run's rows recompute the board that was there before it (the
    committed one, for a subset or a first full run on a fresh clone)."""
    checks = leaderboard.reproduces(board, committed)
    counts = Counter(verdict for *_, verdict in checks)
    what = ("every episode" if board["subset"] is None and committed["subset"] is None
            else "the first trial's episodes it ran")
    print(f"against {path} (as it was before this run; {what}): "
          + ", ".join(f"{n} rows {v}" for v, n in counts.items()))
    rows = {(r["method"], r["setting"]): r for r in committed["rows"]}
    for method, setting, verdict in checks:
        if verdict == "differs":
            other = leaderboard.machine_apart(committed, rows[method, setting])
            here = leaderboard.describe_machine(leaderboard.machine())
            where = ("" if other is None else f" (computed on {other}; this run: {here}; "
                     "docs/protocol.md, 'Another CPU')")
            print(f"  differs: {method} {setting}{where}", file=sys.stderr)


if __name__ == "__main__":
    main()
