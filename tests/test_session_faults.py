"""Runner-level faults through the firmware emulator on a real pseudo-terminal.

Each fault must stop the session with exit code 3 (130 when interrupted), zero both outputs,
leave a log that says what happened and where, print the resume command, and `resume` must then
finish the session exactly as an uninterrupted run with the same seed would have.
"""

from __future__ import annotations

import io
import os
import signal
import time
from pathlib import Path

import pytest
from runner_support import (
    assert_valid_log,
    cli_popen,
    of_kind,
    records,
    timeless,
    trials,
    write_calibration,
    write_device_config,
    write_protocol,
)

from masking_lab.device.config import load_device_config
from masking_lab.device.emulator import FirmwareEmulator
from masking_lab.device.serial_device import SerialDevice
from masking_lab.session.frame import SessionOptions
from masking_lab.session.runner import RunOptions, _default_responder, resume_session, run_session

CAL = {"EV270": -14.0, "MV120": -26.0}
SEED = 7
FAULT_AT = 6  # the 6th trial of the session (set A10, trial_index 5) meets the fault


@pytest.fixture(scope="module")
def lab(tmp_path_factory):
    """A protocol, a fast-failing rig config and the uninterrupted run through the emulator."""
    folder = tmp_path_factory.mktemp("lab")
    protocol = write_protocol(folder, randomize=False)
    config = write_device_config(
        folder,
        serial__reply_timeout_s=0.2,
        serial__done_margin_s=0.3,
        serial__virtual_hang_guard_s=0.3,  # its faults include a board that never answers
    )
    data = folder / "ref"
    write_calibration(data, "S01", CAL)
    ref = run_session(
        RunOptions(protocol, "S01", device="emulator", data_dir=data, seed=SEED),
        stream=io.StringIO(),
    )
    assert ref.exit_code == 0
    return {"protocol": protocol, "config": config, "ref": records(ref.log_path)}


class Emulated:
    """An emulator that outlives the runner's device, so its outputs can be read afterwards."""

    def __init__(self, config_path: Path, *, virtual_time: bool = True, **options) -> None:
        self.config = load_device_config(config_path)
        self.emulator = FirmwareEmulator(self.config, virtual_time=virtual_time, **options).start()

    def open(self, spec: str, clock) -> SerialDevice:
        return SerialDevice(self.emulator.port, self.config, clock, backend="emulator")


class FaultBefore:
    """The real simulated responder; arms an emulator fault just before the n-th trial."""

    name = "sim"

    def __init__(self, inner, arm) -> None:
        self.inner, self.arm, self.seen = inner, arm, 0

    def start_set(self, info) -> None:
        self.inner.start_set(info)

    def trial(self, presentation, play):
        self.seen += 1
        if self.seen == FAULT_AT:
            self.arm()
        return self.inner.trial(presentation, play)

    def close(self) -> None:
        self.inner.close()


def run_with_fault(tmp_path, lab, arm):
    data = tmp_path / "data"
    write_calibration(data, "S01", CAL)
    rig = Emulated(lab["config"])
    stream = io.StringIO()
    result = run_session(
        RunOptions(lab["protocol"], "S01", device="emulator", data_dir=data, seed=SEED),
        open_device=rig.open,
        make_responder=lambda name, ctx: FaultBefore(
            _default_responder(name, ctx), lambda: arm(rig.emulator)
        ),
        stream=stream,
    )
    return result, rig.emulator, stream.getvalue()


def check_fault_logged(result, kind, emulator, printed):
    assert result.exit_code == 3
    recs = assert_valid_log(result.log_path)
    (fault,) = of_kind(recs, "fault")
    assert fault["kind"] == kind
    assert (fault["set_id"], fault["trial_index"]) == ("A10", FAULT_AT - 1)
    assert recs[-1] == fault  # the fault is the log's last word
    assert [t["trial_index"] for t in trials(recs)] == list(range(FAULT_AT - 1))
    assert f"resume with: masking-lab resume {result.log_path}" in printed
    assert f"masking-lab resume {result.log_path}" in result.message
    assert emulator.outputs().zero  # both outputs at 0 V, nothing scheduled
    return fault


