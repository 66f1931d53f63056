"""`masking-lab plan --scene`: the masking functions a scene needs and the masker ranges it plays,
the protocols that measure what is missing or extrapolated (they validate and run on the
simulated device), the rendering error per budget, the report files and clean refusals."""

from __future__ import annotations

import csv
import json
import re
from pathlib import Path

import numpy as np
import pytest
import yaml
from params_support import masking_entry
from runner_support import write_calibration

from masking_lab.commands.cli import main
from masking_lab.core.errors import SolverError
from masking_lab.core.masking import MaskingFunction
from masking_lab.formats.masking_params import write_masking_params
from masking_lab.formats.protocol import load_protocol
from masking_lab.planning.scene_budget import Observers, budget_table, participant_errors
from masking_lab.planning.scene_needs import (
    FunctionNeed,
    function_needs,
    measure_ranges,
    provisional_pair,
)
from masking_lab.planning.scene_protocols import masker_levels, measurement_protocol
from masking_lab.planning.scene_report import SECTION_TITLES
from masking_lab.rendering.scene import load_scene

ROOT = Path(__file__).resolve().parents[1]
SCENES = ROOT / "protocols" / "scenes"
RAMPS = {
    "MV270": ((1.480, 1.113), (-2.240, 0.602)),
    "MV180": ((1.304, 1.062), (-5.927, 0.658)),
}
# Small and quick: the budget numbers are checked through the API below.
QUICK = ["--tracks", "3", "--studies", "10", "--participants", "2,4", "--trials", "12"]


def _params(path: Path, ramps=RAMPS, fitted_range=(5.0, 25.0)) -> str:
    functions = []
    for mv, ((a, b), (c, d)) in ramps.items():
        for entry in (masking_entry(mv, "EV270", a, b), masking_entry("EV270", mv, c, d)):
            entry["fitted_range_db_sl"] = list(fitted_range)
            functions.append(entry)
    doc = {
        "schema_version": 1,
        "software_version": "test",
        "created_utc": "2024-01-01T00:00:00Z",
        "provenance": {"source": "fit", "inputs": [], "settings": {}},
        "functions": functions,
    }
    write_masking_params(path, doc)
    return str(path)


def _plan(scene: str, out: Path, *extra: str) -> int:
    return main(["plan", "--scene", str(SCENES / scene), "--out", str(out), *QUICK, *extra])


def _functions_csv(out: Path) -> dict[tuple[str, str], dict[str, str]]:
    with open(out / "plan_functions.csv", encoding="utf-8") as fh:
        return {(r["target"], r["masker"]): r for r in csv.DictReader(fh)}


def test_missing_stimulus_is_named_and_its_protocols_validate_and_run(tmp_path, capsys):
    # The user test's coarse texture (MV120am40) with parameters from experiments I and II only.
    params = _params(tmp_path / "masking_params.json")
    out = tmp_path / "plan"
    assert _plan("bump_coarse.yaml", out, "--params", params) == 0
    text = capsys.readouterr().out
    assert "EV270 masked by MV120am40" in text and "MV120am40 masked by EV270" in text
    assert text.count("missing (no entry)") == 2
    rows = _functions_csv(out)
    assert {r["status"] for r in rows.values()} == {"missing"}
    written = sorted(out.glob("measure_*.yaml"))
    assert [p.name.split("_")[1:4] for p in written] == [
        ["EV270", "by", "MV120am40"],
        ["MV120am40", "by", "EV270"],
    ]
    data = tmp_path / "data"
    write_calibration(data, "S01", {"EV270": -18.0, "MV120am40": -24.0})
    for path in written:
        assert path.name in text
        assert main(["validate", str(path)]) == 0
        protocol = load_protocol(path)
        spec = protocol.sets[0]
        target, masker = spec.target.name, spec.masker.name
        used = rows[(target, masker)]
        # The protocol covers the used masker range, rounded outward to whole dB.
        assert spec.settings.masker_min_db_sl == np.floor(float(used["used_min_db_sl"]))
        assert spec.settings.masker_max_db_sl == np.ceil(float(used["used_max_db_sl"]))
        assert spec.settings.kind == "functional_ramp" and spec.settings.max_trials == 12
        argv = ["run", str(path), "--participant", "S01", "--device", "sim", "--responder"]
        argv += ["sim", "--data", str(data), "--seed", "3", "--no-progress"]
        assert main(argv) == 0
        log = next((data / "S01").glob(f"{protocol.experiment}-S01-*.jsonl"))
        records = [json.loads(line) for line in log.read_text(encoding="utf-8").splitlines()]
        levels = [r["masker_level_db_sl"] for r in records if r.get("record") == "trial"]
        assert len(levels) == 12
        assert min(levels) >= spec.settings.masker_min_db_sl
        assert max(levels) <= spec.settings.masker_max_db_sl


