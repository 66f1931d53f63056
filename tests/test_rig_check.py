"""A participant's baseline and masked sessions must share one rig record (issue 10)."""

from __future__ import annotations

import copy
import json
import subprocess
import sys

from masking_lab.analysis.rig_check import RigUse, rig_changes
from masking_lab.device.config import default_device_config
from masking_lab.simulation.synthetic_logs import simulate_study


def _rig() -> dict:
    return default_device_config().rig_record()


def test_one_rig_described_by_copies_of_its_file_is_one_rig():
    a, b = _rig(), _rig()
    b["config"] = "/another/computer/rig.yaml"
    uses = [RigUse("S01", "base.jsonl", "baseline", a), RigUse("S01", "m1.jsonl", "I", b)]
    assert rig_changes(uses) == []


def test_a_changed_amplifier_gain_between_baseline_and_masked_sessions_is_named():
    base = _rig()
    other = copy.deepcopy(base)
    other["channels"]["EV"]["amplifier"]["gain_db"] = 40.0
    other["name"] = "rig B"
    uses = [
        RigUse("S02", "m2.jsonl", "II", other),
        RigUse("S02", "base.jsonl", "baseline", base),
        RigUse("S01", "base.jsonl", "baseline", base),
        RigUse("S01", "m1.jsonl", "I", base),
    ]
    (warning,) = rig_changes(uses)
    assert warning.startswith("S02: sessions ran on 2 different rig records")
    assert "base.jsonl [baseline]" in warning and "rig B: m2.jsonl [II]" in warning
    assert "S01" not in warning


def test_logs_without_a_rig_record_are_not_compared():
    uses = [RigUse("S01", "old.jsonl", "baseline", None), RigUse("S01", "m.jsonl", "I", _rig())]
    assert rig_changes(uses) == []


def _set_rig(log, rig):
    lines = log.read_text(encoding="utf-8").splitlines(keepends=True)
    header = json.loads(lines[0])
    header["rig"] = rig
    lines[0] = json.dumps(header, separators=(",", ":")) + "\n"
    log.write_text("".join(lines), encoding="utf-8")
    return header


def test_analyze_warns_when_baseline_and_masked_sessions_ran_on_different_rigs(tmp_path):
    """Through the CLI: one participant's masked log names another EV amplifier gain."""
    data = tmp_path / "data"
    files = simulate_study(data, n_participants=3, seed=5)
    changed = copy.deepcopy(_rig())
    changed["channels"]["EV"]["amplifier"]["gain_db"] = 46.0  # the reference rig: not stated
    for log in files:
        header = json.loads(log.read_text(encoding="utf-8").splitlines()[0])
        moved = header["participant"] == "P01" and header["protocol"]["experiment"] == "experiment1"
        _set_rig(log, changed if moved else _rig())
        if moved:
            masked = log

    out = tmp_path / "out"
    argv = [
        sys.executable,
        "-m",
        "masking_lab.commands.cli",
        "analyze",
        str(data),
        "--out",
        str(out),
    ]
    # The warning comes from reading the headers: no figures, trial tables or psychometric
    # bootstrap, and a short ramp bootstrap, as nothing here reads them.
    argv += ["--figures", "none", "--no-trial-tables", "--pf-boot", "0", "--n-boot", "200"]
    res = subprocess.run(
        argv,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert res.returncode == 0, res.stderr
    assert "P01: sessions ran on 2 different rig records" in res.stderr
    assert "P02: sessions ran" not in res.stderr and "P03: sessions ran" not in res.stderr
    report = (out / "report.txt").read_text(encoding="utf-8")
    assert "RIG CHANGED P01" in report and masked.name in report
    assert "P01: sessions ran on 2 different rig records" in (out / "report.html").read_text(
        encoding="utf-8"
    )
