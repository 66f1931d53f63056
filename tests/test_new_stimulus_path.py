"""The user test's path for a new stimulus, end to end through the CLI (simulated participants,
sim device, virtual time): baseline and experiments I and II, a first analysis, the user test
asking for the coarse texture's baseline and then for its masking in both directions, those
sessions, the analysis of the whole data folder (experiments I and II included), `fit` on the
same shifts, and the user test with the new parameters."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest
from usertest_support import REPO, write_ground_truth, write_rig, write_usertest

from masking_lab.commands.cli import main
from masking_lab.formats.protocol import load_protocol

PARTICIPANTS = ("S01", "S02", "S03")
NEW = "MV120am40"
# The test reads masking_params.json, thresholds.csv and report.txt: no figures, no trial-level
# tables (trials.csv, psychometric.csv and their bootstraps).
ANALYZE = ["--n-boot", "200", "--quiet", "--figures", "none", "--no-trial-tables", "--pf-boot", "0"]


def _run(protocol: Path, participant: str, lab: dict, seed: int, *extra: str) -> int:
    argv = ["run", str(protocol), "--participant", participant, "--device", "sim"]
    argv += ["--responder", "sim", "--data", str(lab["data"]), "--seed", str(seed)]
    argv += ["--ground-truth", str(lab["gt"]), "--device-config", str(lab["rig"])]
    return main([*argv, "--no-progress", *extra])


def _functions(path: Path) -> dict[tuple[str, str], dict]:
    doc = json.loads(path.read_text(encoding="utf-8"))
    return {(f["target"], f["masker"]): f for f in doc["functions"]}


@pytest.fixture(scope="module")
def lab(tmp_path_factory):
    folder = tmp_path_factory.mktemp("newstim")
    # 20 dB more amplifier gain than the shipped ground truth and a rig rated to 65 dB SL, so
    # every compensated object plays unclipped.
    return {
        "folder": folder,
        "data": folder / "data",
        "gt": write_ground_truth(folder / "ground_truth.yaml", shift_db=-20.0),
        "rig": write_rig(folder, max_level_db_sl=65.0),
        "usertest": write_usertest(folder, repeats=1),
    }


def test_new_stimulus_path_end_to_end(lab, tmp_path, capsys):
    data = lab["data"]
    for k, p in enumerate(PARTICIPANTS):
        for j, name in enumerate(("baseline", "experiment1", "experiment2")):
            assert _run(REPO / "protocols" / f"{name}.yaml", p, lab, 100 * k + j) == 0
    first = tmp_path / "analysis1"
    assert main(["analyze", str(data), "--out", str(first), *ANALYZE]) == 0
    assert (NEW, "EV270") not in _functions(first / "masking_params.json")

    # The user test needs the coarse texture: first its baseline ...
    params = first / "masking_params.json"
    capsys.readouterr()
    assert _run(lab["usertest"], "S01", lab, 7, "--params", str(params)) == 2
    baseline = next(data.glob(f"baseline_*{NEW}*.yaml"))
    assert str(baseline) in capsys.readouterr().err
    for k, p in enumerate(PARTICIPANTS):
        assert _run(baseline, p, lab, 200 + k) == 0
    # ... then its masking, one protocol per direction, each saying who wrote it.
    assert _run(lab["usertest"], "S01", lab, 7, "--params", str(params)) == 2
    err = capsys.readouterr().err
    measures = sorted(data.glob("measure_*.yaml"))
    assert [m.name for m in measures] == [
        f"measure_EV270_by_{NEW}.yaml",
        f"measure_{NEW}_by_EV270.yaml",
    ]
    for m in measures:
        assert str(m) in err
        assert m.read_text(encoding="utf-8").startswith("# Written by masking-lab run:")
        protocol = load_protocol(m)
        assert len({(s.target.name, s.masker.name) for s in protocol.sets}) == 1
        for k, p in enumerate(PARTICIPANTS):
            assert _run(m, p, lab, 300 + k) == 0

    # The whole data folder analyses: experiments I and II and both new directions.
    second = tmp_path / "analysis2"
    argv = ["analyze", str(data), "--out", str(second), *ANALYZE]
    assert main(argv) == 0, capsys.readouterr().err
    functions = _functions(second / "masking_params.json")
    for pair in ((NEW, "EV270"), ("EV270", NEW)):
        assert functions[pair]["status"] == "fitted", functions[pair]
        assert functions[pair]["experiment"] == f"measure_{pair[0]}_by_{pair[1]}"
    # Experiments I and II are analysed as before the new sessions were added.
    before = _functions(first / "masking_params.json")
    for pair, f in before.items():
        assert functions[pair]["intercept_db"] == f["intercept_db"], pair
        assert functions[pair]["slope"] == f["slope"], pair
    report = (second / "report.txt").read_text(encoding="utf-8")
    assert f"Experiment measure_EV270_by_{NEW}" in report

    # `fit` on the same shifts gives the same ramps.
    shifts = tmp_path / "shifts.csv"
    with (second / "thresholds.csv").open(encoding="utf-8", newline="") as fh:
        rows = [r for r in csv.DictReader(fh) if r["shift_db"] and r["status"] == "completed"]
    cols = ["participant", "experiment", "target", "masker", "masker_level_db_sl", "shift_db"]
    with shifts.open("w", encoding="utf-8", newline="") as fh:
        w = csv.DictWriter(fh, cols, extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)
    fitted = tmp_path / "fit"
    assert main(["fit", str(shifts), "--out", str(fitted), "--n-boot", "200"]) == 0
    refit = _functions(fitted / "masking_params.json")
    for pair in ((NEW, "EV270"), ("EV270", NEW), ("EV270", "MV180"), ("MV270", "EV270")):
        assert refit[pair]["intercept_db"] == pytest.approx(functions[pair]["intercept_db"])
        assert refit[pair]["slope"] == pytest.approx(functions[pair]["slope"])

    # The user test now runs, compensated with the new parameters.
    new_params = second / "masking_params.json"
    for k, p in enumerate(PARTICIPANTS):
        assert _run(lab["usertest"], p, lab, 400 + k, "--params", str(new_params)) == 0
    report_dir = tmp_path / "usertest"
    assert main(["usertest-report", str(data), "--out", str(report_dir)]) == 0
    printed = capsys.readouterr().out
    assert f"{len(PARTICIPANTS)} session(s)" in printed
    assert (report_dir / "report.html").is_file()