def test_a_fully_covered_scene_has_nothing_to_measure(tmp_path, capsys):
    params = _params(tmp_path / "p.json", fitted_range=(0.0, 40.0))
    out = tmp_path / "plan"
    assert _plan("bump_rough.yaml", out, "--params", params) == 0
    text = capsys.readouterr().out
    assert "nothing to measure" in text
    assert text.count("present, within the fitted range") == 2
    assert not list(out.glob("measure_*.yaml"))
    assert (out / "plan_budgets.csv").read_text(encoding="utf-8").startswith("participants,")
    assert len((out / "plan_budgets.csv").read_text(encoding="utf-8").splitlines()) == 1
    assert "with the parameters as fitted (no new measurement)" in text


def test_an_extrapolated_masker_is_measured_over_exactly_the_missing_range(tmp_path, capsys):
    # The reference rig's 30 dB SL of MV masks EV beyond the 5-25 dB SL the ramp was fitted on.
    params = _params(tmp_path / "p.json")
    out = tmp_path / "plan"
    assert _plan("bump_rough.yaml", out, "--params", params, "--procedure", "quest_plus") == 0
    text = capsys.readouterr().out
    assert "extrapolated: 5.0 dB above the fitted range" in text
    rows = _functions_csv(out)
    assert rows[("EV270", "MV180")]["status"] == "extrapolated"
    assert float(rows[("EV270", "MV180")]["above_fitted_db"]) == pytest.approx(5.0)
    assert rows[("MV180", "EV270")]["status"] == "within"
    (written,) = out.glob("measure_*.yaml")
    assert written.name == "measure_EV270_by_MV180_25-30dB.yaml"
    protocol = load_protocol(written)
    assert [s.masker_level_db_sl for s in protocol.sets] == [25.0, 30.0]
    assert {s.settings.kind for s in protocol.sets} == {"quest_plus"}
    assert (
        main(
            [
                "validate",
                str(written),
                "--device-config",
                str(ROOT / "protocols" / "devices" / "default.yaml"),
            ]
        )
        == 0
    )


def test_measure_ranges_and_protocols_follow_the_need():
    def need(status, used, fitted, below=0.0, above=0.0):
        return FunctionNeed(
            "EV270", "MV180", used, status, fitted, below, above, "fitted", -5.9, 0.66
        )

    assert measure_ranges(need("within", (6.0, 20.0), (5.0, 25.0))) == []
    # Both sides beyond: one range each, widened into the fitted range to two levels.
    both = need("extrapolated", (1.2, 27.5), (5.0, 25.0), below=3.8, above=2.5)
    assert measure_ranges(both) == [(1.0, 6.0), (23.0, 28.0)]
    # A masker that barely varies still gets a ramp's worth of levels; never below 0 dB SL.
    assert measure_ranges(need("missing", (12.0, 12.0), None)) == [(7.0, 12.0)]
    assert measure_ranges(need("missing", (-3.0, 1.0), None)) == [(0.0, 5.0)]
    assert masker_levels(0.0, 20.0) == [0.0, 5.0, 10.0, 15.0, 20.0]
    with pytest.raises(SolverError, match="choose one of"):
        measurement_protocol(both, 20.0, 28.0, procedure="staircase")


