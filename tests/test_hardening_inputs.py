"""Input hardening (issue 11): each defect found by trying bad inputs, reproduced through the
real command, now a clean error (exit 2, or 1 from validate) naming file, key and line."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from masking_lab.commands.cli import main
from masking_lab.formats.resources import shipped

BOMB = "\n".join(
    [
        'l0: &l0 ["lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol"]',
        *(f"l{i}: &l{i} [" + ", ".join([f"*l{i - 1}"] * 9) + "]" for i in range(1, 10)),
    ]
)
RIG = shipped("protocols", "devices/default.yaml").read_text(encoding="utf-8")
TRUTH = shipped("protocols", "simulation/ground_truth.yaml").read_text(encoding="utf-8")
SCENE = shipped("protocols", "scenes/bump_rough.yaml").read_text(encoding="utf-8")
PROTOCOL = """\
schema_version: 1
experiment: pilot
kind: masked
target: EV270
staircase:
  start_level_db: 20
  n_reversals: 11
  n_reversals_averaged: 8
sets:
  - {id: a, masker: MV120, masker_level_db_sl: 5}
  - {id: b, masker: MV120, masker_level_db_sl: 10}
"""


def cli(capsys, *argv: str) -> tuple[int, str]:
    code = main([str(a) for a in argv])
    captured = capsys.readouterr()
    return code, captured.out + captured.err


def write(tmp_path: Path, name: str, text: str | bytes) -> Path:
    path = tmp_path / name
    path.write_bytes(text if isinstance(text, bytes) else text.encode("utf-8"))
    return path


def cli_subprocess(*argv: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "masking_lab.commands.cli", *map(str, argv)],
        capture_output=True,
        text=True,
        timeout=timeout,
    )


# ------------------------------------------------------------------ the shared reader


@pytest.mark.parametrize(
    ("name", "base"), [("protocol.yaml", PROTOCOL), ("rig.yaml", RIG), ("truth.yaml", TRUTH)]
)
def test_an_alias_bomb_is_refused_at_once(tmp_path, name, base):
    # Was: ~2 GB of memory and no end. A real subprocess, so a hang fails by timeout.
    path = write(tmp_path, name, base + "\n" + BOMB + "\n")
    res = cli_subprocess("validate", path, timeout=60)  # a hang ends in TimeoutExpired
    assert res.returncode == 1, res.stderr
    assert "expands to more than 50000 values" in res.stderr and "Traceback" not in res.stderr


def test_a_small_anchor_and_merge_key_still_work(tmp_path, capsys):
    text = PROTOCOL.replace(
        "  - {id: a, masker: MV120, masker_level_db_sl: 5}",
        "  - &first {id: a, masker: MV120, masker_level_db_sl: 5}",
    ).replace(
        "  - {id: b, masker: MV120, masker_level_db_sl: 10}",
        "  - {<<: *first, id: b, masker_level_db_sl: 10}",
    )
    code, out = cli(capsys, "validate", write(tmp_path, "p.yaml", text))
    assert code == 0, out


@pytest.mark.parametrize(
    ("name", "text", "where"),
    [
        ("deep.yaml", "a: " + "[" * 5000 + "]" * 5000 + "\n", "line 1, column "),
        ("deep.json", '{"a": ' + "[" * 100000 + "]" * 100000 + "}", "line 1"),
        ("deep2.yaml", "".join(f"{'  ' * i}k{i}:\n" for i in range(60)) + "  " * 60 + "x\n", ""),
    ],
)
def test_deep_nesting_is_a_clean_error(tmp_path, capsys, name, text, where):
    # Was: RecursionError traceback.
    code, out = cli(capsys, "validate", write(tmp_path, name, text))
    assert code == 1 and "nested more than 32 levels deep" in out and where in out


@pytest.mark.parametrize(
    ("name", "text"),
    [
        ("rig.yaml", RIG.replace("name: reference-rig", "name: r\xe9f")),
        ("truth.yaml", TRUTH.replace("shift_sd_db: 1.0", "shift_sd_db: 1.0 # \xb1")),
        ("calibration.json", '{"participant": "S01",\n "unmasked_al_db_v": {"EV270": -1\xff}}'),
        ("masking_params.json", '{\n "schema_version": 1,\n "functions": ["\xe9"]}'),
        ("shifts.csv", "target,masker,masker_level_db_sl,shift_db\nEV270,MV120,5,1\xe9\n"),
    ],
)
def test_bytes_that_are_not_utf8_name_their_line(tmp_path, capsys, name, text):
    # Was: UnicodeDecodeError traceback. latin-1 bytes: é is 0xE9, not UTF-8 on its own.
    path = write(tmp_path, name, text.encode("latin-1"))
    code, out = cli(capsys, "validate", path)
    assert code == 1, out
    assert "is not UTF-8 text; save the file as UTF-8" in out and "line " in out


# ------------------------------------------------------------------ non-finite numbers


@pytest.mark.parametrize(
    ("old", "new", "where"),
    [
        ("masker_level_db_sl: 5}", "masker_level_db_sl: .nan}", "sets[0].masker_level_db_sl"),
        ("  n_reversals: 11", "  n_reversals: 11\n  max_level_db: .inf", "staircase.max_level_db"),
        ("  start_level_db: 20", "  start_level_db: -.inf", "staircase.start_level_db"),
        ("  start_level_db: 20", "  start_level_db: 1.0e+999", "staircase.start_level_db"),
    ],
)
def test_non_finite_protocol_numbers_are_refused_with_their_line(tmp_path, capsys, old, new, where):
    code, out = cli(capsys, "validate", write(tmp_path, "p.yaml", PROTOCOL.replace(old, new)))
    assert code == 1 and where in out and "is not a finite number" in out
    assert "(line " in out


def test_a_nan_rig_limit_is_refused_by_validate_and_run(tmp_path, capsys):
    # Was: NaN max_level_db_sl let a 40 dB SL masker through validate and run.
    rig = write(tmp_path, "rig.yaml", RIG.replace("max_level_db_sl: 30", "max_level_db_sl: .nan"))
    loud = write(
        tmp_path, "p.yaml", PROTOCOL.replace("masker_level_db_sl: 10", "masker_level_db_sl: 40")
    )
    code, out = cli(capsys, "validate", "--device-config", rig, loud)
    assert code == 2 and "channels.EV.max_level_db_sl (line" in out and "finite" in out
    code, out = cli(capsys, "validate", rig)
    assert code == 1 and "max_level_db_sl" in out
    data = tmp_path / "data"
    code, out = cli(
        capsys, "run", loud, "--participant", "S01", "--data", data, "--device", "sim",
        "--responder", "sim", "--device-config", rig,
    )  # fmt: skip
    assert code == 2 and "finite" in out and not data.exists()


@pytest.mark.parametrize(
    ("old", "new", "where"),
    [
        ("  lapse: 0.02", "  lapse: .nan", "psychometric.lapse"),
        ("MV120: -26.0", "MV120: .inf", "unmasked_al_db_v.MV120"),
        ("slope: 0.711}", "slope: -.inf}", "masking[0].slope"),
    ],
)
def test_non_finite_ground_truth_stops_before_a_log_exists(tmp_path, capsys, old, new, where):
    # Was: a traceback at the header and a 0-byte log.
    truth = write(tmp_path, "truth.yaml", TRUTH.replace(old, new))
    data = tmp_path / "data"
    code, out = cli(
        capsys, "run", shipped("protocols", "baseline.yaml"), "--participant", "S01",
        "--data", data, "--device", "sim", "--responder", "sim", "--ground-truth", truth,
    )  # fmt: skip
    assert code == 2 and where in out and "finite" in out
    assert not list(data.rglob("*.jsonl"))


def test_a_nan_drive_limit_in_the_rig_is_refused_before_a_log_exists(tmp_path, capsys):
    rig = write(tmp_path, "rig.yaml", RIG.replace("max_drive_v: 5.0", "max_drive_v: .nan"))
    data = tmp_path / "data"
    code, out = cli(
        capsys, "run", shipped("protocols", "baseline.yaml"), "--participant", "S01",
        "--data", data, "--device", "sim", "--responder", "sim", "--device-config", rig,
    )  # fmt: skip
    assert code == 2 and "channels.EV.max_drive_v (line" in out
    assert not list(data.rglob("*.jsonl"))


@pytest.mark.parametrize("value", [".inf", "-.inf", ".nan", "1.0e+400", "1e400"])
def test_a_non_finite_scene_target_never_reaches_points_csv(tmp_path, capsys, value):
    scene = write(
        tmp_path, "s.yaml", SCENE.replace("perceived_db_sl: 12", f"perceived_db_sl: {value}")
    )
    out_dir = tmp_path / "out"
    code, out = cli(capsys, "render", scene, "--out", out_dir, "--no-figure")
    assert code == 2 and "texture.perceived_db_sl (line 22)" in out
    assert not (out_dir / "points.csv").exists()


# ------------------------------------------------------------------ duplicate keys


@pytest.mark.parametrize(
    ("name", "text", "where"),
    [
        (
            "scene.yaml",
            SCENE.replace("  perceived_db_sl: 12", "  perceived_db_sl: 12\n  perceived_db_sl: 40"),
            "texture.perceived_db_sl (line 23)",
        ),
        ("truth.yaml", TRUTH + "shift_sd_db: 3.0\n", "shift_sd_db (line"),
        (
            "calibration.json",
            '{"participant": "S01",\n "unmasked_al_db_v": {"EV270": -18,\n "EV270": -30},\n'
            ' "sources": []}',
            "unmasked_al_db_v.EV270 (line 3)",
        ),
    ],
)
def test_duplicate_keys_are_refused_with_their_line(tmp_path, capsys, name, text, where):
    # Was: the last one silently kept (a scene with texture level 12 then 40 rendered at 40).
    code, out = cli(capsys, "validate", write(tmp_path, name, text))
    assert code == 1 and where in out and "appears twice" in out


# ------------------------------------------------------------------ validate: every kind


def test_validate_tells_every_file_kind_apart(tmp_path, capsys):
    data = tmp_path / "data"
    assert main(["run", str(shipped("protocols", "baseline.yaml")), "--participant", "S01",
                 "--data", str(data), "--device", "sim", "--responder", "sim"]) == 0  # fmt: skip
    fit = tmp_path / "fit"
    shifts = shipped("data_schema", "shifts.csv")
    assert main(["fit", str(shifts), "--out", str(fit), "--figures", "none", "--quiet",
                 "--uncertainty", "asymptotic"]) == 0  # fmt: skip
    capsys.readouterr()
    files = {
        "protocol": shipped("protocols", "experiment1.yaml"),
        "usertest": shipped("protocols", "usertest.yaml"),
        "rig config": shipped("protocols", "devices/default.yaml"),
        "ground truth": shipped("protocols", "simulation/ground_truth.yaml"),
        "scene": shipped("protocols", "scenes/bump_rough.yaml"),
        "calibration": data / "S01" / "calibration.json",
        "masking params": fit / "masking_params.json",
        "shifts CSV": shifts,
        "session log": next((data / "S01").glob("*.jsonl")),
    }
    code, out = cli(capsys, "validate", *files.values())
    assert code == 0, out
    lines = out.splitlines()
    assert len(lines) == len(files)
    for (kind, path), line in zip(files.items(), lines, strict=True):
        assert line.startswith(f"ok      {path}: "), line
        assert kind.split()[0] in line.lower() or kind == "protocol", (kind, line)


def test_validate_names_a_file_it_cannot_place(tmp_path, capsys):
    code, out = cli(capsys, "validate", write(tmp_path, "x.json", '{"colour": "blue"}'))
    assert code == 1 and "cannot tell what kind of file this is" in out
    code, out = cli(capsys, "validate", write(tmp_path, "x.yaml", "colour: blue\n"))
    assert code == 1 and "unknown key 'colour'" in out  # YAML: read as a protocol


# ------------------------------------------------------------------ ids, calibration, solver


@pytest.mark.parametrize("participant", ["S" * 300, "S01\n", "S01\r", "../S01", "-S01", ""])
def test_participant_ids_are_matched_whole_with_a_length_limit(tmp_path, capsys, participant):
    # Was: "S01\n" accepted ($ matches before a final newline); 300 characters a traceback.
    data = tmp_path / "data"
    code, out = cli(
        capsys, "run", shipped("protocols", "baseline.yaml"), f"--participant={participant}",
        "--data", data, "--device", "sim", "--responder", "sim",
    )  # fmt: skip
    assert code == 2 and "--participant" in out and "Traceback" not in out
    assert not data.exists() or not any(data.rglob("*.jsonl"))
    assert len(out) < 600  # a 300-character id is not echoed whole


def test_a_broken_calibration_is_refused_before_a_baseline_set_plays(tmp_path, capsys):
    data = tmp_path / "data"
    (data / "S01").mkdir(parents=True)
    (data / "S01" / "calibration.json").write_text('{"participant": "S01", oops', "utf-8")
    code, out = cli(
        capsys, "run", shipped("protocols", "baseline.yaml"), "--participant", "S01",
        "--data", data, "--device", "sim", "--responder", "sim",
    )  # fmt: skip
    assert code == 2 and "calibration.json: line 1" in out
    assert not list(data.rglob("*.jsonl"))  # no set was played


def test_solver_refuses_slopes_outside_its_range_and_infinite_ratings(capsys):
    direct = ("--mv-masked-by-ev", "1,1e300", "--ev-masked-by-mv", "1,0.5")
    code, out = cli(capsys, "solve", *direct, "--mv-target", "5", "--ev-target", "5", "--json")
    assert code == 2 and "slopes up to 100" in out
    ok = ("--mv-masked-by-ev", "1,0.5", "--ev-masked-by-mv", "1,0.5")
    with pytest.raises(SystemExit) as info:  # argparse: a usage error, exit 2
        main(["solve", *ok, "--mv-target", "5", "--ev-target", "5", "--max-mv-db-sl", "inf"])
    assert info.value.code == 2
    assert "'inf' is not a finite number" in capsys.readouterr().err
    code, out = cli(
        capsys, "solve", *ok, "--mv-target", "5,1e300,nan", "--ev-target", "5", "--json"
    )
    doc = json.loads(out)
    assert doc["status"] == ["unique", "none", "none"]
    assert "beyond" in doc["reason"][1]


def test_the_solver_is_not_a_traceback_for_scalar_targets_on_the_fold():
    # Was: TypeError ('numpy.bool' object does not support item assignment) when b·d == 1.
    from masking_lab.rendering.solver import MutualMasking, solve

    sol = solve(MutualMasking(0.0, 1.0, 0.0, 1.0), 0.0, 5.0)
    assert sol.status.shape == ()


def test_an_absurd_shift_is_refused_before_the_fit(tmp_path, capsys):
    # Found by the campaign: a masker level of -1e308 dB SL gave NaN ramps, whose refusal then
    # crashed while the output folder was being cleaned up (TypeError).
    shifts = shipped("data_schema", "shifts.csv").read_text("utf-8")
    bad = write(tmp_path, "s.csv", shifts.replace("MV120,EV270,270,15,", "MV120,EV270,270,-1e308,"))
    code, out = cli(capsys, "fit", bad, "--out", tmp_path / "out", "--figures", "none", "--quiet")
    assert code == 2 and "masker_level_db_sl '-1e308' is outside ±10000" in out


def test_a_user_test_scenes_dir_too_long_for_the_file_system(tmp_path, capsys):
    # Found by the campaign: OSError (file name too long) from the scene lookup.
    text = shipped("protocols", "usertest.yaml").read_text("utf-8")
    path = write(tmp_path, "u.yaml", text.replace("scenes_dir: scenes", "scenes_dir: " + "x" * 250))
    code, out = cli(capsys, "validate", path)
    assert code == 1 and "no scene for geometry" in out and "Traceback" not in out
