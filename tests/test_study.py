"""The speed–accuracy study: its science checks and its one regenerating command."""

from __future__ import annotations

from pathlib import Path

import pytest

from masking_lab.commands.cli import main as cli_main
from masking_lab.core.psychometric import LEVITT_1U3D
from masking_lab.planning.study import (
    StudyError,
    cheapest_matching,
    convergence_study,
    fill_doc,
    settings_study,
)

ROOT = Path(__file__).resolve().parents[1]
BLOCKS = ("meta", "convergence", "settings", "answer", "procedures")


def main(argv: list[str]) -> int:
    """``masking-lab study ARGS`` (the study's command line lives in masking_lab.commands)."""
    return cli_main(["study", *argv])


def test_small_steps_converge_where_levitt_says():
    # 1-up 3-down with equal steps of half a psychometric scale: the reversal mean sits at the
    # 0.794 point (Levitt 1971); a 0.7393 down/up ratio moves it up towards 0.8315.
    rows = convergence_study(step_over_scale=(0.5,), replicates=400, n_reversals=40, n_averaged=32)
    equal = next(r for r in rows if r["down_up_ratio"] == 1.0)
    ratio = next(r for r in rows if r["down_up_ratio"] != 1.0)
    assert equal["target_p"] == pytest.approx(LEVITT_1U3D, abs=1e-6)
    assert equal["p_low"] - 0.005 <= LEVITT_1U3D <= equal["p_high"] + 0.005
    assert abs(equal["p_converged"] - LEVITT_1U3D) < 0.01
    assert ratio["target_p"] == pytest.approx(0.8315, abs=1e-4)
    assert 0.82 < ratio["p_converged"] < 0.85
    assert equal["completed"] == 1.0


def test_the_0_7393_ratio_is_a_2afc_constant():
    """García-Pérez's ratio holds its track near 83 % across step sizes in 2AFC, not in 3IFC."""
    kw = {"ratios": (0.7393,), "replicates": 400, "n_reversals": 40, "n_averaged": 32}
    steps = (0.5, 2.0)
    two = convergence_study(step_over_scale=steps, guess=0.5, **kw)
    three = convergence_study(step_over_scale=steps, guess=1 / 3, **kw)
    assert all(0.82 < r["p_converged"] < 0.845 for r in two)
    assert abs(two[1]["p_converged"] - two[0]["p_converged"]) < 0.01  # flat in 2AFC
    assert three[1]["p_converged"] - three[0]["p_converged"] > 0.008  # drifts up in 3IFC
    assert {r["guess"] for r in two} == {0.5}


def test_cheapest_setting_is_at_least_as_precise_and_no_longer_than_the_paper():
    result = settings_study(replicates=12, ml_replicates=0, max_reversals=15)
    cheapest = cheapest_matching(result)
    assert cheapest.reference["rule"] == "11/8"
    assert cheapest.reference["schedule"] == "4,4,4,2"
    assert cheapest.best["rmse_db"] <= cheapest.reference["rmse_db"]
    assert cheapest.best["trials_median"] <= cheapest.reference["trials_median"]
    assert cheapest.best_reversal_mean["estimator"] == "reversal_mean"


def test_fill_doc_replaces_only_the_generated_blocks():
    doc = (
        "intro\n<!-- study:a -->\nold\n<!-- /study:a -->\nmiddle\n"
        "<!-- study:b -->\n<!-- /study:b -->\n"
    )
    out = fill_doc(doc, {"a": "new a", "b": "new b\n"})
    assert out == (
        "intro\n<!-- study:a -->\nnew a\n<!-- /study:a -->\nmiddle\n<!-- study:b -->\nnew b\n"
        "<!-- /study:b -->\n"
    )
    assert fill_doc(out, {"a": "new a", "b": "new b"}) == out  # idempotent


def test_fill_doc_names_missing_blocks():
    with pytest.raises(StudyError, match=r"study:answer"):
        fill_doc("<!-- study:a -->\n<!-- /study:a -->\n", {"a": "x", "answer": "y"})


def _doc(tmp_path: Path) -> Path:
    doc = tmp_path / "speed-accuracy.md"
    doc.write_text(
        "# Study\n" + "".join(f"<!-- study:{b} -->\n<!-- /study:{b} -->\n" for b in BLOCKS)
    )
    return doc


ARGS = [
    "--replicates",
    "8",
    "--ml-replicates",
    "3",
    "--convergence-replicates",
    "30",
    "--max-reversals",
    "15",
    "--quest-replicates",
    "10",
]


def test_one_command_regenerates_figures_tables_and_the_document_byte_for_byte(tmp_path):
    doc = _doc(tmp_path)
    out = tmp_path / "study"
    assert main(["--out", str(out), "--doc", str(doc), *ARGS]) == 0
    names = (
        "convergence.csv",
        "convergence.png",
        "settings.csv",
        "ladder.csv",
        "speed_accuracy.png",
        "convergence_2afc.png",
        "procedures.csv",
        "procedures.png",
    )
    first = {n: (out / n).read_bytes() for n in names}
    text = doc.read_text()
    assert "| 4,4,4,2 | 11/8 **(paper)** | reversal mean |" in text
    assert "Fewest trials for that precision" in text
    assert "| 3IFC | 0.25 | 0.375 | 1 | 0.7937 |" in text
    assert "| 2AFC | 0.25 | 0.375 | 0.7393 | 0.8315 |" in text
    assert "| QUEST+ | SD ≤ 1.08 dB **(protocol)** | posterior mean |" in text
    assert "Fewest trials for ±1 dB" in text
    assert first["convergence.png"][:4] == b"\x89PNG"
    # a second run gives the same bytes: the committed study only changes with its results
    assert main(["--out", str(out), "--doc", str(doc), *ARGS]) == 0
    assert {n: (out / n).read_bytes() for n in names} == first
    assert doc.read_text() == text


def test_a_document_without_the_blocks_exits_2(tmp_path, capsys):
    doc = tmp_path / "plain.md"
    doc.write_text("# no blocks here\n")
    code = main(["--out", str(tmp_path / "s"), "--doc", str(doc), *ARGS])
    assert code == 2
    assert "no generated block" in capsys.readouterr().err
    assert doc.read_text() == "# no blocks here\n"


def test_the_committed_document_has_every_generated_block():
    text = (ROOT / "docs" / "speed-accuracy.md").read_text(encoding="utf-8")
    for b in BLOCKS:
        assert f"<!-- study:{b} -->" in text and f"<!-- /study:{b} -->" in text
    for png in ("convergence.png", "speed_accuracy.png"):
        assert f"study/{png}" in text
        assert (ROOT / "docs" / "study" / png).read_bytes()[:4] == b"\x89PNG"