def _bump_rough_truth():
    scene = load_scene(SCENES / "bump_rough.yaml")
    prior = {
        ("MV180", "EV270"): MaskingFunction("MV180", "EV270", 1.304, 1.062),
        ("EV270", "MV180"): MaskingFunction("EV270", "MV180", -5.927, 0.658),
    }
    inputs = provisional_pair(None, prior, mv="MV180", ev="EV270")
    _, needs = function_needs(scene, inputs, max_mv_db_sl=30.0, max_ev_db_sl=30.0)
    return scene, inputs, needs


def _measured(needs, trials, seed, tracks=10):
    rng = np.random.default_rng(seed)
    out = {}
    for n in needs:
        ((lo, hi),) = measure_ranges(n)
        doc = measurement_protocol(n, lo, hi, procedure="quest_plus", trials=max(trials))
        key = "g" if n.target.startswith("EV") else "f"
        out[key] = participant_errors(
            doc["procedure"],
            "quest_plus",
            (n.intercept_db, n.slope),
            trials,
            tracks=tracks,
            observers=Observers(),
            rng=rng,
            masker_levels_db_sl=masker_levels(lo, hi),
        )
    return out


def test_rendering_error_falls_with_the_budget_and_is_seeded():
    scene, inputs, needs = _bump_rough_truth()
    assert [n.status for n in needs] == ["missing", "missing"]
    trials = (20, 80)
    kw = dict(
        participants=(2, 8, 32),
        trials=trials,
        studies=30,
        seconds_per_trial=9.3,
        max_mv_db_sl=30.0,
        max_ev_db_sl=30.0,
        gamut_map="clip",
    )
    rows, floor = budget_table(
        scene, inputs.pair, _measured(needs, trials, 1), {}, rng=np.random.default_rng(2), **kw
    )
    table = np.array([[r.rms_db, r.rms_p90_db, r.max_db, r.measurement_rms_db] for r in rows])
    assert np.isfinite(table).all() and np.isfinite(list(floor.values())).all()
    by = {(r.participants, r.trials): r for r in rows}
    for t in trials:
        meas = [by[(n, t)].measurement_rms_db for n in (2, 8, 32)]
        # Four times the participants halves the measurement error's SD (common random numbers).
        assert meas[0] > meas[1] > meas[2] > 0
        assert meas[2] / meas[0] == pytest.approx(0.25, rel=0.5)
    assert by[(32, 80)].rms_db < by[(2, 20)].rms_db
    # No budget beats the ramps known exactly by more than the spread of a few studies.
    assert min(r.rms_db for r in rows) > floor["rms_db"] - 0.05
    assert by[(32, 80)].hours == pytest.approx(32 * 80 * 2 * 9.3 / 3600)
    again, _ = budget_table(
        scene, inputs.pair, _measured(needs, trials, 1), {}, rng=np.random.default_rng(2), **kw
    )
    assert [r.as_dict() for r in again] == [r.as_dict() for r in rows]


def test_report_html_has_the_text_reports_headings_and_folders_follow_plans_rule(
    tmp_path, monkeypatch, capsys
):
    monkeypatch.chdir(tmp_path)
    scene = str(SCENES / "bump_rough.yaml")
    argv = ["plan", "--scene", scene, *QUICK, "--params", _params(tmp_path / "p.json")]
    assert main(argv) == 0
    assert main(argv) == 0
    first, second = tmp_path / "plan_out", tmp_path / "plan_out-2"
    text = (first / "plan.txt").read_text(encoding="utf-8")
    html = (first / "report.html").read_text(encoding="utf-8")
    headings = re.findall(r"<h2[^>]*>(.*?)</h2>", html)
    assert headings == list(SECTION_TITLES)
    assert "data:image/png;base64," in html and (first / "plan_budgets.png").exists()
    assert all(f"\n{t}\n{'-' * len(t)}\n" in text for t in SECTION_TITLES)
    assert (second / "plan.txt").read_text(encoding="utf-8") == text  # seeded
    assert main([*argv, "--out", str(first)]) == 2
    assert "pass --force" in capsys.readouterr().err
    assert main([*argv, "--out", str(first), "--force"]) == 0


