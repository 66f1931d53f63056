"""Campaign findings fixed after the merge (issue 21): a resumed log whose trial has no usable
'correct', and a header whose simulated observer lost its truth, are clean errors."""

from __future__ import annotations

import pytest

from masking_lab.core.clock import VirtualClock
from masking_lab.core.errors import LogError
from masking_lab.session.opening import ResponderContext
from masking_lab.session.procedure_records import settings_from_record
from masking_lab.session.threshold_plan import check_trials


class _Rec:
    def __init__(self, start, trials):
        self.start, self.trials = start, trials


@pytest.mark.parametrize("correct", [None, "yes", 1])
def test_a_trial_without_a_true_or_false_answer_cannot_be_resumed(tmp_path, correct):
    from masking_lab.formats.protocol import load_protocol
    from masking_lab.formats.resources import shipped

    protocol = load_protocol(shipped("protocols", "baseline.yaml"))
    spec = protocol.sets[0]
    level = settings_from_record({}, spec).start().next_level()  # the logged level is right
    key = "level_db_sl" if protocol.level_unit == "db_sl" else "level_db_v"
    trial = {"trial_index": 0, key: level}
    if correct is not None:
        trial["correct"] = correct
    with pytest.raises(LogError, match="'correct' is"):
        check_trials(tmp_path / "log.jsonl", protocol, {spec.id: _Rec({}, [trial])})


@pytest.mark.parametrize(
    "observer",
    [
        {"population_seed": 3},
        {"truth": "x", "population_seed": 3},
        {"truth": {}, "population_seed": "3"},
    ],
)
def test_a_simulated_observer_without_its_truth_is_a_clean_error(observer):
    context = ResponderContext("P01", 1, VirtualClock(), simulated_observer=observer)
    with pytest.raises(LogError, match="simulated_observer lacks"):
        context.simulated_truth()
