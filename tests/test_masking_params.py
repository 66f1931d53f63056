"""masking_params.json: schema, round trip, the load_masking_params API other tools use."""

from __future__ import annotations

import copy
import json

import pytest

from masking_lab.core.errors import AnalysisError, ProtocolError
from masking_lab.formats.masking_params import (
    MaskingParamsError,
    load_masking_params,
    masking_params_json,
    read_masking_params,
    write_masking_params,
)


def _entry(target="EV270", masker="MV120", **kw):
    e = {
        "target": target,
        "masker": masker,
        "masker_frequencies_hz": [120, 180],
        "intercept_db": -6.2628,
        "slope": 0.66526,
        "intercept_se_db": 0.548,
        "slope_se": 0.0298,
        "intercept_ci_db": [-7.5, -5.0],
        "slope_ci": [0.60, 0.73],
        "fitted_range_db_sl": [5, 25],
        "knee_db_sl": 9.414,
        "adj_r2": 0.986,
        "n_points": 10,
        "pooled_pairs": ["EV270|MV120", "EV270|MV180"],
        "status": "fitted",
        "message": None,
    }
    e.update(kw)
    return e


def _doc(*functions):
    return {
        "schema_version": 1,
        "software_version": "0.1.0",
        "created_utc": "2024-05-01T12:00:00Z",
        "provenance": {
            "source": "fit",
            "inputs": [{"path": "shifts.csv", "sha256": "0" * 64}],
            "settings": {"pooling": "paired"},
        },
        "functions": list(functions)
        or [
            _entry(),
            _entry(masker="MV180"),
            _entry(
                target="MV120",
                masker="EV270",
                masker_frequencies_hz=[120],
                intercept_db=None,
                slope=None,
                pooled_pairs=["MV120|EV270"],
                status="insufficient_data",
                message="a ramp needs shifts at two or more masker levels",
            ),
        ],
    }


def test_round_trip_and_keyed_entries(tmp_path):
    path = write_masking_params(tmp_path / "masking_params.json", _doc())
    entries = load_masking_params(path)
    assert set(entries) == {("EV270", "MV120"), ("EV270", "MV180"), ("MV120", "EV270")}
    ev = entries[("EV270", "MV120")]
    assert ev.usable and ev.pooled_pairs == ("EV270|MV120", "EV270|MV180")
    assert ev.masker_frequencies_hz == (120.0, 180.0)
    assert ev.fitted_range_db_sl == (5.0, 25.0)
    fn = ev.masking_function()
    assert float(fn.shift_db(25.0)) == pytest.approx(-6.2628 + 0.66526 * 25)
    mv = entries[("MV120", "EV270")]
    assert not mv.usable
    with pytest.raises(AnalysisError, match="insufficient_data"):
        mv.masking_function()
    assert read_masking_params(path) == json.loads(path.read_text())


def test_extra_keys_are_kept():
    doc = _doc(_entry(experiment="experiment1", uncertainty="bootstrap", ci_level=0.95))
    text = masking_params_json(doc)
    assert '"experiment": "experiment1"' in text


def test_writing_is_deterministic_and_rounds_floats(tmp_path):
    doc = _doc(_entry(intercept_db=-6.262800000000001, slope=0.1 + 0.2))
    a = masking_params_json(doc)
    assert a == masking_params_json(copy.deepcopy(doc))
    assert '"intercept_db": -6.2628,' in a and '"slope": 0.3,' in a
    assert a.endswith("}\n")


def test_non_finite_numbers_are_refused():
    with pytest.raises(MaskingParamsError, match=r"adj_r2: must be a finite number"):
        masking_params_json(_doc(_entry(adj_r2=float("nan"))))


@pytest.mark.parametrize(
    ("mutate", "where"),
    [
        (lambda d: d["functions"][0].pop("slope"), "functions[0]"),
        (lambda d: d["functions"][0].update(target="XX270"), "functions[0].target"),
        (lambda d: d["functions"][0].update(slope=-0.1), "functions[0].slope"),
        (lambda d: d["functions"][0].update(status="maybe"), "functions[0].status"),
        (lambda d: d["functions"][0].update(intercept_db=None), "functions[0].intercept_db"),
        (lambda d: d["functions"][2].update(slope=0.5), "functions[2].slope"),
        (lambda d: d["provenance"].update(source="excel"), "provenance.source"),
        (lambda d: d.update(created_utc="yesterday"), "created_utc"),
        (lambda d: d["functions"].append(_entry()), "functions[3]"),
        (lambda d: d["functions"][0].update(pooled_pairs=["EV270|MV180"]), "pooled_pairs"),
    ],
)
def test_invalid_documents_name_the_key(tmp_path, mutate, where):
    doc = _doc()
    mutate(doc)
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(doc), encoding="utf-8")
    with pytest.raises(MaskingParamsError) as info:
        load_masking_params(path)
    assert isinstance(info.value, ProtocolError)
    assert where in str(info.value) and str(path) in str(info.value)
    with pytest.raises(MaskingParamsError):
        write_masking_params(tmp_path / "out.json", doc)
    assert not (tmp_path / "out.json").exists()


def test_unreadable_and_truncated_files(tmp_path):
    with pytest.raises(MaskingParamsError, match="cannot read"):
        load_masking_params(tmp_path / "missing.json")
    path = tmp_path / "cut.json"
    path.write_text(masking_params_json(_doc())[:200], encoding="utf-8")
    with pytest.raises(MaskingParamsError, match=r"not valid JSON.*truncated"):
        load_masking_params(path)