def test_single_channel_scene_needs_nothing(tmp_path, capsys):
    doc = yaml.safe_load((SCENES / "bump_rough.yaml").read_text(encoding="utf-8"))
    doc["texture"] = None
    path = tmp_path / "bump.yaml"
    path.write_text(yaml.safe_dump(doc), encoding="utf-8")
    assert main(["plan", "--scene", str(path), "--out", str(tmp_path / "o"), *QUICK]) == 0
    text = capsys.readouterr().out
    assert "single-channel scene" in text and "nothing to measure" in text


def test_bad_inputs_are_clean_errors_naming_the_file(tmp_path, capsys):
    params = _params(tmp_path / "p.json")
    out = str(tmp_path / "o")
    missing = str(tmp_path / "nope.yaml")
    assert main(["plan", "--scene", missing, "--out", out]) == 2
    assert "nope.yaml" in capsys.readouterr().err
    assert main(["plan", "--scene", str(SCENES / "bump_rough.yaml"), "--params", missing]) == 2
    assert "nope.yaml" in capsys.readouterr().err
    not_params = str(SCENES / "bump_rough.yaml")
    assert main(["plan", "--scene", not_params, "--params", not_params, "--out", out]) == 2
    assert "bump_rough.yaml" in capsys.readouterr().err
    # A protocol is not a scene.
    assert main(["plan", "--scene", str(ROOT / "protocols" / "experiment1.yaml")]) == 2
    assert "experiment1.yaml" in capsys.readouterr().err
    # The scene's pair is neither fitted nor known to the ground truth.
    gt = yaml.safe_load((ROOT / "protocols" / "simulation" / "ground_truth.yaml").read_text())
    gt["masking"] = [m for m in gt["masking"] if "MV120am40" not in (m["target"], m["masker"])]
    gt_path = tmp_path / "truth.yaml"
    gt_path.write_text(yaml.safe_dump(gt), encoding="utf-8")
    argv = ["plan", "--scene", str(SCENES / "hole_coarse.yaml"), "--params", params]
    assert main([*argv, "--ground-truth", str(gt_path), "--out", out]) == 2
    err = capsys.readouterr().err
    assert "truth.yaml" in err and "MV120am40" in err and "Traceback" not in err
    # Neither or both of PROTOCOL and --scene.
    assert main(["plan", "--out", out]) == 2
    assert main(["plan", str(ROOT / "protocols" / "experiment1.yaml"), "--scene", not_params]) == 2
    assert "not both" in capsys.readouterr().err
    assert not Path(out).exists()


# ---------------------------------------------------------------------------------------------
# Issue 19 items 1-2 as the demo reports them: the gamut and the trade in the closing summary.


