"""``loads_record`` decodes a plain log line with msgspec and any other with json's number
hooks: every line gives the same value (types, key order, numbers), the same non-finite note
and the same error either way."""

from __future__ import annotations

import math

import pytest

from masking_lab.formats import log_bytes
from masking_lab.formats.log_bytes import BadNumber, loads_record
from masking_lab.simulation.synthetic_logs import simulate_study


class _Refuses:
    """A fast decoder that refuses everything: loads_record then takes the exact way."""

    def decode(self, text: str) -> None:
        raise ValueError("refused")


def _outcome(text: str) -> tuple[str, object]:
    try:
        value, non_finite = loads_record(text)
    except (ValueError, RecursionError) as exc:  # JSONDecodeError and BadNumber are ValueErrors
        return ("error", type(exc))
    return ("value", (repr(value), _types(value), non_finite))


def _types(v: object) -> object:
    if isinstance(v, dict):
        return [(k, _types(x)) for k, x in v.items()]
    if isinstance(v, list):
        return [_types(x) for x in v]
    return type(v).__name__


def _both(text: str, monkeypatch: pytest.MonkeyPatch) -> tuple[object, object]:
    fast = _outcome(text)
    with monkeypatch.context() as m:
        m.setattr(log_bytes, "_FAST", _Refuses())
        exact = _outcome(text)
    return fast, exact


EDGE_LINES = [
    '{"record": "trial", "level_db_sl": 12.5, "n": 3, "ok": true, "x": null}',
    '{"a": 1, "a": 2, "b": -0.0, "c": -0, "d": 1E5, "e": 4.9e-324, "f": 0.1e-400}',
    '{"big": 123456789012345678901234567890, "neg": -18446744073709551617}',
    '{"ok64": ' + "9" * 64 + "}",
    '{"long": ' + "9" * 65 + "}",
    '{"longfloat": 0.' + "1" * 80 + "}",
    '{"nan": NaN}',
    '{"inf": -Infinity, "nan": NaN}',
    '{"over": 1e999}',
    '{"over": 2e308, "then": NaN}',
    '{"text": "NaN and Infinity in a note", "v": 1.5}',
    '{"esc": "\\u00e9\\ud83d\\ude00\\/", "raw": "é"}',
    '{"lone": "\\ud800"}',
    '{"lone": "' + "\ud800" + '"}',  # a lone surrogate in the text itself, not escaped
    '{"id": "' + "7" * 70 + '"}',  # a long run of digits in a string
    '{"id": "' + "\u0663" * 70 + '", "n": 1}',  # non-ASCII digits are not a long integer
    '{"n": ' + "1" * 64 + ', "s": "é' + "5" * 65 + '"}',
    '{"ctrl": "a\tb"}',
    "{} {}",
    "{} ",
    '{"a": 1,}',
    "[1, 2",
    "01",
    "",
    "[" * 300 + "]" * 300,
    "[" * 2000 + "]" * 2000,
]


@pytest.mark.parametrize("text", EDGE_LINES)
def test_an_edge_line_decodes_as_json_with_the_hooks_decodes_it(text, monkeypatch):
    fast, exact = _both(text, monkeypatch)
    assert fast == exact


def test_the_notes_and_refusals_are_kept():
    assert loads_record('{"a": NaN}')[1] == "NaN"
    assert math.isinf(loads_record('{"a": 1e999}')[0]["a"])
    with pytest.raises(BadNumber):
        loads_record('{"a": ' + "1" * 65 + "}")


def test_every_line_of_simulated_logs_decodes_the_same_both_ways(tmp_path, monkeypatch):
    paths = simulate_study(tmp_path, n_participants=1, seed=3, baseline_start_above_db=10.0)
    lines = [line for p in paths for line in p.read_text(encoding="utf-8").splitlines()]
    assert len(lines) > 100
    fast = [_outcome(line) for line in lines]
    with monkeypatch.context() as m:
        m.setattr(log_bytes, "_FAST", _Refuses())
        exact = [_outcome(line) for line in lines]
    assert fast == exact
    assert all(kind == "value" for kind, _ in fast)
