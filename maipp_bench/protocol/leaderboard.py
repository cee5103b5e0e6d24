"""Aggregate stored episodes into ``<suite>.json`` / ``.md`` / ``.png`` (written atomically).

The JSON is the data (with provenance: protocol version and hash, package version, git
commit, date, machine, command); the markdown table and the plot are generated from it.
Timing fields (``planning_s_per_episode``) are the only ones that vary between runs.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import math
import os
import platform
import subprocess
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

import maipp_bench
from maipp_bench.hardware import UNRECORDED_CPU, cpu_model, same_cpu
from maipp_bench.kernels import aten_capability, kernel_mode
from maipp_bench.protocol.protocol import Protocol, Setting, Suite, paper_results

STATS = ("trace", "rmse", "evidence_inside", "evidence_outside", "evidence_total", "traps",
         "distance", "steps")
TIMING_FIELDS = ("planning_s_per_episode",)


def git_commit() -> str:
    """The code's commit: ``$MAIPP_BENCH_COMMIT`` where set (a lent GPU machine's copy of
    the tree can carry a stale ``.git``: one run there read the session's first HEAD),
    with a warning where the checkout's HEAD says otherwise; else that HEAD; else
    "unknown"."""
    try:
        root = Path(maipp_bench.__file__).resolve().parent.parent
        out = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True,
                             text=True, timeout=10)
        head = out.stdout.strip() if out.returncode == 0 else ""
    except (OSError, subprocess.SubprocessError):
        head = ""
    named = os.environ.get("MAIPP_BENCH_COMMIT", "")
    if named and head and named != head:
        warnings.warn(f"MAIPP_BENCH_COMMIT={named} is recorded as the code's commit, but "
                      f"this checkout's HEAD is {head}", stacklevel=2)
    return named or head or "unknown"


def machine() -> dict[str, Any]:
    import torch

    return {"platform": platform.platform(), "processor": platform.processor() or "unknown",
            "cpu_model": cpu_model() or "unknown", "cpu_count": os.cpu_count(),
            "mkl_kernels": kernel_mode(), "aten_capability": aten_capability(),
            "python": platform.python_version(),
            "torch": torch.__version__, "torch_threads": torch.get_num_threads()}


def _atomic_write(path: Path, data: bytes) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(data)
    os.replace(tmp, path)


def _num(v: Any) -> Any:
    return "inf" if isinstance(v, float) and math.isinf(v) else v


def aggregate(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Mean / std (ddof 1) / 95% CI half-width (normal approximation) of each statistic."""
    out: dict[str, Any] = {"n": len(rows)}
    for name in STATS:
        x = np.array([r[name] for r in rows], dtype=np.float64)
        std = float(x.std(ddof=1)) if len(x) > 1 else 0.0
        out[f"{name}_mean"] = float(x.mean())
        out[f"{name}_std"] = std
        if name == "trace":
            out["trace_ci95"] = 1.96 * std / math.sqrt(len(x))
    out["planning_s_per_episode"] = float(np.mean([r["planning_s"] for r in rows]))
    return out


def row_checks(suite: Suite, eps: list[dict[str, Any]]) -> dict[str, Any]:
    """What lets anyone check a row without our result files.

    ``spot_check``: the final Tr(P) of the first trial's episodes, in the suite's instance
    order (recomputing that one batched chunk must give these numbers);
    ``episodes_sha256``: sha256 of every episode's (instance, trial, Tr(P)), sorted, so a
    full rerun can be compared bit for bit.
    """
    order = {seed: i for i, seed in enumerate(suite.instance_seeds)}
    first = [r for r in eps if r["trial"] == suite.trial_seeds[0]]
    first.sort(key=lambda r: order[r["instance"]])
    listing = sorted((r["instance"], r["trial"], r["trace"]) for r in eps)
    return {
        "spot_check": {"trial": suite.trial_seeds[0],
                       "instances": [r["instance"] for r in first],
                       "trace": [r["trace"] for r in first]},
        "episodes_sha256": hashlib.sha256(json.dumps(listing).encode()).hexdigest(),
    }


# What boards written before 2026-11-28 did not record: their 2-core AMD EPYC boxes ran
# MKL's default kernels and torch's AVX512 ones.
UNRECORDED = {"mkl_kernels": "default", "aten_capability": "AVX512"}


