"""formats.schemas: arrays of flat string records are checked by a plain loop, with exactly
jsonschema's verdict (the errors of a document are the same with and without the shortcut)."""

from __future__ import annotations

import copy

import pytest

import masking_lab.formats.schemas as schemas
from masking_lab.formats.masking_params import MaskingParamsError, validate_masking_params

SHA = "0123456789abcdef" * 4


def _function(masker: str) -> dict:
    return {
        "target": "EV270", "masker": masker, "masker_frequencies_hz": [120],
        "intercept_db": -6.26, "slope": 0.665, "intercept_se_db": 0.548, "slope_se": 0.0298,
        "intercept_ci_db": [-7.5, -5.0], "slope_ci": [0.6, 0.73], "fitted_range_db_sl": [5, 25],
        "knee_db_sl": 9.41, "adj_r2": 0.986, "n_points": 10, "pooled_pairs": [f"EV270|{masker}"],
        "status": "fitted", "message": None,
    }  # fmt: skip


def _study_doc(n: int = 200) -> dict:
    doc = {
        "schema_version": 1,
        "software_version": "0.1.0",
        "created_utc": "2024-05-01T12:00:00Z",
        "provenance": {"source": "analyze", "settings": {}},
        "functions": [_function("MV120"), _function("MV180")],
    }
    doc["provenance"]["inputs"] = [
        {"path": f"P{k:04d}/P{k:04d}_experiment1.jsonl", "sha256": SHA} for k in range(n)
    ]
    doc["provenance"]["skipped_inputs"] = [{"path": "old/x.jsonl", "reason": "a user-test log"}]
    return doc


def _slow_errors(doc: dict, name: str = "masking_params") -> list[tuple[str, str, str]]:
    """Every error as jsonschema alone reports it (the shortcut off)."""
    errors = sorted(
        schemas._validator(name).iter_errors(doc), key=lambda e: [str(p) for p in e.absolute_path]
    )
    return [(schemas.key_path(e), e.validator, e.message) for e in errors]


def _errors(doc: dict, name: str = "masking_params") -> list[tuple[str, str, str]]:
    return [(schemas.key_path(e), e.validator, e.message) for e in schemas.schema_errors(doc, name)]


def test_the_shortcut_covers_the_provenance_lists_only():
    paths = [p for p, _ in schemas._record_arrays("masking_params")]
    assert paths == [("provenance", "inputs"), ("provenance", "skipped_inputs")]
    # Nothing else qualifies: a list of numbers, a $ref, bounds, branches.
    for name in ("protocol", "scene", "calibration", "usertest", "ground_truth"):
        assert schemas._record_arrays(name) == ()


def test_a_valid_study_document_has_no_error_and_is_not_changed():
    doc = _study_doc()
    before = copy.deepcopy(doc)
    assert _errors(doc) == [] == _slow_errors(doc)
    validate_masking_params(doc)
    assert doc == before  # the shortcut validates a copy along the emptied path
    checked = schemas._records_checked(doc, schemas._record_arrays("masking_params"))
    assert checked["provenance"]["inputs"] == [] == checked["provenance"]["skipped_inputs"]
    assert checked["functions"] is doc["functions"]


BAD_ITEMS = [
    ({"path": "a.jsonl"}, "required"),
    ({"sha256": SHA}, "required"),
    ({"path": "a.jsonl", "sha256": SHA, "size": 3}, "additionalProperties"),
    ({"path": 7, "sha256": SHA}, "type"),
    ({"path": "a.jsonl", "sha256": SHA.upper()}, "pattern"),
    ({"path": "a.jsonl", "sha256": SHA[:-1]}, "pattern"),
    ({"path": "a.jsonl", "sha256": None}, "type"),
    (["a.jsonl", SHA], "type"),
    ("a.jsonl", "type"),
]


@pytest.mark.parametrize(("item", "validator"), BAD_ITEMS)
@pytest.mark.parametrize("at", [0, 117, 199])
def test_a_bad_input_anywhere_is_reported_as_jsonschema_reports_it(item, validator, at):
    doc = _study_doc()
    doc["provenance"]["inputs"][at] = item
    errors = _errors(doc)
    assert errors == _slow_errors(doc)
    assert [e[1] for e in errors] == [validator]
    with pytest.raises(MaskingParamsError, match=rf"provenance\.inputs\[{at}\]"):
        validate_masking_params(doc)


def test_what_jsonschema_accepts_the_shortcut_accepts():
    doc = _study_doc()
    # re.search: "$" also matches before a final newline, as in jsonschema's pattern check
    doc["provenance"]["inputs"][3]["sha256"] = SHA + "\n"
    # skipped_inputs is an open record: other keys are allowed
    doc["provenance"]["skipped_inputs"][0]["note"] = 5
    assert _errors(doc) == [] == _slow_errors(doc)


def test_other_problems_are_unchanged_beside_emptied_lists():
    doc = _study_doc()
    doc["provenance"]["source"] = "excel"
    doc["provenance"]["extra"] = 1
    doc["functions"][0]["slope"] = -1.0
    doc["provenance"]["skipped_inputs"][0].pop("reason")
    errors = _errors(doc)
    assert errors == _slow_errors(doc)
    assert {e[0] for e in errors} >= {
        "provenance",
        "provenance.source",
        "functions[0].slope",
        "provenance.skipped_inputs[0]",
    }


@pytest.mark.parametrize(
    "value",
    [None, {"path": "a"}, "inputs", [], [[]]],
    ids=["null", "dict", "str", "empty", "nested"],
)
def test_inputs_that_are_not_a_list_of_records(value):
    doc = _study_doc()
    doc["provenance"]["inputs"] = value
    assert _errors(doc) == _slow_errors(doc)
    doc["provenance"] = "not an object"
    assert _errors(doc) == _slow_errors(doc)


def test_unusual_item_schemas_are_left_to_jsonschema():
    string = {"type": "string"}
    plain = {"type": "array", "items": {"type": "object", "properties": {"a": string}}}
    assert schemas._record_check(plain) is not None
    for changed in (
        {**plain, "minItems": 1},
        {**plain, "items": {**plain["items"], "properties": {"a": {"type": "number"}}}},
        {**plain, "items": {**plain["items"], "properties": {"a": {**string, "format": "date"}}}},
        {**plain, "items": {**plain["items"], "properties": {"a": {"$ref": "#/$defs/x"}}}},
        {**plain, "items": {**plain["items"], "additionalProperties": string}},
        {**plain, "items": {**plain["items"], "type": ["object", "null"]}},
        {**plain, "items": {**plain["items"], "oneOf": []}},
    ):
        assert schemas._record_check(changed) is None
