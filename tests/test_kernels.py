"""Protocol rows run under MKL's CPU-independent kernels (maipp_bench/kernels.py), so that
boards reproduce on other CPUs; a run that cannot have them says so instead of scoring."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from maipp_bench.kernels import PINNED, kernel_mode

needs_mkl = pytest.mark.skipif(kernel_mode() == "unavailable", reason="torch without MKL")


def test_the_suite_runs_under_the_protocol_kernels():
    # tests/conftest.py pins them before any import makes MKL's first call, as eval does.
    assert kernel_mode() in PINNED
    if torch.backends.mkl.is_available():
        assert kernel_mode() == "COMPATIBLE"


@needs_mkl
def test_eval_refuses_to_score_once_mkl_runs_other_kernels(tmp_path):
    # tensordict's import makes MKL's first call; eval imported after it cannot pin.
    code = ("import tensordict; "
            "from maipp_bench import eval as ev; "
            f"ev.main(['--suite', 'risk_aware', '--methods', 'random', '--episodes', '1', "
            f"'--out', {str(tmp_path)!r}, '--leaderboards', {str(tmp_path)!r}])")
    env = {"PATH": "/usr/bin:/bin", "HOME": str(tmp_path)}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         env=env, timeout=120)
    assert out.returncode != 0
    assert "error: MKL already runs its default kernels in this process" in out.stderr
    assert "MKL_CBWR=COMPATIBLE" in out.stderr


@needs_mkl
def test_importing_eval_pins_the_kernels_before_tensordict_runs_mkl(tmp_path):
    # without MKL_CBWR in the environment: eval's import order alone must pin them
    code = ("import maipp_bench.eval, tensordict, torch; "
            "from maipp_bench.kernels import kernel_mode; "
            "torch.randn(64, 64) @ torch.randn(64, 64); print(kernel_mode())")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         env={"PATH": "/usr/bin:/bin", "HOME": str(tmp_path)}, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split() == ["COMPATIBLE"]


@needs_mkl
def test_kernels_cost_plays_each_method_under_both_kernel_sets(tmp_path, monkeypatch, capsys):
    """benchmarks/kernels_cost.py: each child runs the kernels it was given (the script
    checks the mode each reports) and the two play the same episodes as the board."""
    script = Path(__file__).parents[1] / "benchmarks" / "kernels_cost.py"
    out = tmp_path / "cost.json"
    proc = subprocess.run([sys.executable, str(script), "--methods", "random", "--episodes",
                           "2", "--repeats", "1", "--setting", "budget=2.0", "--branches", "AUTO",
                           "--out", str(out)],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    report = json.loads(out.read_text())["methods"]["random"]
    assert report["episodes_differing"] == []
    # the committed random row's first two episodes, under either kernel set
    assert report["differ_from_board"] == {"default": [], "cpu-independent": []}
    auto = report["branch AUTO"]  # a branch asked for, played alone
    assert auto["kernels"] == "branch 2" and auto["differ_from_board"] == [] and auto["wall_s"] > 0
    assert all(len(v) == 1 and v[0] > 0 for v in report["wall_s"].values())
    # a bad argument fails before any child starts (checked in this process)
    monkeypatch.syspath_prepend(str(script.parent))
    from kernels_cost import main

    monkeypatch.setattr(sys, "argv", ["kernels_cost.py", "--methods", "no_such_method"])
    with pytest.raises(SystemExit) as exit_:
        main()
    assert exit_.value.code == 2 and "no_such_method" in capsys.readouterr().err


@needs_mkl
def test_kernels_chosen_with_mkl_cbwr_are_recorded_and_never_mixed(tmp_path):
    """MKL_CBWR=AUTO (MKL's usual speed): eval warns, scores and records those kernels; a
    run under the pinned kernels on the same store recomputes instead of reusing them."""
    from maipp_bench.eval import main

    args = ["--suite", "risk_aware", "--methods", "random", "--budgets", "2", "--episodes", "2",
            "--out", str(tmp_path / "res"), "--leaderboards", str(tmp_path / "lb"),
            "--no-progress", "--workers", "1"]
    out = subprocess.run([sys.executable, "-m", "maipp_bench.eval", *args], capture_output=True,
                         text=True, timeout=300, cwd=tmp_path,
                         env={"PATH": "/usr/bin:/bin", "HOME": str(tmp_path), "MKL_CBWR": "AUTO"})
    assert out.returncode == 0, out.stderr[-2000:]
    assert "MKL_CBWR=AUTO: rows computed under MKL's branch 2 kernels may differ" in out.stderr
    subset = tmp_path / "res" / "subset-2"

    def stored() -> list[str]:
        lines = (subset / "risk_aware" / "random.jsonl").read_text().splitlines()
        return [json.loads(line)["mkl_kernels"] for line in lines]

    assert stored() == ["branch 2"] * 2
    board = json.loads((subset / "leaderboards" / "risk_aware.json").read_text())
    assert board["machine"]["mkl_kernels"] == "branch 2"
    board = main(args)  # this process runs the pinned kernels (tests/conftest.py)
    assert stored() == ["branch 2"] * 2 + ["COMPATIBLE"] * 2
    assert board["machine"]["mkl_kernels"] == "COMPATIBLE"
    assert [r["n"] for r in board["rows"]] == [2]
