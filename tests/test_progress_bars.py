"""Progress bars (issue 17): drawn by tqdm on a terminal or with --progress, quiet otherwise."""

from __future__ import annotations

from pathlib import Path

from masking_lab.commands.cli import main
from masking_lab.simulation.synthetic_logs import simulate_study

ROOT = Path(__file__).resolve().parents[1]


def test_analyze_draws_bars_for_logs_and_fits_with_progress(tmp_path, capsys):
    simulate_study(tmp_path / "d", n_participants=2, seed=5, baseline_start_above_db=10.0)
    argv = ["analyze", str(tmp_path / "d"), "--figures", "none", "--pf-boot", "0"]
    assert main([*argv, "--out", str(tmp_path / "o"), "--progress"]) == 0
    err = capsys.readouterr().err
    assert "logs read" in err and "6/6" in err
    assert "psychometric fits" in err and "100%" in err
    assert main([*argv, "--out", str(tmp_path / "o2")]) == 0  # not a terminal: quiet
    err = capsys.readouterr().err
    assert "logs read" not in err and "psychometric fits" not in err


def test_plan_draws_a_step_bar_with_progress(tmp_path, capsys):
    argv = ["plan", str(ROOT / "protocols" / "baseline.yaml"), "--replicates", "8"]
    argv += ["--ml-replicates", "0", "--quest-replicates", "0", "--schedules", "4,4,4,2"]
    argv += ["--stop-rules", "11/8", "--max-reversals", "11", "--out", str(tmp_path / "p")]
    assert main([*argv, "--progress"]) == 0
    err = capsys.readouterr().err
    assert "steps" in err and "reversal ladder" in err and "plan: schedule" not in err
    assert main([*argv, "--out", str(tmp_path / "p2")]) == 0
    assert "plan: schedule 1/1" in capsys.readouterr().err  # not a terminal: plain lines
