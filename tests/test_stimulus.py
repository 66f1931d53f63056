"""Stimulus names."""

from __future__ import annotations

import pytest

from masking_lab.core.stimulus import Stimulus, is_stimulus_name, parse_stimulus


@pytest.mark.parametrize("name", ["EV270", "MV120", "MV180", "MV120am40", "MV62.5"])
def test_names_round_trip(name):
    assert parse_stimulus(name).name == name


def test_parsed_fields():
    s = parse_stimulus("MV120am40")
    assert (s.channel, s.carrier_hz, s.envelope_hz) == ("MV", 120.0, 40.0)


@pytest.mark.parametrize("bad", ["ev270", "XV100", "MV", "MV-120", "EV270am", ""])
def test_bad_names_explain_the_format(bad):
    assert not is_stimulus_name(bad)
    with pytest.raises(ValueError, match=r"<EV\|MV><carrier Hz>"):
        parse_stimulus(bad)


def test_invalid_fields_are_refused():
    with pytest.raises(ValueError):
        Stimulus("MV", 0)
    with pytest.raises(ValueError):
        Stimulus("XX", 100)  # type: ignore[arg-type]