def resume_and_compare(lab, log_path, device="emulator"):
    result = resume_session(log_path, SessionOptions(device=device), stream=io.StringIO())
    assert result.exit_code == 0
    recs = assert_valid_log(log_path)
    assert timeless(recs) == timeless(lab["ref"])
    assert recs[-1]["record"] == "session_end"
    return recs


def test_device_unplugged_mid_trial(tmp_path, lab):
    result, emulator, printed = run_with_fault(
        tmp_path, lab, lambda em: em.inject("unplug_on_play")
    )
    fault = check_fault_logged(result, "disconnected", emulator, printed)
    assert "disconnected" in fault["message"]
    assert not emulator.outputs().connected
    assert any("UNPLUG" in line for line in emulator.log_lines())
    emulator.close()
    recs = resume_and_compare(lab, result.log_path)  # plugged in again: a fresh emulator
    assert of_kind(recs, "resume")[0]["device"]["backend"] == "emulator"


def test_garbage_on_the_line(tmp_path, lab):
    result, emulator, printed = run_with_fault(tmp_path, lab, lambda em: em.inject("garbage", 40))
    fault = check_fault_logged(result, "garbage", emulator, printed)
    assert "unframed or corrupted lines" in fault["message"]
    emulator.close()
    resume_and_compare(lab, result.log_path)


def test_a_little_garbage_is_survived_and_counted(tmp_path, lab):
    result, emulator, _ = run_with_fault(tmp_path, lab, lambda em: em.inject("garbage", 3))
    emulator.close()
    assert result.exit_code == 0
    recs = assert_valid_log(result.log_path)
    assert timeless(recs) == timeless(lab["ref"])
    assert of_kind(recs, "fault") == []
    assert trials(recs)[-1]["device_extra"]["garbage_lines"] == 3


def test_corrupted_frames(tmp_path, lab):
    result, emulator, printed = run_with_fault(tmp_path, lab, lambda em: em.inject("bad_crc", 40))
    fault = check_fault_logged(result, "timeout", emulator, printed)
    assert "garbled line" in fault["message"]
    assert emulator.outputs().connected
    emulator.close()  # a board that keeps corrupting frames is replaced
    resume_and_compare(lab, result.log_path)


def test_no_reply(tmp_path, lab):
    result, emulator, printed = run_with_fault(tmp_path, lab, lambda em: em.inject("mute"))
    fault = check_fault_logged(result, "timeout", emulator, printed)
    assert "stopped answering" in fault["message"]
    # The same board answers again: resume through the same port.
    resume_and_compare(lab, result.log_path, device=f"serial:{emulator.port}")
    emulator.close()


def test_a_level_the_device_cannot_drive_is_never_sent(tmp_path, lab):
    data = tmp_path / "data"
    write_calibration(data, "S01", CAL)
    # A20 starts at 30 dB SL = 16 dB re 1 V, above the rig's EV limit of 5 V (14 dB re 1 V).
    sets = [
        {"id": "A10", "masker": "MV120", "masker_level_db_sl": 10},
        {"id": "A20", "masker": "MV120", "masker_level_db_sl": 20, "start_level_db": 30},
    ]
    protocol = write_protocol(tmp_path, sets=sets, randomize=False)
    rig = Emulated(lab["config"])
    result = run_session(
        RunOptions(protocol, "S01", device="emulator", data_dir=data, seed=SEED),
        open_device=rig.open,
        stream=io.StringIO(),
    )
    assert result.exit_code == 0
    recs = assert_valid_log(result.log_path)
    (fault,) = of_kind(recs, "fault")
    assert fault["kind"] == "level_refused" and fault["set_id"] == "A20"
    assert "start level 30 dB SL" in fault["message"]
    end = {e["set_id"]: e for e in of_kind(recs, "set_end")}
    assert end["A20"]["status"] == "aborted" and trials(recs, "A20") == []
    assert end["A10"]["status"] == "completed"
    assert not any("LIMIT" in line for line in rig.emulator.log_lines())
    assert rig.emulator.outputs().zero
    rig.emulator.close()


