"""The evaluation protocol end to end: smoke suite, reproducibility, resumption, errors."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from maipp_bench import algos
from maipp_bench.eval import main as eval_main
from maipp_bench.protocol import leaderboard, load_protocol
from maipp_bench.protocol.protocol import PINNED_SHA256, PROTOCOL_DIR, file_sha256

REPO = Path(__file__).resolve().parent.parent


def _rows_without_timing(board: dict) -> list[dict]:
    return [{k: v for k, v in r.items() if k not in leaderboard.TIMING_FIELDS}
            for r in board["rows"]]


def _run(tmp: Path, *extra: str) -> dict:
    return eval_main(["--suite", "smoke", "--out", str(tmp / "res"), "--leaderboards",
                      str(tmp / "lb"), "--no-progress", *extra])


@pytest.fixture(scope="module")
def smoke_board(tmp_path_factory) -> tuple[dict, Path]:
    tmp = tmp_path_factory.mktemp("smoke")
    return _run(tmp), tmp


def test_protocol_file_hash_is_pinned():
    for version, digest in PINNED_SHA256.items():
        assert file_sha256(PROTOCOL_DIR / f"v{version}.json") == digest
    proto = load_protocol(1)
    assert proto.sha256 == PINNED_SHA256[1]
    suites = proto.suites
    assert {"risk_aware", "agents10", "comm", "aoi_bias", "smoke"} <= set(suites)
    for name in ("risk_aware", "agents10", "comm", "aoi_bias"):
        assert len(suites[name].instance_seeds) == 30 and len(suites[name].trial_seeds) == 10
    assert [s.key for s in suites["risk_aware"].settings] == [
        "budget=2.0", "budget=3.0", "budget=4.0", "budget=5.0"]
    assert suites["agents10"].env_config(suites["agents10"].settings[0]).n_agents == 10


def test_edited_protocol_is_refused(monkeypatch):
    monkeypatch.setitem(PINNED_SHA256, 1, "0" * 64)
    with pytest.raises(RuntimeError, match="never edited in place"):
        load_protocol(1)


def test_bad_suite_and_method_names_list_valid_ones(tmp_path):
    with pytest.raises(SystemExit, match="valid suites.*risk_aware"):
        eval_main(["--suite", "nope", "--out", str(tmp_path)])
    with pytest.raises(SystemExit, match="valid methods.*greedy"):
        eval_main(["--suite", "smoke", "--methods", "nope", "--out", str(tmp_path)])
    with pytest.raises(ValueError, match="valid methods"):
        algos.get_method("nope")
    with pytest.raises(ValueError, match=r"valid settings: \['budget=2.0'"):
        load_protocol(1).suite("risk_aware").setting("budget=9.0")
    assert load_protocol(1).suite("risk_aware").setting("budget=3.0").key == "budget=3.0"
    with pytest.raises(SystemExit, match="METHOD=PATH"):
        eval_main(["--suite", "smoke", "--checkpoint", "greedy", "--out", str(tmp_path)])
    with pytest.raises(SystemExit, match="not among the methods"):
        eval_main(["--suite", "smoke", "--methods", "random", "--checkpoint",
                   "greedy=x.pt", "--out", str(tmp_path)])


def test_every_method_yaml_names_a_registered_policy():
    conf = sorted(p.stem for p in algos.registry.METHOD_CONF_DIR.glob("*.yaml"))
    assert algos.method_names() == conf  # no YAML names an unregistered policy
    for name in conf:
        spec = algos.get_method(name)
        assert spec.policy in algos.POLICIES
    # every registered policy is used by at least one method
    used = {algos.get_method(m).policy for m in algos.method_names()}
    assert used == set(algos.POLICIES)


def test_smoke_suite_end_to_end(smoke_board):
    board, tmp = smoke_board
    assert board["protocol"]["sha256"] == PINNED_SHA256[1]
    assert {(r["method"], r["setting"]) for r in board["rows"]} == {
        (m, s) for m in ("random", "greedy") for s in ("budget=1.0", "budget=1.5")}
    for r in board["rows"]:
        assert r["n"] == 6
        assert r["distance_mean"] <= 2 * float(r["axes"]["budget"]) + 1e-9
    for ext in ("json", "md", "png"):
        assert (tmp / "lb" / f"smoke.{ext}").stat().st_size > 0
    on_disk = json.loads((tmp / "lb" / "smoke.json").read_text())
    assert on_disk["rows"] == board["rows"]


def test_greedy_beats_random_on_smoke(smoke_board):
    board, _ = smoke_board
    by = {(r["method"], r["setting"]): r["trace_mean"] for r in board["rows"]}
    for setting in ("budget=1.0", "budget=1.5"):
        assert by[("greedy", setting)] < by[("random", setting)]


def test_rerun_recomputes_nothing_and_same_seeds_give_identical_rows(smoke_board, tmp_path):
    board, tmp = smoke_board
    store = tmp / "res" / "smoke" / "greedy.jsonl"
    before = store.read_bytes()
    again = _run(tmp)
    assert store.read_bytes() == before  # nothing recomputed
    assert _rows_without_timing(again) == _rows_without_timing(board)
    fresh = _run(tmp_path)  # recomputed from scratch in a new directory
    assert _rows_without_timing(fresh) == _rows_without_timing(board)


def test_rows_of_another_algorithm_version_are_neither_reused_nor_reported(
        smoke_board, tmp_path, monkeypatch):
    board, tmp = smoke_board
    shutil.copytree(tmp / "res", tmp_path / "res")
    store = tmp_path / "res" / "smoke" / "greedy.jsonl"
    old_rows = store.read_text().splitlines()
    monkeypatch.setattr(algos.POLICIES["greedy"], "version", 99, raising=False)
    again = eval_main(["--suite", "smoke", "--methods", "greedy", "--out",
                       str(tmp_path / "res"), "--leaderboards", str(tmp_path / "lb"),
                       "--no-progress"])
    new_rows = store.read_text().splitlines()[len(old_rows):]
    assert len(new_rows) == len(old_rows)  # every episode recomputed
    fingerprint = algos.get_method("greedy").fingerprint()
    assert {json.loads(r)["method_sha256"] for r in new_rows} == {fingerprint}
    assert again["method_sha256"]["greedy"] == fingerprint
    before = {r["setting"]: r["n"] for r in board["rows"] if r["method"] == "greedy"}
    assert {r["setting"]: r["n"] for r in again["rows"]} == before  # old rows not counted


def test_killed_eval_resumes_to_the_same_file(smoke_board, tmp_path):
    board, _ = smoke_board
    cmd = [sys.executable, "-m", "maipp_bench.eval", "--suite", "smoke", "--out",
           str(tmp_path / "res"), "--leaderboards", str(tmp_path / "lb"), "--no-progress"]
    env = {**os.environ, "MAIPP_EVAL_STOP_AFTER_CHUNKS": "3"}
    killed = subprocess.run(cmd, env=env, cwd=REPO, capture_output=True, text=True)
    assert killed.returncode == 3, killed.stderr
    assert not (tmp_path / "lb" / "smoke.json").exists()
    stored = sum(len(p.read_text().splitlines()) for p in (tmp_path / "res" / "smoke").glob("*"))
    assert stored == 9  # three chunks of three episodes survived the kill
    done = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    resumed = json.loads((tmp_path / "lb" / "smoke.json").read_text())
    assert _rows_without_timing(resumed) == _rows_without_timing(board)


def test_a_run_says_whether_it_reproduces_the_board_it_finds(smoke_board, tmp_path, capsys):
    board, tmp = smoke_board
    shutil.copytree(tmp / "lb", tmp_path / "lb")  # the "committed" board
    sub = _run(tmp_path, "--episodes", "2")
    checks = leaderboard.reproduces(sub, board)
    assert len(checks) == len(sub["rows"]) > 0
    assert {v for *_, v in checks} == {"identical"}
    assert f"{len(checks)} rows identical" in capsys.readouterr().out
    assert {v for *_, v in leaderboard.reproduces(board, board)} == {"identical"}

    method, setting = checks[0][:2]
    changed = json.loads(json.dumps(board))
    row = next(r for r in changed["rows"] if (r["method"], r["setting"]) == (method, setting))
    row["spot_check"]["trace"][0] *= 1 + 1e-6  # a changed decision moves Tr(P) by far more
    verdicts = {k[:2]: k[2] for k in leaderboard.reproduces(sub, changed)}
    assert verdicts.pop((method, setting)) == "differs"
    assert set(verdicts.values()) == {"identical"}
    original = next(r for r in board["rows"] if (r["method"], r["setting"]) == (method, setting))
    row["spot_check"]["trace"][0] = original["spot_check"]["trace"][0] * (1 + 1e-12)
    assert dict((k[:2], k[2]) for k in leaderboard.reproduces(sub, changed))[
        (method, setting)] == "within 1e-09"  # last bits another CPU may round differently
    changed["method_sha256"][method] = "another algorithm version"
    verdicts = {k[:2]: k[2] for k in leaderboard.reproduces(sub, changed)}
    assert verdicts[(method, setting)] == "not comparable"
    board_of_another_protocol = json.loads(json.dumps(board))
    board_of_another_protocol["protocol"]["sha256"] = "0" * 64
    assert {v for *_, v in leaderboard.reproduces(sub, board_of_another_protocol)} == {
        "not comparable"}


def test_a_differing_row_names_the_machine_it_was_computed_on(smoke_board, capsys):
    """A row that differs says which CPU, torch kernel width and MKL kernels computed it
    when any of them is not this run's (docs/protocol.md, "Another CPU"), and nothing more
    when all match."""
    from maipp_bench.eval import _report_reproduction
    from maipp_bench.kernels import aten_capability, kernel_mode

    board, _ = smoke_board
    here = leaderboard.machine()
    assert (board["machine"]["mkl_kernels"], board["machine"]["aten_capability"]) == (
        kernel_mode(), aten_capability())
    changed = json.loads(json.dumps(board))
    row = changed["rows"][0]
    row["spot_check"]["trace"][0] += 1.0
    row.pop("provenance", None)  # the board's machine is the row's
    this_run = f"; this run: {leaderboard.describe_machine(here)};"
    other_width = "AVX512" if aten_capability() == "AVX2" else "AVX2"  # not this CPU's
    for apart in ({}, {"cpu_model": "Another CPU 9000"}, {"mkl_kernels": "branch 10"},
                  {"aten_capability": other_width}):
        changed["machine"] = {**board["machine"], **apart}
        _report_reproduction(board, changed, Path("committed.json"))
        err = capsys.readouterr().err
        assert f"differs: {row['method']} {row['setting']}" in err
        named = f"computed on {leaderboard.describe_machine(changed['machine'])}{this_run}"
        assert (named in err) == bool(apart) and ("computed on" in err) == bool(apart)
    # a board of before 2026-11-28 records neither kernels: AMD EPYC's default and AVX512
    old = {k: v for k, v in board["machine"].items()
           if k not in ("cpu_model", "mkl_kernels", "aten_capability")}
    assert leaderboard.describe_machine(leaderboard.row_machine({"machine": old}, {})) == (
        "AMD EPYC (AVX512) with MKL's default kernels")


def test_episode_subset_is_marked_and_kept_apart(tmp_path):
    board = _run(tmp_path, "--episodes", "2", "--methods", "random", "--budgets", "1.0")
    assert board["subset"] == {"episodes_per_setting": 2}
    assert [r["n"] for r in board["rows"]] == [2]
    assert not (tmp_path / "lb").exists()  # subsets never overwrite leaderboards
    assert (tmp_path / "res" / "subset-2" / "leaderboards" / "smoke.md").read_text().count(
        "Quick subset")


def test_scoring_some_methods_keeps_the_other_rows_with_their_provenance(
        smoke_board, tmp_path, monkeypatch, capsys):
    board, tmp = smoke_board
    shutil.copytree(tmp / "lb", tmp_path / "lb")  # the committed board: random and greedy
    shutil.copytree(tmp / "res", tmp_path / "res")
    (tmp_path / "res" / "smoke" / "random.jsonl").unlink()  # random is scored again
    # The copied file, not the fixture's dict: another test may have rewritten the
    # shared board since (same rows, a later date).
    board = json.loads((tmp_path / "lb" / "smoke.json").read_text())
    again = _run(tmp_path, "--methods", "random")
    assert [(r["method"], r["setting"]) for r in again["rows"]] == [
        (r["method"], r["setting"]) for r in board["rows"]]  # same rows, same order
    origin = {k: board[k] for k in leaderboard.PROVENANCE}
    for old, new in zip(board["rows"], again["rows"]):
        if new["method"] == "greedy":  # kept as they were, with the run that made them
            assert new == {**old, "provenance": origin}
        else:
            assert "provenance" not in new
            assert {k: v for k, v in new.items() if k not in leaderboard.TIMING_FIELDS} == {
                k: v for k, v in old.items() if k not in leaderboard.TIMING_FIELDS}
    assert again["method_sha256"] == board["method_sha256"]
    assert json.loads((tmp_path / "lb" / "smoke.json").read_text())["rows"] == again["rows"]
    assert "Rows of `greedy` kept from an earlier run" in (tmp_path / "lb" / "smoke.md").read_text()
    assert "kept 2 rows" in capsys.readouterr().out
    # Kept again by a later run: the provenance stays the first run's.
    assert _run(tmp_path, "--methods", "random")["rows"][-1]["provenance"] == origin

    # Rows of a changed algorithm are dropped, not carried; --fresh-board drops them all.
    monkeypatch.setattr(algos.POLICIES["greedy"], "version", 99, raising=False)
    shutil.copytree(tmp / "lb", tmp_path / "lb2")
    changed = eval_main(["--suite", "smoke", "--methods", "random", "--out",
                         str(tmp_path / "res"), "--leaderboards", str(tmp_path / "lb2"),
                         "--no-progress"])
    assert {r["method"] for r in changed["rows"]} == {"random"}
    assert "dropped 2 rows" in capsys.readouterr().err
    monkeypatch.undo()
    fresh = _run(tmp_path, "--methods", "random", "--fresh-board")
    assert {r["method"] for r in fresh["rows"]} == {"random"}
    assert set(fresh["method_sha256"]) == {"random"}
