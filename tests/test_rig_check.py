"""A participant's baseline and masked sessions must share one rig record (issue 10)."""

from __future__ import annotations

import copy

from masking_lab.analysis.rig_check import RigUse, rig_changes
from masking_lab.device.config import default_device_config


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
