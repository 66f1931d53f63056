"""Every file kind reports its schema problems the same way (formats.schemas.first_problem)."""

from __future__ import annotations

import pytest

from masking_lab.core.errors import MaskingLabError
from masking_lab.formats.calibration import parse_calibration
from masking_lab.formats.masking_params import validate_masking_params
from masking_lab.formats.schemas import first_problem
from masking_lab.rendering.scene import parse_scene
from masking_lab.simulation.observer import ground_truth_from_dict
from masking_lab.usertest.design import parse_usertest

PARSERS = {
    "scene": lambda d, lines: parse_scene(d, "f.yaml", lines=lines),
    "usertest": lambda d, lines: parse_usertest(d, {}, source="f.yaml", lines=lines),
    "masking_params": lambda d, lines: validate_masking_params(d, "f.yaml", lines),
    "ground_truth": lambda d, lines: ground_truth_from_dict(d, "f.yaml", lines),
    "calibration": lambda d, lines: parse_calibration(d, "f.yaml", lines),
}


@pytest.mark.parametrize("kind", sorted(PARSERS))
def test_the_message_names_the_file_the_key_and_counts_the_rest(kind):
    with pytest.raises(MaskingLabError) as err:
        PARSERS[kind]({"schema_version": "one"}, {"schema_version": 4})
    text = str(err.value)
    assert text.startswith("f.yaml: ")
    where, what = first_problem({"schema_version": "one"}, kind, {"schema_version": 4})
    assert where in text and what in text
    assert "more problem(s)" in what


def test_first_problem_is_none_for_a_valid_document():
    cal = {"participant": "P1", "sources": [], "unmasked_al_db_v": {"EV270": -20.0}}
    assert first_problem(cal, "calibration") is None
    assert first_problem({**cal, "unmasked_al_db_v": {"EV270": "x"}}, "calibration") == (
        "unmasked_al_db_v.EV270",
        "must be of type number, got str 'x'",
    )
