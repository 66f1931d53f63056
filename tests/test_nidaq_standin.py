"""The NI-DAQmx back-end against a recording STAND-IN of the ``nidaqmx`` package.

The stand-in (tests/nidaqmx_standin) is not hardware and not NI's driver: it has the API
surface our back-end calls, records every call, and models which level each line holds. These
tests prove the call sequence (commit before start, rate read back and used, abort then 0 V on
STOP / Ctrl-C / SIGTERM, watchdog armed with 0 V expiration states), the error paths and the
identity the log header records. They cannot prove that a real chassis behaves like the model.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import nidaqmx_standin
import numpy as np
import pytest
from hardening_support import short_plan

from masking_lab.core.clock import RealClock
from masking_lab.core.errors import DeviceError, SafetyLimitError
from masking_lab.core.stimulus import parse_stimulus
from masking_lab.device.config import default_device_config, parse_device_config
from masking_lab.device.nidaq import NidaqDevice
from masking_lab.device.registry import open_device
from masking_lab.session.shell import device_record

ROOT = Path(__file__).resolve().parents[1]
EV_LINE, MV_LINE = "cDAQ1Mod1/ao0", "cDAQ1Mod2/ao0"
EV270, MV120 = parse_stimulus("EV270"), parse_stimulus("MV120")


plan = short_plan  # EV270 under MV120, 20 ms stimuli


@pytest.fixture
def standin(monkeypatch):
    state = nidaqmx_standin.install(monkeypatch)
    yield state
    nidaqmx_standin.uninstall()


@pytest.fixture
def device(standin):
    dev = NidaqDevice(default_device_config(), RealClock())
    yield dev
    dev.close()


def trial_task_ids(state) -> list[int]:
    return [c[1] for c in state.ops("cfg_samp_clk_timing") if c[4] > 2]


def index(state, op: str, task_id: int | None = None, *rest) -> int:
    for i, call in enumerate(state.calls):
        same_task = task_id is None or call[1] == task_id
        args = call[2 : 2 + len(rest)]
        if call[0] == op and same_task and tuple(args) == tuple(rest):
            return i
    raise AssertionError(f"{op} {task_id} {rest} not recorded: {state.op_names()}")


def assert_zeroed_after(state, i: int) -> None:
    """A fresh task wrote 0 V to both lines after call ``i``, and both lines hold 0 V."""
    zero_writes = [
        k
        for k, c in enumerate(state.calls)
        if k > i and c[0] == "write" and c[2] == [2] and c[3] is True
    ]
    assert zero_writes, f"no 0 V write after call {i}: {state.op_names()[i:]}"
    assert state.levels == {EV_LINE: 0.0, MV_LINE: 0.0}


def test_standin_identity_has_product_types_serials_chassis_driver_and_watchdog(device):
    ident = device.identity
    assert ident.backend == "nidaq"
    assert ident.model == (f"NI 9264 {EV_LINE} (EV) + NI 9264 {MV_LINE} (MV) in cDAQ-9174 cDAQ1")
    assert ident.serial_number == "cDAQ1Mod1=1D4E5F6, cDAQ1Mod2=1D4E5F7, cDAQ1=1A2B3C4"
    assert "NI-DAQmx 23.5.0" in ident.firmware_version
    assert "20000 S/s" in ident.firmware_version
    assert "watchdog 0 V after 1 s on cDAQ1" in ident.firmware_version
    # What the session log header records for the device.
    header = device_record(ident)
    assert "NI 9264" in header["model"] and "1D4E5F6" in header["serial_number"]
    assert header["max_drive_v"] == {"EV": 5.0, "MV": 10.0}
    assert device.lines == {"EV": EV_LINE, "MV": MV_LINE}


def test_standin_opening_zeroes_and_arms_the_watchdog_with_0v_expiration_states(device, standin):
    assert standin.levels == {EV_LINE: 0.0, MV_LINE: 0.0}
    assert standin.ops("WatchdogTask") == [("WatchdogTask", "cDAQ1", 1.0)]
    (cfg,) = standin.ops("cfg_watchdog_ao_expir_states")
    assert cfg[1] == [(EV_LINE, 0.0, "VOLTAGE"), (MV_LINE, 0.0, "VOLTAGE")]
    assert index(standin, "cfg_watchdog_ao_expir_states") < index(standin, "watchdog.start")
    assert device.watchdog.armed
    # The task's range is the configured limit, so the driver refuses anything beyond it.
    chans = {c[2]: (c[3], c[4]) for c in standin.ops("add_ao_voltage_chan")}
    assert chans == {EV_LINE: (-5.0, 5.0), MV_LINE: (-10.0, 10.0)}


def test_standin_trial_is_committed_before_start_and_finishes_at_0v(device, standin):
    p = plan()
    result = device.play_trial(p, RealClock().now())
    (tid,) = trial_task_ids(standin)
    order = [
        index(standin, "cfg_samp_clk_timing", tid),
        index(standin, "control", tid, "TASK_COMMIT"),
        index(standin, "samp_clk_rate", tid),
        index(standin, "write", tid),
        index(standin, "start", tid),
        index(standin, "is_task_done", tid),
        index(standin, "stop", tid, "done"),
        index(standin, "close", tid),
    ]
    assert order == sorted(order), standin.op_names()
    n = round(p.duration_s * 20000) + 1
    assert standin.ops("write")[-1] == ("write", tid, [2, n], False)
    assert standin.levels == {EV_LINE: 0.0, MV_LINE: 0.0}
    assert result.extra["sample_rate_hz"] == 20000.0
    assert result.played_target_v == 0.5 and result.played_masker_v == 0.3


def test_standin_rate_the_driver_chose_is_read_back_logged_and_used(standin, caplog):
    standin.coerce_rate = lambda requested: 19992.0
    with caplog.at_level(logging.WARNING, logger="masking_lab.device"):
        dev = NidaqDevice(default_device_config(), RealClock())
    try:
        assert dev.sample_rate_hz == 19992.0
        assert "19992 S/s" in dev.identity.firmware_version
        assert any("19992" in r.getMessage() for r in caplog.records)
        p = plan()
        result = dev.play_trial(p, RealClock().now())
        (tid,) = trial_task_ids(standin)
        timing = standin.ops("cfg_samp_clk_timing")[-1]
        n = round(p.duration_s * 19992.0) + 1
        assert timing == ("cfg_samp_clk_timing", tid, 19992.0, "FINITE", n)
        assert standin.ops("write")[-1][2] == [2, n]
        assert result.extra["sample_rate_hz"] == 19992.0
        # Onsets are converted with the rate that really played.
        t0 = result.extra["start_s"]
        assert result.actual_onsets_s[0] == pytest.approx(t0 + round(0.01 * 19992.0) / 19992.0)
    finally:
        dev.close()


def test_standin_rate_changed_for_a_trial_is_refused_before_start(standin):
    dev = NidaqDevice(default_device_config(), RealClock())
    try:
        standin.coerce_rate_after = standin.next_id - 1  # every task from now on
        with pytest.raises(DeviceError, match="changed the sample rate"):
            dev.play_trial(plan(), RealClock().now())
        assert "start" not in standin.op_names()
        assert standin.levels == {EV_LINE: 0.0, MV_LINE: 0.0}
        assert standin.reserved == {}
    finally:
        dev.close()


def test_standin_stop_from_another_thread_aborts_the_trial_then_writes_0v(device, standin):
    standin.polls_until_done = 10**9  # a trial that would play forever
    stopper: list[threading.Thread] = []

    def on_poll(task, n):
        if n == 2:
            stopper.append(threading.Thread(target=device.stop))
            stopper[0].start()

    standin.on_poll = on_poll
    with pytest.raises(DeviceError, match="trial stopped"):
        device.play_trial(plan(), RealClock().now())
    stopper[0].join(timeout=5)
    (tid,) = trial_task_ids(standin)
    aborted = index(standin, "stop", tid, "mid-buffer")
    assert index(standin, "start", tid) < aborted < index(standin, "close", tid)
    # The 0 V write came after the trial task released the lines (else: resource reserved).
    assert_zeroed_after(standin, index(standin, "close", tid))
    assert "playing trial aborted; outputs zeroed" in device.fault_log


def test_standin_ctrl_c_during_a_trial_aborts_it_and_writes_0v(device, standin):
    standin.polls_until_done = 10**9

    def on_poll(task, n):
        if n == 3:
            raise KeyboardInterrupt

    standin.on_poll = on_poll
    with pytest.raises(KeyboardInterrupt):
        device.play_trial(plan(), RealClock().now())
    (tid,) = trial_task_ids(standin)
    assert_zeroed_after(standin, index(standin, "stop", tid, "mid-buffer"))


def test_standin_driver_error_during_a_trial_is_a_device_error_and_0v(device, standin):
    from nidaqmx.errors import DaqError

    standin.fail_on["start"] = DaqError("Onboard device memory underflow.", -200018)
    with pytest.raises(DeviceError, match=r"failed during a trial.*-200018.*0 V"):
        device.play_trial(plan(), RealClock().now())
    assert standin.levels == {EV_LINE: 0.0, MV_LINE: 0.0}
    assert standin.reserved == {}
    assert any("-200018" in f for f in device.fault_log)


def test_standin_over_limit_trial_never_reaches_the_driver(device, standin):
    before = len(standin.calls)
    with pytest.raises(SafetyLimitError):
        device.play_trial(plan(masker_amplitude_v=10.01), RealClock().now())
    assert standin.calls[before:] == []


def test_standin_sigterm_during_a_trial_aborts_it_and_writes_0v(tmp_path):
    trace, levels = tmp_path / "trace.jsonl", tmp_path / "levels.json"
    script = textwrap.dedent(
        f"""
        import atexit, json, sys
        sys.path[:0] = [{str(nidaqmx_standin.SITE)!r}, {str(ROOT)!r}]
        import nidaqmx._standin as standin
        from masking_lab.core.clock import RealClock
        from masking_lab.core.stimulus import parse_stimulus
        from masking_lab.device.base import TrialPlan
        from masking_lab.device.nidaq import NidaqDevice

        st = standin.reset(polls_until_done=10**9)
        st.on_poll = lambda task, n: n == 1 and print("PLAYING", flush=True)
        atexit.register(lambda: open({str(levels)!r}, "w").write(json.dumps(st.levels)))
        dev = NidaqDevice(None, RealClock())
        plan = TrialPlan(parse_stimulus("EV270"), 0.5, 1, parse_stimulus("MV120"), 0.3)
        dev.play_trial(plan, RealClock().now())
        print("FINISHED", flush=True)
        """
    )
    env = {**os.environ, "NIDAQMX_STANDIN_TRACE": str(trace)}
    proc = subprocess.Popen(
        [sys.executable, "-c", script],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        assert line.strip() == "PLAYING", proc.stderr.read() if proc.stderr else line
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert "FINISHED" not in out
    assert proc.returncode == 128 + signal.SIGTERM, err
    calls = [json.loads(x) for x in trace.read_text().splitlines()]
    ops = [c[0] for c in calls]
    started = ops.index("start")
    aborted = next(i for i, c in enumerate(calls) if c[0] == "stop" and c[2] == "mid-buffer")
    zero = next(i for i, c in enumerate(calls) if i > aborted and c[0] == "write" and c[3] is True)
    assert started < aborted < ops.index("close", aborted) < zero
    assert json.loads(levels.read_text()) == {EV_LINE: 0.0, MV_LINE: 0.0}


def test_standin_missing_driver_is_a_device_error_with_the_install_hint(monkeypatch):
    nidaqmx_standin.install(monkeypatch, driver_installed=False)
    try:
        with pytest.raises(DeviceError) as info:
            open_device("nidaq", None, RealClock())
        message = str(info.value)
        assert "NI-DAQmx driver is not installed" in message
        assert "pip install 'masking-lab[nidaq]'" in message
        assert "ni.com" in message and "--device serial:PORT" in message
        assert type(info.value.__cause__).__name__ == "DaqNotFoundError"
    finally:
        nidaqmx_standin.uninstall()


def test_standin_unknown_device_names_the_error_and_the_config(standin):
    with pytest.raises(DeviceError) as info:
        open_device("nidaq:cDAQ9Mod1/ao0,cDAQ9Mod2/ao0", None, RealClock())
    message = str(info.value)
    assert "Device identifier is invalid" in message and "-200220" in message
    assert "NI MAX" in message and "protocols/devices/default.yaml" in message


def test_standin_chassis_without_watchdog_is_reported_and_trials_still_play(standin, caplog):
    with caplog.at_level(logging.WARNING, logger="masking_lab.device"):
        dev = NidaqDevice(default_device_config(), RealClock(), device_name="Dev1")
    try:
        assert dev.lines == {"EV": "Dev1/ao0", "MV": "Dev1/ao1"}
        assert "watchdog unsupported on Dev1" in dev.identity.firmware_version
        assert "-200452" in dev.identity.firmware_version
        assert not dev.watchdog.armed
        assert any("outputs are zeroed by the host only" in r.getMessage() for r in caplog.records)
        assert [c[0] for c in standin.calls].count("watchdog.close") == 1  # not leaked
        dev.play_trial(plan(), RealClock().now())
        assert standin.levels == {"Dev1/ao0": 0.0, "Dev1/ao1": 0.0}
    finally:
        dev.close()


def test_standin_watchdog_is_reset_while_open_and_released_on_close(standin):
    text = (ROOT / "protocols/devices/default.yaml").read_text(encoding="utf-8")
    cfg = parse_device_config(text.replace("watchdog_s: 1.0", "watchdog_s: 0.04"), "fast.yaml")
    dev = NidaqDevice(cfg, RealClock())
    time.sleep(0.15)
    (wd,) = standin.watchdogs
    assert wd.resets >= 3  # every quarter period from the background thread
    dev.close()
    resets = wd.resets
    time.sleep(0.05)
    assert wd.resets == resets and wd.closed
    assert_zeroed_after(standin, 0)
    assert index(standin, "watchdog.stop") > max(
        i for i, c in enumerate(standin.calls) if c[0] == "write"
    )
    dev.close()  # idempotent


def test_standin_expired_watchdog_left_0v_and_is_cleared_before_the_next_trial(device, standin):
    device.play_trial(plan(), RealClock().now())
    (wd,) = standin.watchdogs
    standin.levels[EV_LINE] = 0.5  # as if something had been left on
    wd.expire()  # the hardware's part: the timer ran out
    assert standin.levels == {EV_LINE: 0.0, MV_LINE: 0.0}
    mark = len(standin.calls)
    device.play_trial(plan(), RealClock().now())
    ops = standin.op_names()[mark:]
    assert ops.index("watchdog.clear_expiration") < ops.index("start")
    assert device.watchdog.expirations == 1
    assert any("watchdog had expired" in f for f in device.fault_log)


def test_standin_nidaq_spec_with_one_line_twice_is_refused(standin):
    with pytest.raises(DeviceError, match="not a device or two different lines"):
        open_device(f"nidaq:{EV_LINE},{EV_LINE}", None, RealClock())


def test_standin_buffers_written_are_the_limited_shared_waveforms(device, standin):
    captured = {}
    from nidaqmx.task import Task

    original = Task.write

    def spy(self, data, auto_start=False, timeout=10.0):
        captured.setdefault("data", np.asarray(data)) if not auto_start else None
        return original(self, data, auto_start=auto_start, timeout=timeout)

    Task.write = spy
    try:
        device.play_trial(plan(), RealClock().now())
    finally:
        Task.write = original
    data = captured["data"]
    assert data.shape[0] == 2 and np.all(data[:, 0] == 0.0) and np.all(data[:, -1] == 0.0)
    assert np.max(np.abs(data[0])) == pytest.approx(0.5)
    assert np.max(np.abs(data[1])) == pytest.approx(0.3)


# ---------------------------------------------------------------- issue 23, item 6


def x_series_config():
    """The reference rig wired to one X Series board (the stand-in's Dev1: no watchdog, idle
    output and start-trigger timestamps supported)."""
    text = default_device_config_text().replace(
        "channels: {EV: cDAQ1Mod1/ao0, MV: cDAQ1Mod2/ao0}", "channels: {EV: Dev1/ao0, MV: Dev1/ao1}"
    )
    return parse_device_config(text, "x-series.yaml")


def default_device_config_text() -> str:
    from masking_lab.formats.resources import shipped

    return shipped("protocols", "devices/default.yaml").read_text(encoding="utf-8")


def test_standin_x_series_without_watchdog_is_said_with_what_it_means(standin):
    dev = NidaqDevice(x_series_config(), RealClock())
    try:
        (note,) = dev.notices
        assert "no analog-output watchdog" in note and "X Series" in note
        assert "keeps its last sample" in note and "ends on 0 V" in note
        record = device_record(dev.identity)
        assert record["details"]["notices"] == [note]
        assert record["details"]["watchdog"].startswith("unsupported on Dev1")
    finally:
        dev.close()


def test_standin_cdaq_with_watchdog_has_no_notice(device):
    assert device.notices == [] and device.identity.details["watchdog"].startswith("0 V after")


def test_standin_idle_output_is_zero_volts_where_the_device_allows(standin):
    dev = NidaqDevice(x_series_config(), RealClock())
    try:
        dev.play_trial(plan(), dev.clock.now())
        assert dev.identity.details["idle_output"] == "0 V"
        asked = {c[1] for c in standin.ops("ao_idle_output_behavior") if c[2] == "ZERO_VOLTS"}
        assert asked == {"Dev1/ao0", "Dev1/ao1"}
    finally:
        dev.close()


def test_standin_idle_output_unsupported_is_recorded_and_buffers_still_end_on_0v(device, standin):
    device.play_trial(plan(), device.clock.now())
    assert device.identity.details["idle_output"].startswith("unsupported")
    assert "buffers end on 0 V" in device.identity.details["idle_output"]
    assert standin.levels == {EV_LINE: 0.0, MV_LINE: 0.0}


def test_standin_onsets_come_from_the_hardware_start_trigger_where_supported(standin):
    # The stand-in stamps the start 0.25 s after start() ran: hardware-timed onsets follow
    # the stamp, not the host clock reading before start().
    standin.timestamp_lag_s = 0.25
    dev = NidaqDevice(x_series_config(), RealClock())
    try:
        p = plan()
        result = dev.play_trial(p, dev.clock.now())
        assert result.extra["onsets"] == "hardware start trigger"
        late = [a - q for a, q in zip(result.actual_onsets_s, result.planned_onsets_s, strict=True)]
        assert all(0.2 < d < 0.25 + 0.2 for d in late), late
        spacing = np.diff(result.actual_onsets_s)
        assert spacing == pytest.approx([p.stimulus_s + p.gap_s] * 2, abs=1e-3)
    finally:
        dev.close()


def test_standin_onsets_fall_back_to_the_host_clock_without_timestamps(device):
    result = device.play_trial(plan(), device.clock.now())
    assert result.extra["onsets"] == "host clock at start"
    assert device.identity.details["onsets"] == "host clock at start"


def test_standin_device_locked_by_a_killed_hosts_watchdog_is_reset_at_opening(standin):
    # A previous host was killed: the chassis watchdog expired and nobody cleared it, so the
    # lines refuse writes. Opening resets the device (NI's documented recovery), then 0 V.
    standin.units["cDAQ1"].expired = True
    dev = NidaqDevice(default_device_config(), RealClock())
    try:
        assert [c for c in standin.ops("Device.reset_device") if c[1] == "cDAQ1"]
        (note,) = dev.notices
        assert "reset_device" in note and "0 V" in note
        assert standin.levels == {EV_LINE: 0.0, MV_LINE: 0.0}
        dev.play_trial(plan(), dev.clock.now())
    finally:
        dev.close()


def test_standin_expired_watchdog_that_will_not_clear_is_reset_and_rearmed(device, standin):
    (wd,) = standin.watchdogs
    wd.expire()
    from nidaqmx.errors import DaqError

    standin.fail_on["watchdog.clear_expiration"] = DaqError("cannot clear", -1)
    device.play_trial(plan(), device.clock.now())
    assert [c for c in standin.ops("Device.reset_device") if c[1] == "cDAQ1"]
    assert device.watchdog.armed and device.watchdog.expirations == 1
    assert len(standin.watchdogs) == 2  # a fresh watchdog task after the reset


def test_standin_a_session_on_a_board_without_watchdog_says_so_at_start(standin, tmp_path):
    import io

    from runner_support import write_protocol

    from masking_lab.session.runner import RunOptions, run_session

    protocol = write_protocol(
        tmp_path,
        kind="baseline",
        sets=[{"id": "EV", "target": "EV270"}],
        staircase={"max_trials": 2, "start_level_db": -20},
        timing={"stimulus_s": 0.01, "gap_s": 0.0, "lead_in_s": 0.0, "inter_trial_s": 0.0},
    )
    stream = io.StringIO()
    result = run_session(
        RunOptions(
            protocol, "S01", device="nidaq:Dev1", data_dir=tmp_path / "d", seed=1, real_time=True
        ),
        open_device=lambda spec, clock: NidaqDevice(x_series_config(), clock),
        stream=stream,
    )
    printed = stream.getvalue()
    assert "device: no analog-output watchdog" in printed, printed
    header = json.loads(result.log_path.read_text(encoding="utf-8").splitlines()[0])
    assert "no analog-output watchdog" in header["device"]["details"]["notices"][0]