def test_demo_summary_shows_the_gamut_and_the_mapping_trade(tmp_path):
    from masking_lab.demo_summary import ChannelRow, DemoSummary, _mapping, summary_text
    from masking_lab.rendering.pair import MutualMasking
    from masking_lab.rendering.render import compare_strategies, render_scene, summarize

    scene = load_scene(SCENES / "bump_rough.yaml")
    pair = MutualMasking(0.93, 1.061, -6.49, 0.649, mv="MV180", ev="EV270")
    rendering = summarize(
        render_scene(scene, pair, max_mv_db_sl=30.0, max_ev_db_sl=30.0, gamut_map="clip")
    )
    rendering["gamut_mapping"]["strategies"] = compare_strategies(scene, pair, 30.0, 30.0)
    channel = ChannelRow("MV", "MV180", (20.0, 30.0), 3.0, 0, 919, 0, 30.0)
    m = DemoSummary(
        tmp_path,
        2,
        6,
        30,
        30,
        900,
        "sim",
        None,
        (),
        ("bump_rough", "MV180", "EV270", 0.69),
        (channel,),
        0,
        **_mapping(rendering),
    )
    text = summary_text(m)
    assert "figure4.png, gamut.png)" in text
    line = next(ln for ln in text.splitlines() if "perceptual gamut" in ln)
    # The outline of docs/solver.md for these ramps and the reference rig's 30 dB SL.
    assert "(-0.9, 0.0), (9.1, 0.0), (29.1, -13.0), (-2.8, 17.0), (-22.8, 30.0)" in line
    moved = rendering["gamut_mapping"]["points_moved"]
    assert moved > 800 and f"{moved} of 919 targets lay outside it" in line
    assert "gamut mapping (rendered with clip)" in text
    assert all(s in text for s in ("clip", "scale", "compress", "none"))


def test_no_non_finite_number_reaches_the_plan_files():
    from masking_lab.planning.scene_budget import BudgetRow
    from masking_lab.planning.scene_report import ScenePlan, format_scene_plan, rows_csv

    # A budget whose every study lost every point (b·d ≥ 1 throughout) has no error to show.
    row = BudgetRow(5, 30, 60, 0.8, float("nan"), float("nan"), float("inf"), float("nan"), 1.0)
    csv_text = rows_csv([row.as_dict()])
    assert "nan" not in csv_text.lower() and "inf" not in csv_text.lower()
    assert csv_text.splitlines()[1] == "5,30,60,0.8,,,,,1"
    text = format_scene_plan(ScenePlan(["h"], "", [], [], [row], None, None, []))
    assert "nan" not in text.lower() and "inf" not in text.lower()


def test_an_unmapped_scene_measures_only_what_the_rig_can_play():
    scene, inputs, _ = _bump_rough_truth()
    # Unmapped, bump_rough asks for ~62 dB SL of MV; the rig plays at most its 30 dB SL.
    r, needs = function_needs(scene, inputs, max_mv_db_sl=30.0, max_ev_db_sl=30.0, gamut_map="none")
    assert np.nanmax(r.mv_input_db_sl) > 50
    assert max(n.used_range_db_sl[1] for n in needs) == 30.0
    _, unrated = function_needs(scene, inputs, max_mv_db_sl=None, max_ev_db_sl=None)
    assert unrated[0].used_range_db_sl[1] > 50  # no rating, nothing caps it


@pytest.mark.parametrize("scene", ["ascending_coarse", "descending_coarse", "hole_coarse"])
def test_every_coarse_user_test_object_names_the_missing_texture(scene, tmp_path, capsys):
    params = _params(tmp_path / "p.json")
    out = tmp_path / "plan"
    assert _plan(f"{scene}.yaml", out, "--params", params, "--trials", "10") == 0
    text = capsys.readouterr().out
    assert text.count("missing (no entry)") == 2 and "MV120am40" in text
    written = sorted(out.glob("measure_*.yaml"))
    assert len(written) == 2
    for path in written:
        assert main(["validate", str(path)]) == 0


def test_the_budget_figure_is_legible_and_embedded(tmp_path):
    from masking_lab.formats.png_figure import small_texts
    from masking_lab.planning.figures import png_bytes
    from masking_lab.planning.scene_budget import BudgetRow
    from masking_lab.planning.scene_figure import budget_figure

    rows = [
        BudgetRow(n, t, 2 * t, n * t * 2 * 9.3 / 3600, 1 / n + 0.5, 1.2 / n + 0.5, 2.0, 0.4, 0.0)
        for n in (5, 10)
        for t in (30, 90)
    ]
    fig = budget_figure(rows, {"rms_db": 0.5, "max_db": 2.0}, title="bump_coarse")
    assert png_bytes(fig).startswith(b"\x89PNG")
    assert small_texts(fig) == []
    assert {t.get_text() for t in fig.axes[0].get_legend().get_texts()} == {
        "5 participants",
        "10 participants",
        "ramps known exactly",
    }