def test_resumed_on_a_weaker_device_the_rest_is_refused_not_played(tmp_path, lab):
    result, emulator, _ = run_with_fault(tmp_path, lab, lambda em: em.inject("mute"))
    emulator.close()
    # Plugged into a rig whose EV limit (0.5 V = -6 dB re 1 V = 8 dB SL) is below the levels
    # this session needs: the runner refuses rather than asking the device for them.
    weak = write_device_config(tmp_path, channels__EV__max_drive_v=0.5)
    rig = Emulated(weak)
    out = resume_session(result.log_path, open_device=rig.open, stream=io.StringIO())
    assert out.exit_code == 0
    recs = assert_valid_log(result.log_path)
    refused = [f for f in of_kind(recs, "fault") if f["kind"] == "level_refused"]
    assert {f["set_id"] for f in refused} == {"A10", "A20"}
    end = {e["set_id"]: e for e in of_kind(recs, "set_end")}
    assert end["A10"]["status"] == end["A20"]["status"] == "aborted"
    # Nothing was played after the resume: the trials are those from before the fault.
    assert end["A10"]["n_trials"] == len(trials(recs, "A10")) == FAULT_AT - 1
    assert not any("LIMIT" in line for line in rig.emulator.log_lines())
    assert rig.emulator.outputs().zero
    rig.emulator.close()


