"""The smaller defects of issue 17, each with the behaviour that replaces it."""

from __future__ import annotations

import json
import re
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from masking_lab.analysis.export import determination
from masking_lab.analysis.report import experiment_heading
from masking_lab.commands.cli import main
from masking_lab.formats.masking_params import determination_warnings
from masking_lab.formats.schemas import schema_errors

ROOT = Path(__file__).resolve().parents[1]
CLI = Path(sys.executable).with_name("masking-lab")


def test_sigint_prints_the_resume_message_once_with_the_trial_of_the_progress_line(tmp_path):
    """A real process, a real SIGINT while trial 2 is on the progress line."""
    args = [str(CLI), "run", str(ROOT / "protocols" / "baseline.yaml"), "--participant", "S1"]
    args += ["--device", "sim", "--responder", "sim", "--real-time", "--progress"]
    args += ["--data", str(tmp_path / "data")]
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    seen = ""
    while "| trial 2 |" not in seen:
        ch = proc.stderr.read(1)
        assert ch, f"the session ended before trial 2: {seen!r}"
        seen += ch
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 130
    shown = seen + err + out
    assert shown.count("Resume with:") == 1, shown
    set_id = re.findall(r"set \d+/\d+ (\S+) \| trial 2 \|", seen)[-1]
    assert f"interrupted in set {set_id}, trial 2;" in err


def test_a_keypad_without_a_terminal_is_a_responder_error_not_a_device_error(tmp_path):
    args = [str(CLI), "run", str(ROOT / "protocols" / "baseline.yaml"), "--participant", "S1"]
    args += ["--device", "sim", "--responder", "keys", "--data", str(tmp_path)]
    done = subprocess.run(args, stdin=subprocess.DEVNULL, capture_output=True, text=True)
    assert done.returncode == 3
    assert "responder error: the keys responder reads" in done.stderr
    assert "device error" not in done.stderr
    assert "fix the participant's terminal or window" in done.stderr


def test_solve_checks_the_reference_rigs_ratings_by_default(capsys):
    argv = ["solve", "--mv-masked-by-ev=-5,0.5", "--ev-masked-by-mv=-3,0.6"]
    assert main([*argv, "--mv-target", "40", "--ev-target", "30"]) == 0
    assert "MV above its rating (30 dB SL)" in capsys.readouterr().out
    # --max-* still override the rig
    assert main([*argv, "--mv-target", "40", "--ev-target", "30", "--max-mv-db-sl", "90",
                 "--max-ev-db-sl", "90"]) == 0  # fmt: skip
    assert "rating" not in capsys.readouterr().out


def test_poorly_determined_fits_are_marked_and_warned_about(tmp_path, capsys):
    assert main(["fit", str(ROOT / "data_schema" / "shifts.csv"), "--out", str(tmp_path / "f"),
                 "--figures", "none", "--quiet"]) == 0  # fmt: skip
    path = tmp_path / "f" / "masking_params.json"
    doc = json.loads(path.read_text())
    assert all(f["poorly_determined"] is False for f in doc["functions"])
    assert schema_errors(doc, "masking_params") == []
    # The new-stimulus fit of issue 17: b = 0.51 [-0.34, 1.36].
    f = next(f for f in doc["functions"] if (f["target"], f["masker"]) == ("EV270", "MV120"))
    f["slope"], f["slope_ci"] = 0.51, [-0.34, 1.36]
    f |= determination("fitted", tuple(f["intercept_ci_db"]), (-0.34, 1.36))
    assert f["poorly_determined"] and "includes 0" in f["determination"]
    assert schema_errors(doc, "masking_params") == []
    path.write_text(json.dumps(doc))
    capsys.readouterr()
    argv = ["solve", "--params", str(path), "--mv", "MV120", "--mv-target", "10"]
    assert main([*argv, "--ev-target", "10"]) == 0
    err = capsys.readouterr().err
    assert "warning" in err and "EV270 masked by MV120 is poorly determined" in err
    assert main(["solve", "--params", str(path), "--mv", "MV180", "--mv-target", "10",
                 "--ev-target", "10"]) == 0  # fmt: skip
    assert "poorly determined" not in capsys.readouterr().err  # another pair: no warning
    # An older file without the field: the slope interval alone decides.
    del f["poorly_determined"], f["determination"]
    assert determination_warnings(doc, "old.json", ("MV120", "EV270"))


def test_intervals_wider_than_the_limits_are_poorly_determined():
    assert determination("fitted", (0.0, 12.0), (0.4, 0.6))["poorly_determined"]
    assert determination("fitted", (0.0, 2.0), (0.1, 1.3))["poorly_determined"]
    assert not determination("no_masking", None, None)["poorly_determined"]


def test_study_help_describes_every_option_with_its_default(capsys):
    with pytest.raises(SystemExit):
        main(["study", "--help"])
    text = capsys.readouterr().out.split("options:", 1)[1]
    for option in ("--replicates", "--ml-replicates", "--convergence-replicates",
                   "--max-reversals", "--seed", "--out"):  # fmt: skip
        block = text.split(f"\n  {option} ", 1)[1].split("\n  -", 1)[0]
        assert "default" in block, option