def row_machine(board: dict[str, Any], row: dict[str, Any]) -> dict[str, Any]:
    """The machine that computed a committed row: its own provenance's (a row kept from an
    earlier run), else the board's, with :data:`UNRECORDED` filling what it lacks."""
    return {**UNRECORDED, **(row.get("provenance") or board)["machine"]}


def describe_machine(m: dict[str, Any]) -> str:
    """A machine record in words: CPU model, torch's kernel width and MKL's kernels."""
    return (f"{m.get('cpu_model') or UNRECORDED_CPU} ({m['aten_capability']}) with MKL's "
            f"{m['mkl_kernels']} kernels")


def machine_apart(board: dict[str, Any], row: dict[str, Any]) -> str | None:
    """The machine that computed a committed row, in words, when its CPU, torch kernel
    width or MKL kernels are not this process's; None when all three match. eval names it
    beside any row that differs (docs/protocol.md, "Another CPU"): every board computed
    before eval pinned MKL's kernels is apart from a pinned run, even on its own CPU, so
    the note says where the row came from, not why it differs."""
    m = row_machine(board, row)
    if same_cpu(m.get("cpu_model")) and (m["aten_capability"], m["mkl_kernels"]) == (
            aten_capability(), kernel_mode()):
        return None
    return describe_machine(m)


def reproduces(board: dict[str, Any], committed: dict[str, Any], rel: float = 1e-9
               ) -> list[tuple[str, str, str]]:
    """Check the rows of a fresh run (``board``, full or subset) against a committed board
    of the same suite: ``(method, setting, verdict)`` per row of ``board``.

    Rows are comparable when both boards used the same protocol file and both rows the
    same method fingerprint and checkpoint. Then the
    first trial's Tr(P_f) of every instance the run has must equal the committed
    ``spot_check`` (to ``rel``: another CPU may round the last bits differently), and a
    full row's ``episodes_sha256`` the committed one. Verdicts: ``"identical"`` (every
    checked value bit for bit), ``"within <rel>"``, ``"differs"``, ``"not comparable"``,
    and for a full row whose hash differs, ``"first trial ..., other episodes not
    bit-identical"``.
    """
    def ident(b: dict[str, Any], method: str) -> tuple:
        return (b.get("method_sha256", {}).get(method),
                b.get("checkpoints", {}).get(method, {}).get("sha256"))

    ref = {(r["method"], r["setting"]): r for r in committed["rows"]}
    same_protocol = board["protocol"]["sha256"] == committed["protocol"]["sha256"]
    out = []
    for row in board["rows"]:
        key = (row["method"], row["setting"])
        old = ref.get(key)
        if (old is None or not same_protocol
                or ident(board, row["method"]) != ident(committed, row["method"])):
            out.append((*key, "not comparable"))
            continue
        mine = dict(zip(row["spot_check"]["instances"], row["spot_check"]["trace"]))
        theirs = dict(zip(old["spot_check"]["instances"], old["spot_check"]["trace"]))
        pairs = [(v, theirs[i]) for i, v in mine.items() if i in theirs]
        full = board["subset"] is None and committed["subset"] is None
        if not pairs:
            verdict = "not comparable"
        elif not all(math.isclose(a, b, rel_tol=rel, abs_tol=rel) for a, b in pairs):
            verdict = "differs"
        else:
            verdict = "identical" if all(a == b for a, b in pairs) else f"within {rel:g}"
            if full and row["episodes_sha256"] != old["episodes_sha256"]:
                # Only the first trial is stored per episode: the rest is known by hash.
                verdict = f"first trial {verdict}, other episodes not bit-identical"
        out.append((*key, verdict))
    return out


PROVENANCE = ("git_commit", "date", "machine", "command")


