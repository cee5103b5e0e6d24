"""The committed leaderboards belong to this code: same protocol, same method fingerprints,
same shipped checkpoints, and their cheap rows recompute to the numbers they show."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch

from maipp_bench import algos
from maipp_bench.kernels import aten_capability
from maipp_bench.protocol.leaderboard import machine_apart, row_machine
from maipp_bench.protocol.protocol import file_sha256, load_protocol
from maipp_bench.protocol.runner import run_chunk

ROOT = Path(__file__).resolve().parent.parent
BOARDS = sorted((ROOT / "leaderboards").glob("*.json"))
# Spot-check rows of the cheap methods recompute in full (random always; greedy and the
# learned methods' greedy decoding with at most CHEAP_MAX_AGENTS agents); the others (RRT,
# oracle, TI, ten agents) their first EXPENSIVE_EPISODES episodes (each episode's noise is
# its own, so a prefix is exact). Chosen by method, not by the row's measured planning
# time, which moves with the machine and its kernels.
FREE_METHODS = frozenset({"random"})
CHEAP_METHODS = frozenset({"greedy", "catnipp_greedy", "ours_greedy", "mappo",
                           "catnipp_greedy_full_roadmap"})
CHEAP_MAX_AGENTS = 3
EXPENSIVE_EPISODES = 2


def _load(path: Path) -> dict:
    return json.loads(path.read_text())


def test_the_paper_and_dual_domain_suites_have_boards():
    assert {p.stem for p in BOARDS} >= {"risk_aware", "agents10", "comm", "aoi_bias"}


@pytest.mark.parametrize("path", BOARDS, ids=lambda p: p.stem)
def test_board_matches_protocol_fingerprints_and_checkpoints(path):
    board = _load(path)
    protocol = load_protocol(board["protocol"]["version"])
    assert board["protocol"]["sha256"] == protocol.sha256
    assert board["subset"] is None and board["rows"]
    methods = {r["method"] for r in board["rows"]}
    assert methods == set(board["method_sha256"])
    for method, sha in board["method_sha256"].items():
        # A changed algorithm (version, params, policy) must come with rerun rows.
        assert algos.get_method(method).fingerprint() == sha, method
    for method, ckpt in board["checkpoints"].items():
        shipped = algos.get_method(method).checkpoint(None)
        assert file_sha256(shipped) == ckpt["sha256"], method
    suite = protocol.suite(board["suite"])
    for r in board["rows"]:
        assert r["n"] == suite.n_episodes
        spot = r["spot_check"]
        assert spot["trial"] == suite.trial_seeds[0]
        assert spot["instances"] == list(suite.instance_seeds)
        assert len(spot["trace"]) == len(suite.instance_seeds)


def _first_setting_rows():
    for path in BOARDS:
        board = _load(path)
        first = board["rows"][0]["setting"]
        for r in board["rows"]:
            if r["setting"] == first:
                yield pytest.param(board, r, id=f"{path.stem}-{r['method']}-{first}")


@pytest.mark.parametrize("board,row", list(_first_setting_rows()))
def test_committed_row_spot_check_recomputes(board, row):
    suite = load_protocol(board["protocol"]["version"]).suite(board["suite"])
    setting = next(s for s in suite.settings if s.key == row["setting"])
    spec = algos.get_method(row["method"])
    kwargs = {"checkpoint": str(spec.checkpoint(None))} if spec.learned else {}
    spot = row["spot_check"]
    config = suite.env_config(setting)
    cheap = row["method"] in FREE_METHODS or (row["method"] in CHEAP_METHODS
                                              and config.n_agents <= CHEAP_MAX_AGENTS)
    n = len(spot["instances"]) if cheap else EXPENSIVE_EPISODES
    with torch.inference_mode():
        rows = run_chunk(spec, config, spot["instances"][:n], spot["trial"], **kwargs)
    # Same seeds, same code, MKL's CPU-independent kernels (tests/conftest.py, as eval
    # pins them): the same episodes on another x86 CPU. The tolerance only absorbs the last
    # bits other vector units may round differently; a changed decision moves Tr(P) by far
    # more.
    got = [r["trace"] for r in rows]
    if got != pytest.approx(spot["trace"][:n], rel=1e-9, abs=1e-9):
        recorded = row_machine(board, row)["aten_capability"]
        matched = sum(math.isclose(g, t, rel_tol=1e-9, abs_tol=1e-9)
                      for g, t in zip(got, spot["trace"]))
        if (spec.params.get("mode") == "ti" and recorded != aten_capability()
                and 2 * matched >= n):
            # torch's own float32 softmax and attention kernels (not MKL's, so not pinned)
            # round differently at another vector width, which can flip a decision of TI's
            # float32 rollouts (docs/protocol.md, "Another CPU"); a changed algorithm would
            # change most of a row's episodes, not one in a few.
            pytest.xfail(f"{row['method']}: TI row computed with torch's {recorded} kernels, "
                         f"recomputed with {aten_capability()}: {got} against "
                         f"{spot['trace'][:n]}")
    assert got == pytest.approx(spot["trace"][:n], rel=1e-9, abs=1e-9)
    if machine_apart(board, row) is None:
        # Computed on this kind of CPU, at this kernel width, under these MKL kernels (a row
        # recomputed under the pinned kernels, here on a box like its own): bit for bit.
        assert got == spot["trace"][:n]


def test_git_commit_named_by_the_environment(monkeypatch):
    """A lent GPU machine's copy of the tree may carry a stale ``.git``: the commit the
    command names ($MAIPP_BENCH_COMMIT) is recorded, with a warning where the checkout's
    HEAD differs; without either, "unknown"."""
    import subprocess

    from maipp_bench.protocol import leaderboard

    monkeypatch.delenv("MAIPP_BENCH_COMMIT", raising=False)
    git = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True,
                         text=True)
    if git.returncode:
        pytest.skip("not a git checkout")
    assert leaderboard.git_commit() == git.stdout.strip()
    monkeypatch.setenv("MAIPP_BENCH_COMMIT", "f" * 40)
    with pytest.warns(UserWarning, match="but this checkout.s HEAD is"):
        assert leaderboard.git_commit() == "f" * 40
    monkeypatch.setattr(leaderboard.subprocess, "run", lambda *a, **k: subprocess.
                        CompletedProcess(a, 128, "", "fatal: not a git repository"))
    assert leaderboard.git_commit() == "f" * 40  # no HEAD to differ: no warning
    monkeypatch.delenv("MAIPP_BENCH_COMMIT")
    assert leaderboard.git_commit() == "unknown"
