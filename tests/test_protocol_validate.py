"""`masking-lab validate`: the paper's protocols pass; malformed ones name the problem."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from masking_lab.commands.cli import main
from masking_lab.core.errors import ProtocolError
from masking_lab.formats.protocol import load_protocol, parse_protocol
from masking_lab.formats.resources import shipped

ROOT = Path(__file__).resolve().parents[1]
PAPER = sorted((ROOT / "protocols").glob("*.yaml"))

GOOD = """\
schema_version: 1
experiment: pilot
kind: masked
target: EV270
staircase:
  start_level_db: 20
  n_reversals: 11
  n_reversals_averaged: 8
sets:
  - {id: a, masker: MV120, masker_level_db_sl: 5}
  - {id: b, masker: MV120, masker_level_db_sl: 10}
"""


def test_paper_protocols_are_valid(capsys):
    assert {p.name for p in PAPER} >= {"baseline.yaml", "experiment1.yaml", "experiment2.yaml"}
    assert main(["validate", *map(str, PAPER)]) == 0
    out = capsys.readouterr().out
    # the summary names the procedure and every set's trial cap (issue 21 item 2)
    assert "experiment1 (masked, 15 sets; staircase, at most 150 trials per set)" in out
    assert "experiment2 (masked, 15 sets; staircase, at most 150 trials per set)" in out


def test_paper_experiments_match_table_1():
    e1 = load_protocol(ROOT / "protocols" / "experiment1.yaml")
    assert {s.target.name for s in e1.sets} == {"EV270"}
    assert sorted({(s.masker.name, s.masker_level_db_sl) for s in e1.sets}) == sorted(
        (m, float(lv)) for m in ("MV120", "MV180", "MV270") for lv in (5, 10, 15, 20, 25)
    )
    e2 = load_protocol(ROOT / "protocols" / "experiment2.yaml")
    assert {s.masker.name for s in e2.sets} == {"EV270"}
    assert {s.target.name for s in e2.sets} == {"MV120", "MV180", "MV270"}
    base = load_protocol(ROOT / "protocols" / "baseline.yaml")
    assert base.level_unit == "db_v" and e1.level_unit == "db_sl"
    assert {s.target.name for s in base.sets} == {"EV270", "MV120", "MV180", "MV270"}
    for p in (base, e1, e2):
        sc = p.sets[0].staircase
        assert (sc.n_up, sc.n_down, sc.n_reversals, sc.n_reversals_averaged) == (1, 3, 11, 8)
        assert p.timing.stimulus_s == 1.8


def test_set_order_is_a_seeded_permutation():
    p = parse_protocol(GOOD.encode(), "good.yaml")
    orders = {tuple(p.set_order(seed)) for seed in range(20)}
    assert all(sorted(o) == ["a", "b"] for o in orders) and len(orders) == 2
    assert p.set_order(7) == p.set_order(7)


# (replacement applied to GOOD, text expected in the message: key path and/or line)
MALFORMED = {
    "malformed_yaml": (("  - {id: a,", "  - {id: a,,"), ["line 10", "malformed YAML"]),
    "unknown_key": (("kind: masked", "kind: masked\ncolour: red"), ["colour (line 4)", "unknown"]),
    "typo_key_suggests": (
        ("  n_reversals: 11", "  n_reversal: 11"),
        ["did you mean 'n_reversals'"],
    ),
    "wrong_type": (
        ("start_level_db: 20", "start_level_db: loud"),
        ["staircase.start_level_db", "number"],
    ),
    "n_down_zero": (
        ("  n_reversals: 11", "  n_reversals: 11\n  n_down: 0"),
        ["staircase.n_down", "≥ 1"],
    ),
    "negative_step": (
        ("  n_reversals: 11", "  n_reversals: 11\n  step_sizes_db: [2, -1]"),
        ["staircase.step_sizes_db[1]", "> 0"],
    ),
    "more_averaged_than_run": (
        ("n_reversals_averaged: 8", "n_reversals_averaged: 12"),
        ["n_reversals_averaged", "cannot average more"],
    ),
    "masker_above_device_limit": (
        ("masker_level_db_sl: 10", "masker_level_db_sl: 80"),
        ["sets[1].masker_level_db_sl (line 11)", "device limit"],
    ),
    "duplicate_set": (
        (
            "{id: b, masker: MV120, masker_level_db_sl: 10}",
            "{id: b, masker: MV120, masker_level_db_sl: 5}",
        ),
        ["sets[1] (line 11)", "duplicate set"],
    ),
    "duplicate_id": (("{id: b,", "{id: a,"), ["sets[1].id", "duplicate set id 'a'"]),
    "duplicate_key": (
        ("kind: masked", "kind: masked\nkind: baseline"),
        ["kind (line 4)", "appears twice"],
    ),
    "bad_stimulus_name": (
        ("target: EV270", "target: EV-270"),
        ["target (line 4)", "not a stimulus name"],
    ),
    "missing_required": (("experiment: pilot\n", ""), ["missing required key 'experiment'"]),
    "python_object_tag": (
        ("experiment: pilot", "experiment: !!python/object/apply:os.system [echo]"),
        ["not allowed"],
    ),
    "baseline_with_masker": (
        ("kind: masked", "kind: baseline"),
        ["baseline protocol measures unmasked"],
    ),
    "not_a_mapping": ((GOOD, "- just\n- a list\n"), ["YAML mapping"]),
}


@pytest.mark.parametrize("case", sorted(MALFORMED))
def test_malformed_protocol_is_named(case, tmp_path, capsys):
    (old, new), expected = MALFORMED[case]
    assert old in GOOD, f"test setup: {old!r} not in template"
    path = tmp_path / f"{case}.yaml"
    path.write_text(GOOD.replace(old, new, 1), encoding="utf-8")
    rig = tmp_path / "rig.yaml"
    # A whole rig config (validate checks it in full): the reference rig with MV at 40 dB SL.
    reference = shipped("protocols", "devices/default.yaml").read_text(encoding="utf-8")
    head, mv = reference.split("  MV:\n", 1)
    rig.write_text(head + "  MV:\n" + mv.replace("max_level_db_sl: 30", "max_level_db_sl: 40", 1))
    assert main(["validate", "--device-config", str(rig), str(path)]) == 1
    err = capsys.readouterr().err
    assert str(path) in err
    for text in expected:
        assert text in err, f"{text!r} missing from: {err}"


def test_one_bad_file_among_good_ones_fails_the_run(tmp_path, capsys):
    bad = tmp_path / "bad.yaml"
    bad.write_text(GOOD.replace("n_reversals_averaged: 8", "n_reversals_averaged: 0"))
    assert main(["validate", *map(str, PAPER), str(bad)]) == 1
    captured = capsys.readouterr()
    assert captured.out.count("ok ") == len(PAPER)
    assert "bad.yaml" in captured.err


def test_a_folder_is_refused_with_what_to_give_instead(capsys):
    assert main(["validate", str(shipped("protocols", "experiment1.yaml").parent)]) == 1
    out = capsys.readouterr()
    text = out.out + out.err
    assert "INVALID" in text and "give the files one by one" in text


def test_unreadable_file(tmp_path):
    with pytest.raises(ProtocolError, match="cannot read"):
        load_protocol(tmp_path / "missing.yaml")


def test_yaml_anchors_and_merge_keys_are_allowed(tmp_path):
    text = GOOD.replace(
        "sets:\n", "x-common: &m {masker: MV120}\nsets:\n"
    )  # unknown top-level key must still be refused...
    with pytest.raises(ProtocolError, match="unknown key 'x-common'"):
        parse_protocol(text.encode(), "anchors.yaml")
    merged = GOOD.replace(
        "  - {id: a, masker: MV120, masker_level_db_sl: 5}",
        "  - &first {id: a, masker: MV120, masker_level_db_sl: 5}",
    ).replace(
        "  - {id: b, masker: MV120, masker_level_db_sl: 10}",
        "  - {<<: *first, id: b, masker_level_db_sl: 10}",
    )
    p = parse_protocol(merged.encode(), "merged.yaml")
    assert [s.masker.name for s in p.sets] == ["MV120", "MV120"]


SCRIPT = shutil.which("masking-lab", path=str(Path(sys.executable).parent))


@pytest.mark.skipif(SCRIPT is None, reason="console script not installed next to the interpreter")
def test_console_script_exit_codes(tmp_path):
    ok = subprocess.run([SCRIPT, "validate", *map(str, PAPER)], capture_output=True, text=True)
    assert ok.returncode == 0, ok.stderr
    bad = tmp_path / "bad.yaml"
    bad.write_text("schema_version: 1\n")
    res = subprocess.run(
        [sys.executable, "-m", "masking_lab.commands.cli", "validate", str(bad)],
        capture_output=True,
        text=True,
    )
    assert res.returncode == 1 and "missing required key" in res.stderr