def keep_rows(board: dict[str, Any], committed: dict[str, Any],
              identity: Callable[[str, str | None], tuple | None]) -> tuple[list, list]:
    """Add to the full-run ``board`` the rows of the full ``committed`` board it did not
    recompute, so that scoring some methods does not erase the others' rows.

    A committed row is kept only while it still belongs to this code: same protocol file,
    and ``identity(method, checkpoint_path)`` (this code's method fingerprint and the
    sha256 of the file at the recorded checkpoint path; None for an unknown method) equals
    what the committed board recorded. A kept row carries the ``provenance`` of the run
    that computed it (commit, date, machine, command). Rows keep the committed order, a
    recomputed row in its old place, new ones after. Returns ``(kept, dropped)``
    (method, setting) pairs.
    """
    if board["subset"] is not None or committed["subset"] is not None:
        raise ValueError("only full-run boards are merged")
    mine = {(r["method"], r["setting"]): r for r in board["rows"]}
    same_protocol = board["protocol"]["sha256"] == committed["protocol"]["sha256"]
    rows, kept, dropped = [], [], []
    checkpoints, fingerprints = {}, {}
    for old in committed["rows"]:
        key = (old["method"], old["setting"])
        if key in mine:
            rows.append(mine.pop(key))
            continue
        method = old["method"]
        ckpt = committed.get("checkpoints", {}).get(method)
        recorded = (committed.get("method_sha256", {}).get(method),
                    ckpt and ckpt["sha256"])
        if not same_protocol or identity(method, ckpt and ckpt["path"]) != recorded:
            dropped.append(key)
            continue
        rows.append({**old, "provenance": old.get("provenance")
                     or {k: committed[k] for k in PROVENANCE}})
        kept.append(key)
        fingerprints[method] = recorded[0]
        if ckpt:
            checkpoints[method] = ckpt
    rows += mine.values()
    order = list(dict.fromkeys(r["method"] for r in rows))
    board["rows"] = rows
    for field, extra in (("checkpoints", checkpoints), ("method_sha256", fingerprints)):
        both = {**extra, **board.get(field, {})}
        board[field] = {m: both[m] for m in order if m in both}
    return kept, dropped


def _paper_lookup(suite: Suite) -> dict[tuple, tuple[float, float]]:
    if not suite.paper_table:
        return {}
    table = paper_results()[suite.paper_table]
    found = {}
    for r in table["rows"]:
        axes = tuple((a, math.inf if r[a] == "inf" else float(r[a])) for a in table["axes"])
        found[(r["method"], axes)] = (r["mean"], r["std"])
    return found


def build(
    protocol: Protocol,
    suite: Suite,
    settings: list[Setting],
    methods: list[str],
    rows_by_method: dict[str, list[dict[str, Any]]],
    command: str,
    subset: int | None,
    commit: str | None = None,
) -> dict[str, Any]:
    """The leaderboard document: one row per (method, setting) with stored episodes.

    ``commit`` is the code that computed the rows (taken when the run starts)."""
    paper = _paper_lookup(suite)
    board_rows = []
    for method in methods:
        by_setting: dict[str, list] = {}
        for r in rows_by_method.get(method, []):
            by_setting.setdefault(r["setting"], []).append(r)
        for setting in settings:
            eps = sorted(by_setting.get(setting.key, []), key=lambda r: (r["trial"], r["instance"]))
            if not eps:
                continue
            row = {"method": method, "setting": setting.key,
                   "axes": {k: _num(v) for k, v in setting.values}}
            row.update(aggregate(eps))
            key = (method, tuple((k, float(v)) for k, v in setting.values if k in
                                 ("budget", "comm_range")))
            ref = paper.get(key)
            row["paper_trace_mean"], row["paper_trace_std"] = ref if ref else (None, None)
            row.update(row_checks(suite, eps))
            board_rows.append(row)
    return {
        "suite": suite.name,
        "description": suite.description,
        "protocol": {"version": protocol.version, "sha256": protocol.sha256},
        "package_version": maipp_bench.__version__,
        "git_commit": commit or git_commit(),
        "date": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "machine": machine(),
        "command": command,
        "subset": None if subset is None else {"episodes_per_setting": subset},
        "episodes_per_setting": suite.n_episodes if subset is None else subset,
        "rows": board_rows,
    }


def write(board: dict[str, Any], directory: str | Path) -> list[Path]:
    """Write ``<suite>.json``, ``<suite>.md`` and ``<suite>.png`` into ``directory``."""
    directory = Path(directory)
    name = board["suite"]
    paths = [directory / f"{name}.json", directory / f"{name}.md", directory / f"{name}.png"]
    _atomic_write(paths[0], (json.dumps(board, indent=2, sort_keys=False) + "\n").encode())
    _atomic_write(paths[1], markdown(board).encode())
    _atomic_write(paths[2], plot(board))
    return paths


def _fmt(x: float | None, digits: int = 2) -> str:
    return "-" if x is None else f"{x:.{digits}f}"


