"""The one-pass continuity check agrees with the full one: it never passes a damaged log.

``SessionLog.continuity_problems`` answers intact typed logs in one tight pass and sends
anything unusual to the full check (which names the problem and its line). Here real logs of
a simulated study are damaged at random (records deleted, repeated, swapped, a set's id or a
trial index changed); for every damaged log, the fast answer "intact" must agree with the full
check finding nothing.
"""

from __future__ import annotations

import random

import msgspec
import pytest

from masking_lab.analysis.log_reading import fast_parse
from masking_lab.formats.log_integrity import problems_of_keys, record_key
from masking_lab.formats.log_records import view_keys
from masking_lab.formats.typed_layout import typed_structure_intact
from masking_lab.simulation.synthetic_logs import simulate_study


@pytest.fixture(scope="module")
def logs(tmp_path_factory):
    folder = tmp_path_factory.mktemp("study")
    return [fast_parse(p.read_bytes(), p) for p in simulate_study(folder, n_participants=2)]


def _full_check(log, records):
    keys = [(log.header_line, *record_key(log.header))]
    keys += view_keys(list(range(2, len(records) + 2)), records)
    return problems_of_keys(keys, counter_intact=True)


def _damage(records, rng):
    recs = list(records)
    i, j = sorted(rng.sample(range(len(recs)), 2))
    how = rng.choice(["delete", "repeat", "swap", "set_id", "index"])
    if how == "delete":
        del recs[i]
    elif how == "repeat":
        recs.insert(j, recs[i])
    elif how == "swap":
        recs[i], recs[j] = recs[j], recs[i]
    elif how == "set_id" and hasattr(recs[i], "set_id"):
        recs[i] = msgspec.structs.replace(recs[i], set_id="other")
    elif how == "index" and hasattr(recs[i], "trial_index"):
        recs[i] = msgspec.structs.replace(recs[i], trial_index=recs[i].trial_index + 1)
    return recs


def test_intact_logs_take_the_fast_path_and_the_full_check_agrees(logs):
    for log in logs:
        assert typed_structure_intact(log.records)
        assert _full_check(log, log.records) == []
        assert log.continuity_problems() == []


def test_the_fast_path_never_passes_a_log_the_full_check_faults(logs):
    rng = random.Random(7)
    faulted = 0
    for _ in range(600):
        log = rng.choice(logs)
        damaged = _damage(log.records, rng)
        problems = _full_check(log, damaged)
        if typed_structure_intact(damaged):
            assert problems == [], problems
        faulted += bool(problems)
    assert faulted > 300  # the damage was real most of the time
