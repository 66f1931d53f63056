"""`masking-lab demo`: the whole system end to end on its embedded defaults."""

from __future__ import annotations

import json
import re
from dataclasses import replace

import numpy as np
import pytest

from masking_lab.commands.cli import main
from masking_lab.core.errors import MaskingLabError
from masking_lab.core.masking import MaskingFunction
from masking_lab.demo import sample_truth
from masking_lab.formats.masking_params import read_masking_params
from masking_lab.formats.schemas import schema_errors
from masking_lab.formats.session_log import read_log
from masking_lab.simulation.observer import load_ground_truth


@pytest.fixture(scope="module")
def demo_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo")
    code = main(["demo", "--out", str(out), "--jobs", "2", "--n-boot", "400"])
    return out, code


def test_demo_runs_every_stage_through_the_c_firmware(demo_run, capsys):
    out, code = demo_run
    assert code == 0
    logs = sorted((out / "data").rglob("*.jsonl"))
    assert len(logs) == 30  # 10 participants x 3 protocols
    statuses = [o["status"] for p in logs for o in read_log(p).records if o["record"] == "set_end"]
    assert len(statuses) == 340 and set(statuses) == {"completed"}
    for path in logs[:3]:
        log = read_log(path)
        assert (log.header["device"]["backend"], log.header["device"]["model"]) == (
            "serial",
            "ML-FW-2CH",
        )
        assert log.header["clock"] == "virtual"
        assert all(not schema_errors(r, "session_log") for r in [log.header, *log.records])
    for name in ("thresholds.csv", "anova.csv", "masking_params.json", "report.txt"):
        assert (out / "analysis" / name).is_file(), name
    for name in ("points.csv", "summary.json", "figure4.png"):
        assert (out / "render" / name).is_file(), name


def test_fitted_parameters_recover_the_ground_truth(demo_run):
    out, _ = demo_run
    params = read_masking_params(out / "analysis" / "masking_params.json")
    truth = load_ground_truth()
    people = [f"S{i:02d}" for i in range(1, 11)]
    fitted = [f for f in params["functions"] if f["status"] == "fitted"]
    assert {(f["target"], f["masker"]) for f in fitted} >= {
        ("EV270", "MV270"),
        ("MV120", "EV270"),
        ("MV180", "EV270"),
    }
    for f in fitted:
        pairs = [tuple(p.split("|")) for p in f["pooled_pairs"]]
        lo, hi = f["fitted_range_db_sl"]
        a, b = sample_truth(truth, people, pairs, np.arange(lo, hi + 1e-9, 5.0))
        # Within 3 standard errors: six correlated 95 % intervals all cover the truth only about
        # 3 times in 4, so a per-interval check would pass or fail with the seed.
        assert abs(f["intercept_db"] - a) <= 3 * f["intercept_se_db"], f
        assert abs(f["slope"] - b) <= 3 * f["slope_se"], f


def test_summary_puts_fits_beside_truth(demo_run):
    out, _ = demo_run
    summary = json.loads((out / "render" / "summary.json").read_text())
    assert summary["scene"] == "bump_rough"
    assert summary["masking"]["mv"].startswith("MV")
    # The demo's scene is mapped into the rig's gamut: every input within the ratings.
    gm = summary["gamut_mapping"]
    assert gm["strategy"] == "clip" and gm["as_played"]["share_within_ratings"] == 1.0
    assert set(gm["strategies"]) == {"clip", "scale", "compress", "none"}


def test_demo_refuses_a_folder_with_logs(demo_run):
    out, _ = demo_run
    with pytest.raises(MaskingLabError, match="already holds session logs"):
        from masking_lab.demo import DemoSettings, run_demo

        run_demo(DemoSettings(out=out, participants=2))


def test_sample_truth_is_the_nominal_ramp_without_individual_differences():
    truth = replace(load_ground_truth(), participant_sd_db=0.0, shift_sd_db=0.0)
    fn: MaskingFunction = truth.masking_function("MV180", "EV270")
    a, b = sample_truth(truth, ["S01", "S02"], [("MV180", "EV270")], [5, 10, 15, 20, 25])
    assert a == pytest.approx(fn.intercept_db, abs=1e-6)
    assert b == pytest.approx(fn.slope, abs=1e-6)


def test_sample_truth_of_a_pool_averages_the_pairs():
    truth = replace(load_ground_truth(), participant_sd_db=0.0, shift_sd_db=0.0)
    x = [15.0, 20.0, 25.0]  # above both knees: the mean of two lines is a line
    a, b = sample_truth(truth, ["S01"], [("EV270", "MV120"), ("EV270", "MV180")], x)
    f1, f2 = truth.masking_function("EV270", "MV120"), truth.masking_function("EV270", "MV180")
    assert b == pytest.approx((f1.slope + f2.slope) / 2, abs=1e-9)
    assert a == pytest.approx((f1.intercept_db + f2.intercept_db) / 2, abs=1e-9)


def test_too_few_participants_is_a_clear_error(tmp_path, capsys):
    assert main(["demo", "--out", str(tmp_path / "d"), "--participants", "1"]) == 2
    assert re.search(r"at least 2 participants", capsys.readouterr().err)


@pytest.mark.parametrize("jobs", ["0", "-3"])
def test_no_worker_process_is_a_clear_error(tmp_path, capsys, jobs):
    # (both ran the demo with one process, silently)
    assert main(["demo", "--out", str(tmp_path / "d"), "--jobs", jobs]) == 2
    assert re.search(rf"--jobs {jobs}: use at least 1 worker process", capsys.readouterr().err)
    assert not (tmp_path / "d").exists()
