"""A simulated user-test study through the firmware emulator over real pseudo-terminals.

Simulated participants sit the baseline the user test asks for, then the user test itself on the
emulator (virtual clock); their logs validate against the schema, `usertest-report` analyses them
and compensation helps in the paper's direction. A runner killed with SIGKILL, and device faults
in the middle of a trial, resume to exactly the trials an uninterrupted run logs.
"""

from __future__ import annotations

import io
import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import jsonschema
import pytest
from usertest_support import (
    REPO,
    of_kind,
    records,
    timeless,
    trials,
    write_calibration,
    write_ground_truth,
    write_params,
    write_rig,
    write_usertest,
)

from masking_lab.core.errors import CalibrationError
from masking_lab.device.config import load_device_config
from masking_lab.device.emulator import FirmwareEmulator
from masking_lab.device.serial_device import SerialDevice
from masking_lab.formats.schemas import load_schema
from masking_lab.session.frame import SessionOptions
from masking_lab.session.runner import RunOptions, run_session
from masking_lab.simulation.observer import load_ground_truth, make_participant
from masking_lab.usertest.runner import (
    UserTestOptions,
    default_responder,
    resume_usertest,
    run_usertest,
)

PARTICIPANTS = ("S01", "S02", "S03", "S04")
STIMULI = ("EV270", "MV120am40", "MV180", "MV270")


@pytest.fixture(scope="module")
def lab(tmp_path_factory):
    folder = tmp_path_factory.mktemp("study")
    return {
        "folder": folder,
        "protocol": write_usertest(folder, repeats=1),  # 24 trials per participant
        "params": write_params(folder / "masking_params.json"),
        # A rig with 20 dB more amplifier gain than the shipped ground truth assumes: every
        # compensated input then fits the reference rig's drive limits; the rig allows 65 dB SL.
        "gt": write_ground_truth(folder / "ground_truth.yaml", shift_db=-20.0),
        "rig": write_rig(folder, max_level_db_sl=65.0),
    }


def options(lab, data: Path, participant: str = "S01", **changes) -> UserTestOptions:
    base = dict(
        protocol=lab["protocol"],
        participant=participant,
        device="emulator",
        responder="sim",
        data_dir=data,
        params=lab["params"],
        seed=100 + PARTICIPANTS.index(participant) if participant in PARTICIPANTS else 7,
        ground_truth=lab["gt"],
        device_config=lab["rig"],
        progress=False,
    )
    base.update(changes)
    return UserTestOptions(**base)


def true_calibration(lab, data: Path, participant: str) -> None:
    person = make_participant(load_ground_truth(lab["gt"]), participant, 0)
    write_calibration(data, participant, {k: person.unmasked_al_db_v[k] for k in STIMULI})


def assert_valid(path: Path) -> list[dict]:
    schema = load_schema("session_log")
    validator = jsonschema.validators.validator_for(schema)(schema)
    recs = records(path)
    for i, rec in enumerate(recs, start=1):
        errors = list(validator.iter_errors(rec))
        assert not errors, f"{path} line {i}: {errors[0].message[:300]}"
    return recs


@pytest.fixture(scope="module")
def study(lab):
    """Each participant: the baseline the user test asks for, then the user test (emulator)."""
    data = lab["folder"] / "data"
    logs = []
    for k, participant in enumerate(PARTICIPANTS):
        with pytest.raises(CalibrationError) as refused:
            run_usertest(options(lab, data, participant))
        baseline = data / "baseline_EV270_MV120am40_MV180_MV270.yaml"
        assert str(baseline) in str(refused.value)
        cal = run_session(
            RunOptions(
                baseline, participant, device="sim", data_dir=data, seed=10 + k,
                ground_truth=lab["gt"], progress=False,
            ),
            stream=io.StringIO(),
        )  # fmt: skip
        assert cal.exit_code == 0
        result = run_usertest(options(lab, data, participant), stream=io.StringIO())
        assert result.exit_code == 0, result.message
        logs.append(result.log_path)
    return {"data": data, "logs": logs}


