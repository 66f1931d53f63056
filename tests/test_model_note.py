"""A Bayesian procedure that states one slope or lapse: `validate` warns, `analyze` says what its
intervals assume (issue 18, deliverable 5; procedures/model_note.py)."""

from __future__ import annotations

import csv

import yaml

from masking_lab.commands.cli import main
from masking_lab.formats.protocol import load_protocol
from masking_lab.formats.resources import shipped
from masking_lab.procedures.functional import FunctionalRampSettings
from masking_lab.procedures.model_note import COVERAGE_DOC, STATED_MODEL, stated_model_note
from masking_lab.procedures.quest_plus import QuestPlusSettings
from masking_lab.procedures.registry import settings_record
from masking_lab.procedures.staircase import StaircaseSettings

QUEST = shipped("protocols", "experiment1_questplus.yaml")


def _known_slope_protocol(tmp_path, **procedure):
    """The shipped QUEST+ protocol with the slope and lapse stated as single values."""
    doc = yaml.safe_load(QUEST.read_text(encoding="utf-8"))
    doc["experiment"] = "experiment1_known"
    doc["procedure"].update({"scales_db": 1.5, "lapses": 0.02, **procedure})
    path = tmp_path / "known.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False), encoding="utf-8")
    return path


def test_the_note_names_what_is_fixed_and_only_for_fixed_models():
    known = stated_model_note(QuestPlusSettings(-20.0, 45.0, scales_db=1.5, lapses=0.02))
    assert known.startswith(STATED_MODEL) and "scale 1.5 dB, lapse 0.02" in known
    assert COVERAGE_DOC in known
    one_lapse = stated_model_note(QuestPlusSettings(-20.0, 45.0, lapses=0.02))
    assert "(lapse 0.02)" in one_lapse and "scale" not in one_lapse.split(";")[0]
    assert stated_model_note(QuestPlusSettings(-20.0, 45.0)) is None  # the defaults
    assert stated_model_note(FunctionalRampSettings()) is None  # marginalises both
    assert stated_model_note(FunctionalRampSettings(scales_db=(1.5,))).count("scale 1.5") == 1
    assert stated_model_note(StaircaseSettings(10.0)) is None
    record = settings_record(QuestPlusSettings(-20.0, 45.0, scales_db=2.0, lapses=0.0))
    assert "scale 2 dB, lapse 0" in stated_model_note(record)
    assert stated_model_note({"scales_db": "not numbers", "lapses": [0]}) is None


def test_validate_warns_about_a_stated_slope_and_not_about_the_shipped_protocol(tmp_path, capsys):
    known = _known_slope_protocol(tmp_path)
    assert main(["validate", str(known), str(QUEST)]) == 0
    out = capsys.readouterr().out.splitlines()
    warnings = [ln for ln in out if ln.startswith("warning")]
    assert len(warnings) == 1 and str(known) in warnings[0]
    assert STATED_MODEL in warnings[0] and "docs/procedures.md" in warnings[0]
    assert sum(ln.startswith("ok") for ln in out) == 2  # a warning, not a refusal


def test_analyze_prints_the_caveat_beside_the_intervals_of_stated_slope_sets(tmp_path):
    from masking_lab.simulation.synthetic_logs import simulate_study

    known = load_protocol(str(_known_slope_protocol(tmp_path, target_sd_db=2.0)))
    marginal = load_protocol(str(QUEST))
    simulate_study(tmp_path / "logs", n_participants=1, seed=3, protocols=("baseline", known))
    out = tmp_path / "out"
    assert main(["analyze", str(tmp_path / "logs"), "--out", str(out), "--quiet"]) == 0
    report = (out / "report.txt").read_text(encoding="utf-8")
    caveats = [ln for ln in report.splitlines() if STATED_MODEL in ln]
    assert len(caveats) == 1 and "intervals of 15 set(s)" in caveats[0]
    with open(out / "thresholds.csv", newline="", encoding="utf-8") as fh:
        rows = [r for r in csv.DictReader(fh) if r["experiment"] == "experiment1_known"]
    assert len(rows) == 15
    assert all(r["al_ci95_low_db"] and r["note"].startswith(STATED_MODEL) for r in rows)
    # The shipped protocol marginalises both: no caveat.
    assert all(stated_model_note(s.settings) is None for s in marginal.sets)


def test_the_shipped_bayesian_protocols_marginalise_slope_and_lapse_past_008():
    """Issue 18: both shipped Bayesian protocols and both settings' defaults put grids over the
    slope and the lapse, the lapse grid reaching past 0.08 (an observer on a grid's edge is
    undercovered), and neither gets the caveat."""
    functional = shipped("protocols", "experiment1_functional.yaml")
    for settings in (
        QuestPlusSettings(-20.0, 45.0),
        FunctionalRampSettings(),
        *(s.settings for s in load_protocol(str(QUEST)).sets),
        *(s.settings for s in load_protocol(str(functional)).sets),
    ):
        assert len(settings.scales_db) > 1 and max(settings.lapses) > 0.08, settings
        assert min(settings.scales_db) <= 0.75 and max(settings.scales_db) >= 3.0
        assert stated_model_note(settings) is None
