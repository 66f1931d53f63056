"""`masking-lab solve`: table and JSON answers, parameters from a file, bad input exits 2."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
from params_support import masking_entry

from masking_lab.commands.cli import main
from masking_lab.formats.masking_params import write_masking_params
from masking_lab.formats.resources import shipped

DIRECT = ["--mv-masked-by-ev", "1.39,1.09", "--ev-masked-by-mv=-6.22,0.66"]


def table4_case4(m_p, e_p, a=1.39, b=1.09, c=-6.22, d=0.66):
    """Paper Table 4, case 4 (both ramps rising)."""
    return (m_p + b * e_p + a + b * c) / (1 - b * d), (d * m_p + e_p + c + a * d) / (1 - b * d)


def run_json(capsys, *args):
    code = main(["solve", *args, "--json"])
    return code, json.loads(capsys.readouterr().out)


def test_json_has_equal_length_arrays_and_the_paper_answers(capsys):
    code, out = run_json(capsys, *DIRECT, "--mv-target", "12", "--ev-target", "0,5,10")
    assert code == 0
    for key in ("mv_input_db", "ev_input_db", "case", "status", "solutions"):
        assert len(out[key]) == 3
    assert out["status"] == ["unique"] * 3 and out["case"] == [4, 4, 4]
    for i, e_p in enumerate((0.0, 5.0, 10.0)):
        m_i, e_i = table4_case4(12.0, e_p)
        assert out["mv_input_db"][i] == pytest.approx(m_i, abs=1e-9)
        assert out["ev_input_db"][i] == pytest.approx(e_i, abs=1e-9)
        assert out["solutions"][i] == [
            {"mv_input_db": out["mv_input_db"][i], "ev_input_db": out["ev_input_db"][i], "case": 4}
        ]
    assert out["bd"] == pytest.approx(1.09 * 0.66)


def test_json_lists_every_answer_when_there_are_several(capsys):
    code, out = run_json(
        capsys,
        "--mv-masked-by-ev",
        "1,2",
        "--ev-masked-by-mv=-1,1",
        "--mv-target=-20,3",
        "--ev-target=-5,0",
    )
    assert code == 1  # not every target has exactly one answer
    assert out["status"] == ["multiple", "none"]
    assert out["mv_input_db"] == [None, None] and out["case"] == [None, None]
    assert out["solutions"][0] == [
        {"mv_input_db": -20.0, "ev_input_db": -5.0, "case": 1},
        {"mv_input_db": 31.0, "ev_input_db": 25.0, "case": 4},
    ]
    assert out["solutions"][1] == [] and "outside the reachable region" in out["reason"][1]


def test_json_marks_a_continuum_with_its_direction(capsys):
    code, out = run_json(
        capsys,
        "--mv-masked-by-ev",
        "1,2",
        "--ev-masked-by-mv=-1,0.5",
        "--mv-target=-9",
        "--ev-target=5",
    )
    assert code == 1 and out["status"] == ["multiple"] and out["continuum"] == [True]
    assert out["solutions"][0] == [
        {"mv_input_db": 2.0, "ev_input_db": 5.0, "case": 4, "direction": [1.0, 0.5]}
    ]


def test_silence_nan_and_the_rating_in_json(capsys):
    code, out = run_json(
        capsys, *DIRECT, "--mv-target", "12", "--ev-target=-inf,nan,10", "--max-mv-db-sl", "30"
    )
    assert code == 1
    assert out["ev_input_db"][0] == "-inf" and out["mv_input_db"][0] == 12.0
    assert out["status"][1] == "none" and out["reason"][1] == "target is NaN"
    assert out["mv_exceeds_rating"] == [False, False, True]
    assert out["mv_input_db"][2] > 30  # reported, not clipped
    # --max-mv-db-sl overrides; EV keeps the reference rig's rating (solve checks it by default)
    assert out["max_mv_db_sl"] == 30.0 and out["max_ev_db_sl"] == 30.0


def test_table_output(capsys):
    code = main(["solve", *DIRECT, "--mv-target", "12", "--ev-target", "5", "--max-mv-db-sl=30"])
    text = capsys.readouterr().out
    assert code == 0
    m_i, e_i = table4_case4(12.0, 5.0)
    row = next(line for line in text.splitlines() if line.strip().startswith("12"))
    assert f"{m_i:.4g}" in row and f"{e_i:.4g}" in row and "unique" in row
    assert "MV above its rating (30 dB SL)" in row


def test_table_shows_several_answers(capsys):
    code = main(
        [
            "solve",
            "--mv-masked-by-ev",
            "1,2",
            "--ev-masked-by-mv=-1,0.5",
            "--mv-target=-9",
            "--ev-target=5",
        ]
    )
    text = capsys.readouterr().out
    assert code == 1 and "multiple" in text and "t ≥ 0" in text


def _write_params(tmp_path, functions):
    """A masking_params.json that follows data_schema/masking_params.schema.json."""
    doc = {
        "schema_version": 1,
        "software_version": "test",
        "created_utc": "2024-01-01T00:00:00Z",
        "provenance": {"source": "fit", "inputs": [], "settings": {}},
        "functions": functions,
    }
    path = tmp_path / "masking_params.json"
    write_masking_params(path, doc)
    return str(path)


def test_params_file_with_named_stimuli(tmp_path, capsys):
    params = _write_params(
        tmp_path,
        [
            masking_entry("MV180", "EV270", 1.39, 1.09),
            masking_entry("EV270", "MV180", -6.22, 0.66),
            masking_entry("MV120", "EV270", -0.387, 0.939),
            masking_entry("EV270", "MV120", -7.44, 0.711),
        ],
    )
    code, out = run_json(
        capsys, "--params", params, "--mv", "MV180", "--mv-target", "12", "--ev-target", "5"
    )
    assert code == 0 and out["mv_stimulus"] == "MV180" and out["ev_stimulus"] == "EV270"
    assert out["mv_input_db"][0] == pytest.approx(table4_case4(12.0, 5.0)[0], abs=1e-9)
    # Two MV stimuli in the file: --mv is needed.
    assert main(["solve", "--params", params, "--mv-target", "1", "--ev-target", "1"]) == 2
    assert "--mv NAME" in capsys.readouterr().err


def test_params_file_with_one_mv_stimulus_needs_no_name(tmp_path, capsys):
    params = _write_params(
        tmp_path,
        [
            masking_entry("MV270", "EV270", 1.48, 1.113),
            masking_entry("EV270", "MV270", -2.24, 0.602),
        ],
    )
    code, out = run_json(capsys, "--params", params, "--mv-target", "6", "--ev-target", "0")
    assert code == 0 and out["mv_stimulus"] == "MV270"


def test_device_config_supplies_the_rating(tmp_path, capsys):
    cfg = tmp_path / "rig.yaml"
    # A whole rig config (it is validated in full): the reference rig with MV 20, EV 25 dB SL.
    reference = shipped("protocols", "devices/default.yaml").read_text(encoding="utf-8")
    head, mv = reference.split("  MV:\n", 1)
    head = head.replace("max_level_db_sl: 30", "max_level_db_sl: 25", 1)
    cfg.write_text(head + "  MV:\n" + mv.replace("max_level_db_sl: 30", "max_level_db_sl: 20", 1))
    code, out = run_json(
        capsys, *DIRECT, "--mv-target", "12", "--ev-target", "0", "--device-config", str(cfg)
    )
    assert code == 0 and (out["max_mv_db_sl"], out["max_ev_db_sl"]) == (20.0, 25.0)
    assert out["mv_exceeds_rating"] == [True] and out["ev_exceeds_rating"] == [False]


@pytest.mark.parametrize(
    "args, message",
    [
        (["--mv-target", "1,2", "--ev-target", "1,2,3"], "equal length"),
        (["--mv-target", "1,x", "--ev-target", "1"], "'x' is not a number"),
        (["--mv-masked-by-ev", "1,2,3", "--ev-masked-by-mv", "1,1"], "give two numbers"),
        (["--mv-masked-by-ev", "1,2"], "give both"),
        (["--mv-masked-by-ev=1,-2", "--ev-masked-by-mv", "1,1"], "slopes must be ≥ 0"),
        (["--params", "p.json", "--mv-masked-by-ev", "1,1"], "not both"),
        ([], "no masking functions"),
        (["--params", "/nonexistent/masking_params.json"], "cannot read"),
    ],
)
def test_bad_input_exits_2_with_a_message(args, message, capsys):
    base = ["--mv-target", "1", "--ev-target", "1"]
    if not any(a.startswith("--mv-target") for a in args):
        args = [*args, *base]
    if not any(a.startswith(("--mv-masked", "--ev-masked", "--params")) for a in args) and (
        message != "no masking functions"
    ):
        args = [*DIRECT, *args]
    assert main(["solve", *args]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err


def test_params_problems_exit_2(tmp_path, capsys):
    bad_json = tmp_path / "bad.json"
    bad_json.write_text("{not json")
    assert main(["solve", "--params", str(bad_json), "--mv-target", "1", "--ev-target", "1"]) == 2
    assert "not valid JSON" in capsys.readouterr().err
    off_schema = tmp_path / "off.json"
    off_schema.write_text(json.dumps({"schema_version": 1, "functions": []}))
    assert main(["solve", "--params", str(off_schema), "--mv-target", "1", "--ev-target", "1"]) == 2
    assert "software_version" in capsys.readouterr().err
    unfitted = _write_params(
        tmp_path,
        [
            masking_entry("MV180", "EV270", None, None, "insufficient_data"),
            masking_entry("EV270", "MV180", -6, 0.6),
        ],
    )
    code = main(
        ["solve", "--params", unfitted, "--mv", "MV180", "--mv-target", "1", "--ev-target", "1"]
    )
    assert code == 2
    assert "status 'insufficient_data', not fitted" in capsys.readouterr().err


def test_no_masking_entries_are_used_and_reported(tmp_path, capsys):
    params = _write_params(
        tmp_path,
        [
            masking_entry("MV180", "EV270", 1.39, 1.09),
            masking_entry("EV270", "MV180", 0.0, 0.0, "no_masking"),
        ],
    )
    code, out = run_json(capsys, "--params", params, "--mv-target", "12", "--ev-target", "5")
    assert code == 0 and out["d"] == 0.0
    assert len(out["notes"]) == 1 and "no masking was found" in out["notes"][0]
    # Only MV is masked: Table 4 case 3, m_i = m_p + a + b·e_p.
    assert out["case"] == [3] and out["mv_input_db"][0] == pytest.approx(12 + 1.39 + 1.09 * 5)
    main(["solve", "--params", params, "--mv-target", "12", "--ev-target", "5"])
    assert "note: EV270 masked by MV180: no masking was found" in capsys.readouterr().out


def test_cli_entry_point_prints_no_traceback():
    res = subprocess.run(
        [
            sys.executable,
            "-m",
            "masking_lab.commands.cli",
            "solve",
            "--mv-target",
            "1",
            "--ev-target",
            "1",
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert res.returncode == 2 and "no masking functions" in res.stderr
    assert "Traceback" not in res.stderr


def test_solve_one_ulp_below_bd_1_is_ill_conditioned_and_exits_1(capsys):
    # Was (issue 21): "unique" answers of ~1e17 dB SL, 52 dB off through the model, exit 0.
    args = ["solve", "--mv-masked-by-ev", "1.39,1.0", "--ev-masked-by-mv=-6.22,0.9999999999999999"]
    assert main([*args, "--mv-target", "12", "--ev-target", "0,5,10", "--json"]) == 1
    doc = json.loads(capsys.readouterr().out)
    assert doc["status"] == ["none"] * 3 and doc["mv_input_db"] == [None] * 3
    assert all(r.startswith("ill-conditioned") for r in doc["reason"])
    assert doc["one_minus_bd"] == 2.0**-53 and doc["reproduce_tol_db"] == 1e-6
    assert main([*args, "--mv-target", "12", "--ev-target", "5"]) == 1
    text = capsys.readouterr().out
    assert "b·d = 1 − 1.11e-16" in text and "ill-conditioned" in text