def test_simulated_study_logs_validate_and_use_the_emulator(study):
    for log in study["logs"]:
        recs = assert_valid(log)
        header = recs[0]
        assert header["kind"] == "usertest" and header["device"]["backend"] == "emulator"
        assert header["clock"] == "virtual" and header["usertest"]["clipped_objects"] == []
        ts = trials(recs)
        assert [t["trial"] for t in ts] == list(range(24))
        assert all(t["n_frames"] > 0 and "clipped" not in t for t in ts)
        assert recs[-1]["record"] == "session_end"


def test_compensation_helps_in_the_papers_direction(study, tmp_path, capsys):
    from masking_lab.commands.cli import main

    out = tmp_path / "report"
    assert main(["usertest-report", str(study["data"]), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "4 session(s), 96 trials" in printed
    for name in ("rates.csv", "summary.csv", "tests.csv", "report.txt", "figure8a.png"):
        assert (out / name).stat().st_size > 0
    assert (out / "figure8a.png").read_bytes().startswith(b"\x89PNG\r\n\x1a\n")
    import csv

    rates = list(csv.DictReader((out / "rates.csv").open(encoding="utf-8")))
    by = {(r["participant"], r["condition"]): r for r in rates}
    for p in PARTICIPANTS:
        comp, unc = by[(p, "compensated")], by[(p, "uncompensated")]
        # Paper Figure 8a: "both" and "geometry" clearly better with compensation.
        assert float(comp["both"]) > float(unc["both"])
        assert float(comp["geometry"]) > float(unc["geometry"])
    tests = {r["measure"]: r for r in csv.DictReader((out / "tests.csv").open(encoding="utf-8"))}
    assert float(tests["both"]["mean_difference"]) > 0.15
    assert float(tests["geometry"]["mean_difference"]) > 0.15
    assert float(tests["both"]["t"]) > 0 and float(tests["both"]["p"]) < 0.05


# ---------------------------------------------------------------------------------------------
# Kill and faults, then resume


@pytest.fixture(scope="module")
def reference(lab):
    """The uninterrupted session (simulated device: the records do not depend on the device)."""
    data = lab["folder"] / "ref"
    true_calibration(lab, data, "S09")
    opts = options(lab, data, "S09", device="sim", protocol=lab["protocol"])
    result = run_usertest(opts, stream=io.StringIO())
    assert result.exit_code == 0
    return records(result.log_path)


def wait_for_trials(folder: Path, n: int, proc, timeout: float = 30.0) -> Path:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        logs = list(folder.glob("*.jsonl"))
        if logs and len(trials(records(logs[0]))) >= n:
            return logs[0]
        assert proc.poll() is None, proc.communicate()
        time.sleep(0.01)
    raise AssertionError(f"fewer than {n} trials logged in {timeout} s")


def cli(*args: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "masking_lab.commands.cli", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=REPO,
    )


def test_sigkill_mid_session_then_resume_loses_and_repeats_nothing(lab, reference, tmp_path):
    data = tmp_path / "data"
    true_calibration(lab, data, "S09")
    proc = cli(
        "run", str(lab["protocol"]), "--participant", "S09", "--device", "emulator",
        "--responder", "sim", "--params", str(lab["params"]), "--data", str(data),
        "--seed", "7", "--ground-truth", str(lab["gt"]), "--device-config", str(lab["rig"]),
        "--no-progress",
    )  # fmt: skip
    log = wait_for_trials(data / "S09", 5, proc)
    proc.send_signal(signal.SIGKILL)
    proc.communicate(timeout=10)
    assert proc.returncode == -signal.SIGKILL
    before = log.read_bytes()
    n_before = len(trials(records(log)))
    assert 5 <= n_before < 24, "the kill came after the session ended; nothing was tested"
    resumed = subprocess.run(
        # Resume opens no file the log names by itself: the rig config is named again.
        [
            *(sys.executable, "-m", "masking_lab.commands.cli", "resume", str(log)),
            *("--no-progress", "--device-config", str(lab["rig"])),
        ],
        capture_output=True,
        text=True,
        cwd=REPO,
        timeout=60,
    )
    assert resumed.returncode == 0, resumed.stderr
    assert "user test: 24 of 24 trials logged" in resumed.stdout
    assert log.read_bytes().startswith(before.rsplit(b"\n", 1)[0])
    recs = assert_valid(log)
    assert [t["trial"] for t in trials(recs)] == list(range(24))  # none lost, none twice
    assert timeless(recs) == timeless(reference)
    (fault,) = of_kind(recs, "fault")
    assert fault["kind"] == "unclean_stop" and fault["trial_index"] == n_before
    assert len(of_kind(recs, "resume")) == 1


class Emulated:
    """An emulator that outlives the runner's device, so it can be faulted and inspected."""

    def __init__(self, config_path: Path) -> None:
        self.config = load_device_config(config_path)
        self.emulator = FirmwareEmulator(self.config, virtual_time=True).start()

    def open(self, spec: str, clock) -> SerialDevice:
        return SerialDevice(self.emulator.port, self.config, clock, backend="emulator")


class FaultAt:
    """The device, except that the n-th amplitude update first arms a fault in the emulator."""

    def __init__(self, device, n: int, arm) -> None:
        self.device, self.n, self.arm, self.calls = device, n, arm, 0
        self.identity = device.identity

    def set_amplitude(self, channel, stimulus, amplitude_v):
        self.calls += 1
        if self.calls == self.n:
            self.arm()
        return self.device.set_amplitude(channel, stimulus, amplitude_v)

    def play_trial(self, plan, start_s):
        return self.device.play_trial(plan, start_s)

    def stop(self):
        self.device.stop()

    def close(self):
        self.device.close()


@pytest.mark.parametrize(
    "fault, kind",
    # A board gone mute in a virtual-time session: the host has no wall-clock reply timeout
    # there (load must not trip it), so the board's own watchdog ends the session.
    [("unplug", "disconnected"), ("mute", "watchdog")],
)
def test_device_fault_mid_trial_then_resume(lab, reference, tmp_path, fault, kind):
    rig_path = write_rig(tmp_path, max_level_db_sl=65.0)
    text = rig_path.read_text(encoding="utf-8").replace(
        "reply_timeout_s: 0.5", "reply_timeout_s: 0.2"
    )
    rig_path.write_text(text, encoding="utf-8")
    rig = Emulated(rig_path)
    arm = rig.emulator.unplug if fault == "unplug" else lambda: rig.emulator.inject("mute")
    data = tmp_path / "data"
    true_calibration(lab, data, "S09")
    out = io.StringIO()
    try:
        result = run_usertest(
            options(lab, data, "S09", device_config=rig_path, protocol=lab["protocol"]),
            open_device=lambda spec, clock: FaultAt(rig.open(spec, clock), 1000, arm),
            stream=out,
        )
        assert rig.emulator.outputs().zero  # both outputs at 0 V after the fault
    finally:
        rig.emulator.close()
    assert result.exit_code == 3
    recs = assert_valid(result.log_path)
    (logged_fault,) = of_kind(recs, "fault")
    assert logged_fault["kind"] == kind and recs[-1] == logged_fault
    n = len(trials(recs))
    assert 0 < n < 24 and logged_fault["trial_index"] == n  # the trial in flight is not logged
    assert f"masking-lab resume {result.log_path}" in out.getvalue()
    resumed = resume_usertest(
        result.log_path, SessionOptions(device_config=rig_path), stream=io.StringIO()
    )
    assert resumed.exit_code == 0
    recs = assert_valid(result.log_path)
    assert timeless(recs) == timeless(reference)
    assert [r["kind"] for r in of_kind(recs, "fault")] == [kind]


def test_the_report_reads_what_the_runner_wrote(study):
    """Logs → records → the pure analysis: nothing is lost between the runner and the report."""
    from masking_lab.usertest.report import collect_usertest

    data = collect_usertest(study["data"])
    assert len(data.records) == 96 and len(data.sessions) == 4
    assert {s["log"].split("/")[1].split("-")[0] for s in data.skipped} == {
        "baseline_EV270_MV120am40_MV180_MV270"
    }
    logged = [json.dumps(t, sort_keys=True) for log in study["logs"] for t in trials(records(log))]
    assert sorted(json.dumps(r, sort_keys=True) for r in data.records) == sorted(logged)


def test_default_responder_refuses_an_unknown_name(lab):
    from masking_lab.core.errors import MaskingLabError

    with pytest.raises(MaskingLabError, match="mouse"):
        default_responder("mouse", None)  # type: ignore[arg-type]