def test_fault_paths_of_the_pure_parts_are_clean_errors():
    from masking_lab.core.errors import AnalysisError

    bad = {"functions": [{"target": "MV180", "masker": "EV270", "intercept_db": 1.0,
                          "slope": -1.0, "status": "fitted"}]}  # fmt: skip
    prior = {("EV270", "MV180"): MaskingFunction("EV270", "MV180", -5.9, 0.66)}
    with pytest.raises(SolverError, match=r"p\.json: masking slope b .* must be ≥ 0"):
        provisional_pair(bad, prior, mv="MV180", ev="EV270", params_source="p.json")
    need = FunctionNeed("EV270", "MV180", (5, 9), "missing", None, 0, 0, "missing", -5.9, 0.66)
    with pytest.raises(SolverError, match="need 0 ≤ lo < hi"):
        measurement_protocol(need, 9.0, 9.0)
    doc = measurement_protocol(need, 5.0, 10.0, procedure="quest_plus")
    with pytest.raises(AnalysisError, match="at least two masker levels"):
        participant_errors(
            doc["procedure"], "quest_plus", (-5.9, 0.66), [20], tracks=3,
            observers=Observers(), rng=np.random.default_rng(0), masker_levels_db_sl=[5.0],
        )  # fmt: skip


@pytest.mark.parametrize(
    "option", [["--participants", "0"], ["--trials", "3,x"], ["--tracks", "2"], ["--studies", "5"]]
)
def test_bad_budget_options_are_refused_by_the_parser(option, tmp_path, capsys):
    scene = str(SCENES / "bump_rough.yaml")
    with pytest.raises(SystemExit) as exc:
        main(["plan", "--scene", scene, "--out", str(tmp_path / "o"), *option])
    assert exc.value.code == 2
    assert option[0] in capsys.readouterr().err


def test_a_missing_ground_truth_file_is_named(tmp_path, capsys):
    missing = str(tmp_path / "truth.yaml")
    argv = ["plan", "--scene", str(SCENES / "bump_rough.yaml"), "--ground-truth", missing]
    assert main([*argv, "--out", str(tmp_path / "o")]) == 2
    assert "truth.yaml" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_the_rig_config_sets_the_ratings_and_so_the_ranges(tmp_path, capsys):
    from usertest_support import write_rig

    # A rig rated at 20 dB SL keeps bump_rough's maskers within the 5-25 dB SL fitted on.
    rig = write_rig(tmp_path, max_level_db_sl=20.0)
    params = _params(tmp_path / "p.json")
    out = tmp_path / "plan"
    assert _plan("bump_rough.yaml", out, "--params", params, "--device-config", str(rig)) == 0
    text = capsys.readouterr().out
    assert "rated MV 20, EV 20 dB SL" in text and "nothing to measure" in text
    rows = _functions_csv(out)
    assert max(float(r["used_max_db_sl"]) for r in rows.values()) <= 20.0


def test_an_unfitted_entry_counts_as_missing_and_says_why():
    from masking_lab.planning.scene_report import status_text

    scene = load_scene(SCENES / "bump_rough.yaml")
    params = {
        "functions": [
            masking_entry("MV180", "EV270", 1.304, 1.062),
            masking_entry("EV270", "MV180", 0.0, 0.0, status="insufficient_data"),
        ]
    }
    prior = {("EV270", "MV180"): MaskingFunction("EV270", "MV180", -5.927, 0.658)}
    inputs = provisional_pair(params, prior, mv="MV180", ev="EV270")
    assert inputs.pair.c_db == -5.927  # the prior's ramp predicts the inputs
    _, needs = function_needs(scene, inputs, max_mv_db_sl=30.0, max_ev_db_sl=30.0)
    assert [status_text(n) for n in needs] == [
        "missing (status insufficient_data)",
        "present, within the fitted range",
    ]


