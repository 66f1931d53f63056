"""``validate --data --participant`` checks a protocol for the participant ``run`` will use
(issue 21.2: a protocol masked by MV90.5 validated, then ``run`` refused it for want of an
unmasked AL); without them a masked protocol's summary names the ALs a run needs."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from masking_lab.commands.cli import main

PROTOCOL = """schema_version: 1
experiment: pilot
kind: masked
target: EV270
staircase: {start_level_db: 10, step_sizes_db: [4, 2], n_reversals: 3, n_reversals_averaged: 2,
            max_trials: 30}
timing: {stimulus_s: 0.2, gap_s: 0.1, lead_in_s: 0.1, inter_trial_s: 0.1}
order: {randomize: false}
sets:
  - {id: a, masker: MASKER, masker_level_db_sl: 5}
"""


def _files(tmp_path: Path, masker: str) -> tuple[Path, Path]:
    protocol = tmp_path / "p.yaml"
    protocol.write_text(PROTOCOL.replace("MASKER", masker), encoding="utf-8")
    data = tmp_path / "data"
    (data / "S01").mkdir(parents=True)
    cal = {
        "participant": "S01",
        "unmasked_al_db_v": {"EV270": -18.0, "MV120": -26.0},
        "sources": ["by hand"],
    }
    (data / "S01" / "calibration.json").write_text(json.dumps(cal), encoding="utf-8")
    return protocol, data


def _run(protocol: Path, data: Path) -> int:
    return main(
        [
            *("run", str(protocol), "--participant", "S01", "--data", str(data)),
            *("--device", "sim", "--responder", "sim", "--seed", "1", "--no-progress"),
        ]
    )


def test_without_participant_the_summary_names_the_als_a_run_needs(tmp_path, capsys):
    protocol, _ = _files(tmp_path, "MV90.5")
    assert main(["validate", str(protocol)]) == 0
    assert "a run needs the participant's unmasked ALs of EV270, MV90.5" in capsys.readouterr().out


def test_with_participant_a_missing_al_is_refused_as_run_refuses_it(tmp_path, capsys):
    protocol, data = _files(tmp_path, "MV90.5")
    argv = ["validate", str(protocol), "--data", str(data), "--participant", "S01"]
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert str(protocol) in err and "no unmasked AL for MV90.5" in err
    assert "Traceback" not in err
    assert _run(protocol, data) == 2  # and run agrees


def test_with_participant_what_validates_runs(tmp_path, capsys):
    protocol, data = _files(tmp_path, "MV120")
    argv = ["validate", str(protocol), "--data", str(data), "--participant", "S01"]
    assert main(argv) == 0
    assert "runs for S01 (calibrated: EV270, MV120)" in capsys.readouterr().out
    assert _run(protocol, data) == 0


def test_a_broken_calibration_is_refused_naming_both_files(tmp_path, capsys):
    protocol, data = _files(tmp_path, "MV120")
    (data / "S01" / "calibration.json").write_text('{"participant": 3}', encoding="utf-8")
    argv = ["validate", str(protocol), "--data", str(data), "--participant", "S01"]
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert str(protocol) in err and "calibration.json" in err


@pytest.mark.parametrize("half", [["--data", "x"], ["--participant", "S01"]])
def test_data_and_participant_go_together(tmp_path, capsys, half):
    protocol, _ = _files(tmp_path, "MV120")
    assert main(["validate", str(protocol), *half]) == 2
    assert "go together" in capsys.readouterr().err


def test_resume_of_a_log_whose_protocol_path_the_os_cannot_look_up(tmp_path, capsys):
    # Campaign seed 62: a header's protocol path of thousands of characters ended resume in an
    # OSError (ENAMETOOLONG) traceback; the stored protocol is what resume runs anyway.
    protocol, data = _files(tmp_path, "MV120")
    assert _run(protocol, data) == 0
    log = next((data / "S01").glob("*.jsonl"))
    lines = log.read_text(encoding="utf-8").splitlines()
    header = json.loads(lines[0])
    header["protocol"]["path"] = "}" * 5000 + "e.yaml"
    # Cut to the first records, so resume has a session to continue.
    log.write_text("\n".join([json.dumps(header), *lines[1:4]]) + "\n", encoding="utf-8")
    code = main(["resume", str(log), "--no-progress"])
    err = capsys.readouterr().err
    assert "Traceback" not in err and "File name too long" not in err
    assert code in (0, 1, 2)
