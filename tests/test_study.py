"""The speed–accuracy study: its science checks, its command (which writes only into --out)
and docs/generate.py, the script outside the package that regenerates docs/ from it."""

from __future__ import annotations

import ast
import importlib.util
from pathlib import Path

import pytest

from masking_lab.commands.cli import main as cli_main
from masking_lab.core.psychometric import LEVITT_1U3D
from masking_lab.planning.study import (
    BLOCKS,
    cheapest_matching,
    convergence_study,
    settings_study,
)

ROOT = Path(__file__).resolve().parents[1]


def _load_generate():
    spec = importlib.util.spec_from_file_location("docs_generate", ROOT / "docs" / "generate.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


generate = _load_generate()
fill_doc = generate.fill_doc


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
    with pytest.raises(generate.DocError, match=r"study:answer"):
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


NAMES = (
    "convergence.csv",
    "convergence.png",
    "settings.csv",
    "ladder.csv",
    "speed_accuracy.png",
    "convergence_2afc.png",
    "procedures.csv",
    "procedures.png",
    *(f"blocks/{b}.md" for b in BLOCKS),
)


@pytest.fixture(scope="module")
def generated(tmp_path_factory):
    """Two runs of ``docs/generate.py study`` (each runs ``masking-lab study --out OUT ARGS``
    in-process) on one document and one --out: the files and the document after each.

    The command test and the script test share these two simulations: one pair of runs shows
    both that the command repeats its bytes and that the script repeats its document.
    """
    root = tmp_path_factory.mktemp("generated")
    doc, out = _doc(root), root / "study"
    runs = []
    for _ in range(2):
        assert generate.main(["study", "--doc", str(doc), "--out", str(out), *ARGS]) == 0
        files = {n: (out / n).read_bytes() for n in NAMES}
        listed = sorted(p.relative_to(out).as_posix() for p in out.rglob("*.*"))
        runs.append((files, listed, doc.read_text()))
    return out, runs


def test_the_command_writes_figures_tables_and_blocks_into_out_byte_for_byte(generated):
    _, ((first, listed, _), (second, listed_again, _)) = generated
    assert listed == listed_again == sorted(NAMES)
    settings = first["blocks/settings.md"].decode()
    assert "| 4,4,4,2 | 11/8 **(paper)** | reversal mean |" in settings
    assert "Fewest trials for that precision" in first["blocks/answer.md"].decode()
    convergence = first["blocks/convergence.md"].decode()
    assert "| 3IFC | 0.25 | 0.375 | 1 | 0.7937 |" in convergence
    assert "| 2AFC | 0.25 | 0.375 | 0.7393 | 0.8315 |" in convergence
    procedures = first["blocks/procedures.md"].decode()
    assert "| psi-marginal | SD ≤ 1.6 dB **(protocol)** | posterior mean |" in procedures
    assert "Fewest trials for ±1 dB" in procedures
    assert first["convergence.png"][:4] == b"\x89PNG"
    # a second run gives the same bytes: the committed study only changes with its results
    assert second == first


def test_generate_script_pastes_the_blocks_into_the_document(generated):
    _, ((files, _, text), (_, _, text_again)) = generated
    for b in BLOCKS:
        body = files[f"blocks/{b}.md"].decode().rstrip()
        assert f"<!-- study:{b} -->\n{body}\n<!-- /study:{b} -->" in text
    assert "Generated by `python docs/generate.py study`" in text
    assert text_again == text  # the second run leaves the document as the first left it


def test_a_document_without_the_blocks_exits_2_before_simulating(tmp_path, capsys):
    doc = tmp_path / "plain.md"
    doc.write_text("# no blocks here\n")
    code = generate.main(["study", "--doc", str(doc), "--out", str(tmp_path / "s"), *ARGS])
    assert code == 2
    assert "no generated block" in capsys.readouterr().err
    assert doc.read_text() == "# no blocks here\n"
    assert not (tmp_path / "s").exists()
    assert generate.main(["study", "--doc", str(tmp_path / "none.md"), *ARGS]) == 2
    assert "cannot read the study document" in capsys.readouterr().err


def test_the_command_leaves_docs_alone_in_the_repository(tmp_path, monkeypatch):
    # Run where a docs/speed-accuracy.md exists (as in the repository): only study_out/ appears.
    monkeypatch.chdir(tmp_path)
    doc = _doc(tmp_path)
    (tmp_path / "docs").mkdir()
    doc = doc.rename(tmp_path / "docs" / "speed-accuracy.md")
    before = doc.read_text()
    small = ["--replicates", "4", "--ml-replicates", "0", "--convergence-replicates", "4"]
    assert main([*small, "--quest-replicates", "0", "--max-reversals", "15"]) == 0
    assert doc.read_text() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["docs", "study_out"]
    assert [p.name for p in (tmp_path / "docs").iterdir()] == ["speed-accuracy.md"]


def test_no_module_of_the_package_is_a_script():
    # Scripts live outside the package (docs/generate.py); the CLI's entry point is the one
    # `__main__` guard, for `python -m masking_lab.commands.cli`.
    for path in (ROOT / "masking_lab").rglob("*.py"):
        if path == ROOT / "masking_lab" / "commands" / "cli.py":
            continue
        source = path.read_text(encoding="utf-8")
        if "__name__" not in source:
            continue  # no comparison with __name__ can be in it: not worth parsing
        for node in ast.walk(ast.parse(source)):
            if isinstance(node, ast.Compare) and isinstance(node.left, ast.Name):
                assert node.left.id != "__name__", f"{path}: a __main__ script"


def test_the_committed_document_has_every_generated_block():
    text = (ROOT / "docs" / "speed-accuracy.md").read_text(encoding="utf-8")
    for b in BLOCKS:
        assert f"<!-- study:{b} -->" in text and f"<!-- /study:{b} -->" in text
    for png in ("convergence.png", "speed_accuracy.png"):
        assert f"study/{png}" in text
        assert (ROOT / "docs" / "study" / png).read_bytes()[:4] == b"\x89PNG"