def test_truncated_last_line_then_resume_through_the_emulator(tmp_path, lab):
    result, emulator, _ = run_with_fault(tmp_path, lab, lambda em: em.inject("mute"))
    lines = result.log_path.read_text().splitlines(keepends=True)
    # Replace the fault record by half a trial record: the crash hit mid-write.
    result.log_path.write_text("".join(lines[:-1]) + lines[-2][: len(lines[-2]) // 2])
    out = resume_session(
        result.log_path, SessionOptions(device=f"serial:{emulator.port}"), stream=io.StringIO()
    )
    emulator.close()
    assert out.exit_code == 0
    recs = assert_valid_log(result.log_path)
    assert timeless(recs) == timeless(lab["ref"])
    assert of_kind(recs, "resume")[0]["dropped_partial_line"] is True


# ---------------------------------------------------------------------------------------------
# The runner as a separate process, the emulator in this one (as a rig's board would be).


def wait_for_trials(log_dir: Path, n: int, proc, timeout: float = 30.0) -> Path:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        logs = list(log_dir.glob("*.jsonl"))
        if logs and len(trials(records(logs[0]))) >= n:
            return logs[0]
        assert proc.poll() is None, proc.communicate()
        time.sleep(0.02)
    raise AssertionError(f"fewer than {n} trials logged in {timeout} s")


TINY_TIMING = {"stimulus_s": 0.01, "gap_s": 0.005, "lead_in_s": 0.005}


def ref_set(lab, set_id="A10"):
    """The reference run's trials of one set, without times."""
    return timeless([r for r in lab["ref"] if r.get("set_id") == set_id])


def start_runner(tmp_path, protocol, port):
    """``masking-lab run`` of set A10 in a subprocess, on the real clock, to the emulator."""
    data = tmp_path / "data"
    write_calibration(data, "S01", CAL)
    proc = cli_popen(
        "run", str(protocol), "--participant", "S01", "--device", f"serial:{port}",
        "--responder", "sim", "--real-time", "--seed", str(SEED), "--data", str(data),
        "--sets", "A10",
    )  # fmt: skip
    return proc, data / "S01"


def wait_zero(emulator, timeout: float = 3.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if emulator.outputs().zero:
            return True
        time.sleep(0.01)
    return False


def test_sigkill_mid_session_then_resume_loses_and_repeats_nothing(tmp_path, lab):
    emulator = FirmwareEmulator(load_device_config(None), virtual_time=False).start()
    try:
        # Same sets and staircase as the reference run, shorter intervals (times are not compared).
        quick = write_protocol(tmp_path, randomize=False, timing=TINY_TIMING)
        proc, folder = start_runner(tmp_path, quick, emulator.port)
        log = wait_for_trials(folder, 6, proc)
        proc.kill()
        proc.communicate(timeout=10)
        assert proc.returncode == -signal.SIGKILL
        # Nobody stops the outputs of a killed host: the firmware watchdog must.
        assert wait_zero(emulator)
        before = log.read_bytes()
        result = resume_session(
            log, SessionOptions(device=f"serial:{emulator.port}"), stream=io.StringIO()
        )
        assert result.exit_code == 0
    finally:
        emulator.close()
    assert log.read_bytes().startswith(before)
    recs = assert_valid_log(log)
    assert recs[0]["clock"] == "real"
    assert timeless(recs) == ref_set(lab)
    assert [f["kind"] for f in of_kind(recs, "fault")] == ["unclean_stop"]
    assert len(of_kind(recs, "resume")) == 1


def test_sigterm_stops_zeroes_and_logs_interrupted(tmp_path, lab):
    emulator = FirmwareEmulator(load_device_config(None), virtual_time=False).start()
    try:
        quick = write_protocol(tmp_path, randomize=False, timing=TINY_TIMING)
        proc, folder = start_runner(tmp_path, quick, emulator.port)
        log = wait_for_trials(folder, 3, proc)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=10)
        assert proc.returncode == 130, err
        assert emulator.outputs().zero
        assert f"Resume with: masking-lab resume {log}" in err
        last = records(log)[-1]
        assert last["record"] == "fault" and last["kind"] == "interrupted"
        assert "SIGTERM" in last["message"]
        result = resume_session(
            log, SessionOptions(device=f"serial:{emulator.port}"), stream=io.StringIO()
        )
        assert result.exit_code == 0
    finally:
        emulator.close()
    recs = assert_valid_log(log)
    assert timeless(recs) == ref_set(lab)
    assert [f["kind"] for f in of_kind(recs, "fault")] == ["interrupted"]  # no unclean_stop


def test_watchdog_trips_when_the_host_goes_quiet_mid_trial(tmp_path, lab):
    slow = write_protocol(
        tmp_path, randomize=False, timing={"stimulus_s": 0.15, "gap_s": 0.05, "lead_in_s": 0.05}
    )
    emulator = FirmwareEmulator(
        load_device_config(None), virtual_time=False, watchdog_s=0.1
    ).start()
    try:
        proc, folder = start_runner(tmp_path, slow, emulator.port)
        log = wait_for_trials(folder, 1, proc)
        for _ in range(10):  # freeze the host while a trial plays
            while not emulator.outputs().playing and proc.poll() is None:
                time.sleep(0.002)
            os.kill(proc.pid, signal.SIGSTOP)
            time.sleep(0.4)
            tripped = any("WATCHDOG" in line for line in emulator.log_lines())
            os.kill(proc.pid, signal.SIGCONT)
            if tripped:
                break
        assert tripped
        assert emulator.outputs().zero
        _, err = proc.communicate(timeout=10)
    finally:
        emulator.close()
    assert proc.returncode == 3, err
    recs = assert_valid_log(log)
    (fault,) = of_kind(recs, "fault")
    assert fault["kind"] == "watchdog" and "watchdog tripped" in fault["message"]
    assert fault["set_id"] == "A10" and fault["trial_index"] == len(trials(recs))
    # resume never opens the port a header names, so the hint repeats it
    assert f"resume with: masking-lab resume {log} --device serial:{emulator.port}" in err