def markdown(board: dict[str, Any]) -> str:
    lines = [
        f"# Leaderboard: `{board['suite']}`",
        "",
        board["description"] + ".",
        "",
        f"Protocol v{board['protocol']['version']} (sha256 `{board['protocol']['sha256'][:12]}`),"
        f" {board['episodes_per_setting']} episodes per row, maipp_bench "
        f"{board['package_version']} at `{board['git_commit'][:10]}`, {board['date']}.",
        f"Produced by `{board['command']}`; data in `{board['suite']}.json`.",
        "",
    ]
    earlier: dict[tuple, list[str]] = {}  # rows kept from earlier runs, by their run
    for r in board["rows"]:
        if "provenance" in r:
            run = tuple(r["provenance"][k] for k in ("command", "git_commit", "date"))
            methods = earlier.setdefault(run, [])
            if r["method"] not in methods:
                methods.append(r["method"])
    for (command, commit, date), methods in earlier.items():
        lines += [f"Rows of {', '.join(f'`{m}`' for m in methods)} kept from an earlier run: "
                  f"`{command}` at `{commit[:10]}`, {date} (`provenance` in the JSON)."]
    if earlier:
        lines += [""]
    if board["subset"]:
        lines += ["**Quick subset, not the full protocol: do not compare with full rows.**", ""]
    for method, ckpt in board.get("checkpoints", {}).items():
        lines += [f"Learned method `{method}`: checkpoint `{ckpt['path']}` (sha256 "
                  f"`{ckpt['sha256'][:12]}`)."]
    if board.get("checkpoints"):
        lines += [""]
    lines += [
        "Tr(P_f): final Tr(P) over the high-interest region (lower is better), mean ± std "
        "[95% CI half-width]; paper: the paper's mean / std for the same method and setting.",
        "",
        "| method | setting | n | Tr(P_f) | paper | RMSE | evidence in / out / total | traps "
        "| distance | plan s/ep |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in board["rows"]:
        paper = ("-" if r["paper_trace_mean"] is None
                 else f"{r['paper_trace_mean']:.2f} / {r['paper_trace_std']:.2f}")
        lines.append(
            f"| {r['method']} | {r['setting']} | {r['n']} | {r['trace_mean']:.2f} ± "
            f"{r['trace_std']:.2f} [{r['trace_ci95']:.2f}] | {paper} | {r['rmse_mean']:.3f} | "
            f"{r['evidence_inside_mean']:.2f} / {r['evidence_outside_mean']:.2f} / "
            f"{r['evidence_total_mean']:.2f} | {r['traps_mean']:.2f} | {r['distance_mean']:.2f} "
            f"| {r['planning_s_per_episode']:.3f} |"
        )
    lines += ["", f"![Tr(P_f) by setting]({board['suite']}.png)", ""]
    return "\n".join(lines)


def plot(board: dict[str, Any]) -> bytes:
    """PNG bytes: Tr(P_f) against the last axis, one panel per value of the other axes."""
    import io

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = board["rows"]
    axes_names = list(rows[0]["axes"]) if rows else ["budget"]
    x_name, panel_names = axes_names[-1], axes_names[:-1]
    panels = sorted({tuple(str(r["axes"][a]) for a in panel_names) for r in rows}) or [()]
    fig, axs = plt.subplots(1, len(panels), figsize=(5 * len(panels), 4), squeeze=False)
    methods = list(dict.fromkeys(r["method"] for r in rows))
    for ax, panel in zip(axs[0], panels):
        for i, method in enumerate(methods):
            sel = [r for r in rows if r["method"] == method
                   and tuple(str(r["axes"][a]) for a in panel_names) == panel]
            if not sel:
                continue
            xs = [float(r["axes"][x_name]) for r in sel]
            color = f"C{i % 10}"
            ax.errorbar(xs, [r["trace_mean"] for r in sel], yerr=[r["trace_ci95"] for r in sel],
                        marker="o", capsize=3, label=method, color=color)
            ref = [(x, r["paper_trace_mean"]) for x, r in zip(xs, sel)
                   if r["paper_trace_mean"] is not None]
            if ref:
                ax.plot(*zip(*ref), linestyle="--", marker="x", color=color, alpha=0.6,
                        label=f"{method} (paper)")
        title = ", ".join(f"{a}={v}" for a, v in zip(panel_names, panel))
        ax.set_title(title or board["suite"])
        ax.set_xlabel(x_name)
        ax.set_ylabel("Tr(P_f) (mean, 95% CI)")
        ax.grid(alpha=0.3)
    axs[0][-1].legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, metadata={"Software": None})
    plt.close(fig)
    return buf.getvalue()
