"""`analyze` on functional-procedure logs: per-participant ramp posteriors recomputed from the
logged trials, group masking functions by partial pooling and by the paper's route, and
masking_params.json entries that name their procedure and estimate. Sessions run in virtual
time with the in-process simulated device and observers."""

from __future__ import annotations

import csv
import io
import json
import math

import pytest
from runner_support import write_calibration
from test_functional_session import CAL, functional_protocol

from masking_lab.analysis.batch import run_analyze
from masking_lab.analysis.functional import ramp_posterior, random_effects
from masking_lab.analysis.settings import AnalysisSettings
from masking_lab.formats.masking_params import read_masking_params
from masking_lab.formats.session_log import read_log
from masking_lab.session.runner import RunOptions, run_session


@pytest.fixture(scope="module")
def analysed(tmp_path_factory):
    folder = tmp_path_factory.mktemp("fa")
    protocol = functional_protocol(folder)
    logs = []
    for i, who in enumerate(("S01", "S02", "S03")):
        write_calibration(folder / "data", who, CAL)
        result = run_session(
            RunOptions(protocol, who, data_dir=folder / "data", seed=20 + i),
            stream=io.StringIO(),
        )
        assert result.exit_code == 0
        logs.append(result.log_path)
    out = folder / "out"
    summary = run_analyze(folder / "data", out, AnalysisSettings(figures="none"))
    return out, logs, summary


def _rows(path):
    with path.open(encoding="utf-8") as f:
        return list(csv.DictReader(f))


def test_each_participants_ramp_posterior_is_recomputed_from_the_logged_trials(analysed):
    out, logs, _ = analysed
    rows = _rows(out / "ramp_posteriors.csv")
    assert len(rows) == 3 * 2
    for path in logs:
        log = read_log(path)
        who = log.header["participant"]
        for rec in log.sets().values():
            row = next(
                r for r in rows if (r["participant"], r["masker"]) == (who, rec.start["masker"])
            )
            logged = rec.end["ramp"]
            assert float(row["intercept_db"]) == pytest.approx(logged["intercept_db"], rel=1e-5)
            assert float(row["slope_sd"]) == pytest.approx(logged["slope_sd"], rel=1e-5)
            assert float(row["intercept_ci_low_db"]) < float(row["intercept_db"])
            assert float(row["intercept_db"]) < float(row["intercept_ci_high_db"])
            assert row["procedure"] == "functional_ramp"


def test_group_ramps_pool_the_participants_by_random_effects_and_by_the_papers_route(analysed):
    out, _, _ = analysed
    posts = _rows(out / "ramp_posteriors.csv")
    groups = _rows(out / "group_ramps.csv")
    for masker in ("MV120", "MV180"):
        mine = [r for r in posts if r["masker"] == masker]
        re_row = next(
            g for g in groups if g["masker"] == masker and g["estimate"] == "random_effects"
        )
        mu, se, _tau = random_effects(
            [float(r["slope"]) for r in mine], [float(r["slope_sd"]) for r in mine]
        )
        assert float(re_row["slope"]) == pytest.approx(mu, rel=1e-5)
        assert float(re_row["slope_se"]) == pytest.approx(se, rel=1e-5)
        assert int(re_row["n_participants"]) == 3
        assert any(g["masker"] == masker and g["estimate"] == "paper_route" for g in groups)


def test_masking_params_names_the_procedure_and_estimate_of_each_function(analysed):
    out, _, _summary = analysed
    doc = read_masking_params(out / "masking_params.json")
    pairs = {(f["target"], f["masker"]): f for f in doc["functions"]}
    assert set(pairs) == {("EV270", "MV120"), ("EV270", "MV180")}
    for f in pairs.values():
        assert f["procedure"] == "functional_ramp" and f["estimate"] == "random_effects"
        assert all(math.isfinite(v) for v in (f["intercept_db"], f["slope"]))
    assert "\nnan" not in (out / "group_ramps.csv").read_text(encoding="utf-8").lower()
    assert json.loads((out / "masking_params.json").read_text(encoding="utf-8"))


def test_random_effects_widens_with_spread_beyond_the_sds():
    mu, se, tau = random_effects([0.0, 10.0], [1.0, 1.0])
    assert mu == pytest.approx(5.0) and tau > 6 and se > 4
    mu, se, tau = random_effects([1.0, 1.2], [1.0, 1.0])
    assert tau == 0.0 and se == pytest.approx(1 / math.sqrt(2))


def test_a_ramp_posterior_refuses_bad_trials_cleanly():
    from masking_lab.core.errors import ProcedureError

    proc = {"kind": "functional_ramp", "max_trials": 4}
    with pytest.raises(ProcedureError, match="finite"):
        ramp_posterior(proc, [5.0, math.nan], [0.0, 1.0], [True, False])
    with pytest.raises(ProcedureError, match="one masker level"):
        ramp_posterior(proc, [], [], [])


def test_ramp_intervals_of_a_stated_slope_and_lapse_carry_the_caveat(analysed):
    """The test protocol states one slope and lapse: its ramp intervals assume them, and analyze
    says so once, with the number of sets. Marginalised grids: no caveat."""
    from masking_lab.analysis.functional import ramp_posteriors_from_logs
    from masking_lab.procedures.model_note import STATED_MODEL

    _, paths, _ = analysed
    logs = [read_log(p) for p in paths]
    posteriors, problems = ramp_posteriors_from_logs(logs)
    caveats = [p for p in problems if STATED_MODEL in p]
    assert len(posteriors) == 6
    assert caveats == [caveats[0]] and caveats[0].startswith("ramp intervals of 6 set(s): ")
    assert "scale 1.5 dB, lapse 0.02" in caveats[0]
    for log in logs:
        for rec in log.sets().values():
            grids = {"scales_db": [0.75, 1.5, 3.0], "lapses": [0.0, 0.06, 0.12]}
            rec.start["procedure"] = {**rec.start["procedure"], **grids}
    posteriors, problems = ramp_posteriors_from_logs(logs)
    assert len(posteriors) == 6 and not [p for p in problems if STATED_MODEL in p]