# ---------------------------------------------------------------------------------------------
# Issue 19.2 on the paper's scenes: every strategy within the ratings, clip the closest.

PAPER_RAMPS = {**RAMPS, "MV120am40": ((-0.387, 0.939), (-7.442, 0.711))}


@pytest.mark.parametrize("path", sorted(SCENES.glob("*.yaml")), ids=lambda p: p.stem)
def test_each_strategy_on_the_papers_scenes(path):
    from masking_lab.rendering.pair import MutualMasking
    from masking_lab.rendering.render import compare_strategies

    scene = load_scene(path)
    ((mv, ev),) = scene.stimulus_pairs()
    (a, b), (c, d) = PAPER_RAMPS[mv]
    trade = compare_strategies(scene, MutualMasking(a, b, c, d, mv=mv, ev=ev), 30.0, 30.0)
    json.dumps(trade, allow_nan=False)
    for name in ("clip", "scale", "compress"):
        assert trade[name]["share_within_ratings"] == 1.0, name
        assert trade[name]["points_without_a_level"] == 0, name
    # Clip moves each point to the nearest renderable pair, so no strategy that renders every
    # point comes closer to the intent (RMS over points and both channels).
    for name in ("scale", "compress"):
        assert trade["clip"]["rms_error_db"] <= trade[name]["rms_error_db"] + 1e-9, name


def test_functions_not_remeasured_carry_their_exported_standard_errors():
    scene, inputs, _ = _bump_rough_truth()
    kw = dict(
        participants=(1,), trials=(1,), studies=40, seconds_per_trial=9.3, max_mv_db_sl=30.0,
        max_ev_db_sl=30.0, gamut_map="clip",
    )  # fmt: skip
    exact, floor = budget_table(scene, inputs.pair, {}, {}, rng=np.random.default_rng(0), **kw)
    assert exact[0].rms_db == pytest.approx(floor["rms_db"], abs=1e-12)
    assert exact[0].measurement_rms_db == pytest.approx(0.0, abs=1e-12)
    spread = {"f": (0.5, 0.05), "g": (0.5, 0.05)}
    known, _ = budget_table(scene, inputs.pair, {}, spread, rng=np.random.default_rng(0), **kw)
    assert known[0].measurement_rms_db > 0.1
    assert known[0].hours == 0.0 and known[0].trials_per_participant == 0


def test_a_long_path_is_resampled_for_the_budgets(tmp_path, capsys):
    doc = yaml.safe_load((SCENES / "bump_coarse.yaml").read_text(encoding="utf-8"))
    doc["path"]["n_points"] = 20_000
    path = tmp_path / "long.yaml"
    path.write_text(yaml.safe_dump(doc), encoding="utf-8")
    out = tmp_path / "o"
    argv = ["plan", "--scene", str(path), "--out", str(out), *QUICK]
    assert main([*argv, "--params", _params(tmp_path / "p.json")]) == 0
    text = capsys.readouterr().out
    assert "budgets evaluated on 2000 of the scene's 20000 points" in text
    with open(out / "plan_budgets.csv", encoding="utf-8") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 2 and all(float(r["rms_db"]) > 0 for r in rows)


def test_force_replaces_the_whole_plan_no_stale_protocol_left(tmp_path, capsys):
    params = _params(tmp_path / "p.json")
    out = tmp_path / "plan"
    assert _plan("bump_coarse.yaml", out, "--params", params, "--trials", "10") == 0
    assert len(list(out.glob("measure_*.yaml"))) == 2
    assert _plan("bump_rough.yaml", out, "--params", params, "--force") == 0
    assert [p.name for p in out.glob("measure_*.yaml")] == ["measure_EV270_by_MV180_25-30dB.yaml"]