def test_study_runs_outside_the_repository(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    argv = ["study", "--replicates", "4", "--ml-replicates", "0", "--convergence-replicates", "4"]
    assert main([*argv, "--quest-replicates", "0", "--max-reversals", "15"]) == 0
    assert (tmp_path / "study_out" / "settings.csv").is_file()
    assert (tmp_path / "study_out" / "blocks" / "settings.md").is_file()


def test_headings_do_not_repeat_experiment():
    assert experiment_heading("experiment1") == "experiment1"
    assert experiment_heading("II") == "Experiment II"


def test_fit_report_says_undated_instead_of_1970(tmp_path):
    assert main(["fit", str(ROOT / "data_schema" / "shifts.csv"), "--out", str(tmp_path / "f"),
                 "--figures", "none", "--quiet"]) == 0  # fmt: skip
    for name in ("report.txt", "report.html"):
        text = (tmp_path / "f" / name).read_text()
        assert "export created 1970" not in text and "export created: 1970" not in text
        assert "undated" in text


def test_track_figures_use_legible_text_and_visible_wrong_answers(tmp_path):
    from masking_lab.analysis import track_figures as tf
    from masking_lab.analysis.track_figures import _canvas, _track_png
    from masking_lab.formats.png_figure import small_texts

    panel = tf.TrackPanel(
        set_id="A", status="completed", unit="level (dB SL)", levels=[4.0, 2.0, 2.0, 4.0],
        correct=[True, False, True, True], reversal=[False, True, False, False], al=3.0,
    )  # fmt: skip
    png = _track_png(tf.TrackJob(path=str(tmp_path / "t.png"), title="t", panels=(panel,)))
    assert png[:4] == b"\x89PNG"
    fig, axes = _canvas(1)
    assert small_texts(fig, 9.0) == []
    wrong = next(line for line in axes.ravel()[0].lines if line.get_label() == "wrong")
    assert wrong.get_markersize() >= 6 and wrong.get_markeredgewidth() >= 1.5
    assert wrong.get_markerfacecolor() == "white" and wrong.get_zorder() > 2
    assert fig.dpi >= 100


def test_figure4_draws_each_masked_al_in_its_own_colour_and_both_rated_maxima(
    tmp_path, monkeypatch
):
    import matplotlib.colors as mcolors

    from masking_lab.rendering import figures

    sys.path.insert(0, str(ROOT / "tests"))
    from test_render import write_params

    drawn = []
    real = figures.png_bytes

    def keep(fig, **kw):
        drawn.append([(ln.get_label(), ln.get_color()) for ax in fig.axes for ln in ax.lines])
        return real(fig, **kw)

    monkeypatch.setattr(figures, "png_bytes", keep)
    params = write_params(tmp_path / "p.json")
    scene = str(ROOT / "protocols" / "scenes" / "bump_rough.yaml")
    assert main(["render", scene, "--params", params, "--out", str(tmp_path / "o")]) == 0
    (lines,) = drawn
    colour = {label: mcolors.to_hex(c) for label, c in lines}
    assert colour["masked AL of MV (by EV)"] == mcolors.to_hex(figures.MV_COLOUR)
    assert colour["masked AL of EV (by MV)"] == mcolors.to_hex(figures.EV_COLOUR)
    # The reference rig rates both channels at 30 dB SL: one line says so, none hides another.
    assert "MV and EV rated maximum (30 dB SL)" in colour
    assert not any(label in ("MV rated maximum", "EV rated maximum") for label in colour)


def test_the_new_stimulus_path_names_every_refusal_at_once_with_a_complete_command(
    tmp_path, capsys
):
    data = tmp_path / "data"
    base = ["--participant", "S01", "--device", "sim", "--responder", "sim", "--data", str(data)]
    assert main(["run", str(ROOT / "protocols" / "baseline.yaml"), *base]) == 0
    assert main(["fit", str(ROOT / "data_schema" / "shifts.csv"), "--out", str(tmp_path / "f"),
                 "--figures", "none", "--quiet"]) == 0  # fmt: skip
    params = tmp_path / "f" / "masking_params.json"
    capsys.readouterr()
    usertest = str(ROOT / "protocols" / "usertest.yaml")
    assert main(["run", usertest, *base, "--params", str(params)]) == 2
    err = capsys.readouterr().err
    # both refusals in one message: the missing baseline and the missing masking functions
    assert "cannot start yet, for 2 reasons" in err
    assert "1. " in err and "no unmasked AL for MV120am40" in err
    assert "2. " in err and "not fitted" in err
    # the printed baseline command is complete: this run's device and responder, no "..."
    baseline = next(data.glob("baseline_*MV120am40*.yaml"))
    assert f"masking-lab run {baseline} --participant S01" in err
    assert "--device sim --responder sim, then start the user test again" in err
    assert "--device ..." not in err
    assert sorted(p.name for p in data.glob("measure_*.yaml")) == [
        "measure_EV270_by_MV120am40.yaml",
        "measure_MV120am40_by_EV270.yaml",
    ]
