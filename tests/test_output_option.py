"""Every command's ``--out``: an empty name (``--out "$OUT"`` with OUT unset) is refused at once.

``Path("")`` is the current folder: before, the demo wrote its data/, analysis/ and render/
folders there, and ``plan`` simulated for seconds before failing to replace it.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from masking_lab.commands.cli import main

ROOT = Path(__file__).resolve().parents[1]
BASELINE = str(ROOT / "protocols" / "baseline.yaml")
SCENE = str(ROOT / "protocols" / "scenes" / "bump_rough.yaml")
SHIFTS = str(ROOT / "data_schema" / "shifts.csv")

COMMANDS = {
    "analyze": ["analyze", "DATA"],
    "fit": ["fit", SHIFTS],
    "usertest-report": ["usertest-report", "DATA"],
    "plan": ["plan", BASELINE],
    "study": ["study"],
    "demo": ["demo"],
    "render": ["render", SCENE, "--params", "masking_params.json"],
    "gamut": ["gamut", "--params", "masking_params.json"],
}


@pytest.mark.parametrize("command", sorted(COMMANDS))
@pytest.mark.parametrize("name", ["", "  "])
def test_an_empty_output_folder_is_refused_before_any_work(
    command, name, tmp_path, monkeypatch, capsys
):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "DATA").mkdir()
    with pytest.raises(SystemExit) as exit_:
        main([*COMMANDS[command], "--out", name])
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert f"masking-lab {command}: error: argument --out: an empty name" in err
    assert "give the output folder" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["DATA"]  # nothing written here


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_every_out_option_checks_its_name(command):
    # A command added later with its own --out should use options.output_folder too.
    from masking_lab.commands.cli import build_parser
    from masking_lab.commands.options import output_folder

    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    (out,) = [a for a in sub.choices[command]._actions if "--out" in a.option_strings]
    assert out.type is output_folder
