"""A board's numbers are data to check (issue 21, item 1): every TIME, DONE and HELLO value is
range- and order-checked against the trial it answers. A hostile but checksum-valid board ends
the session with a device fault (exit 3), never a traceback, and nothing is logged as played.
A scripted board on the master side of a real pseudo-terminal; the host is the real one."""

from __future__ import annotations

import io

import pytest
from hardening_support import HELLO, RIG, ScriptedPeer, raw_frame, short_plan, standard
from runner_support import assert_valid_log, of_kind, trials, write_calibration, write_protocol

from masking_lab.core.clock import RealClock, VirtualClock
from masking_lab.core.errors import DeviceProtocolError
from masking_lab.device import protocol as proto
from masking_lab.device.config import parse_device_config
from masking_lab.device.serial_device import SerialDevice
from masking_lab.session.runner import RunOptions, run_session

PLAN = short_plan()  # onsets at +0.01, +0.04, +0.07 s, stimuli of 0.02 s


@pytest.fixture
def peers():
    made: list[ScriptedPeer] = []
    yield made
    for peer in made:
        peer.close()


def open_device(peers, respond) -> SerialDevice:
    peer = ScriptedPeer(respond)
    peers.append(peer)
    return SerialDevice(peer.port, parse_device_config(RIG, "rig"), VirtualClock())


def done_saying(onsets, end=None, tamp=None):
    """A board whose DONE reports ``onsets(at)`` (and ``end(at)``, ``tamp``) for each PLAY."""

    def respond(frame, events):
        if frame.name != "PLAY":
            return None
        events[0] += 1
        at = float(frame.fields["at"])
        on = ",".join(onsets(at))
        stop = end(at) if end else f"{at + 0.09:.6f}"
        amp = tamp if tamp is not None else frame.fields["tamp"]
        body = f"!{events[0]} DONE seq={frame.seq} on={on} end={stop} tamp={amp} mamp=0.3"
        return [proto.encode_ok(frame.seq), raw_frame(body)]

    return respond


def planned(at: float) -> list[float]:
    return [at + 0.01, at + 0.04, at + 0.07]


def fmt(values) -> list[str]:
    return [f"{v:.6f}" for v in values]


HOSTILE = {
    "onsets +1e308": (lambda at: ["1e308", "1e308", "1e308"], None, "is not in 0.."),
    "onsets -1e308": (lambda at: ["-1e308", *fmt(planned(at)[1:])], None, "is not in 0.."),
    "1e9 s late": (lambda at: fmt(p + 1e9 for p in planned(at)), None, "outside its window"),
    "out of order": (
        lambda at: fmt([planned(at)[0], planned(at)[2], planned(at)[1]]),
        None,
        "not strictly increasing",
    ),
    # A firmware that adds offsets in single precision: three onsets collapse to one value.
    "collapsed by precision loss": (
        lambda at: fmt([planned(at)[0]] * 3),
        None,
        "not strictly increasing",
    ),
    "onset 0.5 s early": (lambda at: fmt(p - 0.5 for p in planned(at)), None, "outside its window"),
    "end before the last onset": (
        lambda at: fmt(planned(at)),
        lambda at: f"{at + 0.05:.6f}",
        "end at",
    ),
    "end 1e9 s late": (lambda at: fmt(planned(at)), lambda at: f"{at + 1e9:.6f}", "end at"),
}


@pytest.mark.parametrize("case", sorted(HOSTILE))
def test_a_hostile_done_is_a_device_fault_not_an_onset(peers, case):
    onsets, end, message = HOSTILE[case]
    device = open_device(peers, done_saying(onsets, end))
    with pytest.raises(DeviceProtocolError, match=message) as info:
        device.play_trial(PLAN, 1.0)
    assert "not logged as played" in str(info.value) or "malformed DONE" in str(info.value)
    assert device.fault_log[-1]["kind"] == "DeviceProtocolError"
    device.close()


def test_the_control_board_is_accepted(peers):
    # The same scripted board telling the truth: the failures above are the numbers' fault.
    device = open_device(peers, done_saying(lambda at: fmt(planned(at))))
    result = device.play_trial(PLAN, 1.0)
    assert result.actual_onsets_s == pytest.approx(result.planned_onsets_s, abs=1e-6)
    device.close()


def test_a_played_amplitude_more_than_one_lsb_off_is_refused(peers):
    device = open_device(peers, done_saying(lambda at: fmt(planned(at)), tamp="0.6"))
    with pytest.raises(DeviceProtocolError, match=r"played target amplitude 0\.6 V differs"):
        device.play_trial(PLAN, 1.0)
    device.close()


@pytest.mark.parametrize("t", ["1e300", "9007199255", "-0.5"])
def test_a_huge_or_negative_time_is_a_clean_fault(peers, t):
    # A huge TIME used to become a clock offset, then a PLAY 'at' too long for a frame: a
    # FrameError traceback. Now the TIME reply itself is refused.
    def respond(frame, events):
        if frame.name == "TIME":
            return [raw_frame(f"{frame.seq} OK t={t}")]
        return None

    peer = ScriptedPeer(respond)
    peers.append(peer)
    with pytest.raises(DeviceProtocolError, match="malformed TIME reply"):
        SerialDevice(peer.port, parse_device_config(RIG, "rig"), VirtualClock())


def test_a_time_at_the_edge_of_microsecond_precision_still_plays(peers):
    # 2**53 µs is the largest device time a float64 holds to the µs: accepted, and the trial's
    # 'at' (device time) still fits a frame.
    edge = proto.MAX_DEVICE_TIME_S - 10.0

    def respond(frame, events):
        if frame.name == "TIME":
            return [proto.encode_ok(frame.seq, {"t": edge})]
        return done_saying(lambda at: fmt(planned(at)))(frame, events)

    device = open_device(peers, respond)
    result = device.play_trial(PLAN, 1.0)
    assert result.actual_onsets_s == pytest.approx(result.planned_onsets_s, abs=1e-5)
    device.close()


def test_a_hostile_done_mid_session_exits_3_and_logs_nothing_as_played(tmp_path):
    """Through the runner: the third trial's DONE is 1e9 s late; the log keeps two trials and a
    device fault, and the session ends with exit code 3."""
    plays = [0]

    def respond(frame, events):
        if frame.name != "PLAY":
            return None
        plays[0] += 1
        if plays[0] < 3:
            return standard(frame, events)
        return done_saying(lambda at: fmt(p + 1e9 for p in planned(at)))(frame, events)

    peer = ScriptedPeer(respond)
    rig = parse_device_config(RIG, "rig")
    protocol = write_protocol(tmp_path, randomize=False)
    data = tmp_path / "data"
    write_calibration(data, "S01", {"EV270": -14.0, "MV120": -26.0})
    try:
        result = run_session(
            RunOptions(protocol, "S01", device="emulator", data_dir=data, seed=3),
            open_device=lambda spec, clock: SerialDevice(peer.port, rig, clock, backend="serial"),
            stream=io.StringIO(),
        )
    finally:
        peer.close()
    assert result.exit_code == 3
    recs = assert_valid_log(result.log_path)
    assert len(trials(recs)) == 2
    (fault,) = of_kind(recs, "fault")
    assert fault["kind"] == "garbage" and "outside its window" in fault["message"]
    assert "1000000000" not in str(trials(recs))  # no hostile onset reached the log


def test_a_device_clock_that_steps_back_is_a_clean_fault(peers):
    # Real time: the host reads TIME five times at opening and again before each trial; the
    # reading before the trial is earlier than those at opening.
    times = iter(["100.001", "100.002", "100.003", "100.004", "100.005", "50.0"])

    def respond(frame, events):
        if frame.name == "HELLO":
            return [proto.encode_ok(frame.seq, {**HELLO, "vt": 0})]
        if frame.name == "TIME":
            return [raw_frame(f"{frame.seq} OK t={next(times)}")]
        return None

    peer = ScriptedPeer(respond)
    peers.append(peer)
    device = SerialDevice(peer.port, parse_device_config(RIG, "rig"), RealClock())
    with pytest.raises(DeviceProtocolError, match="the device clock stepped back"):
        device.play_trial(PLAN, device.clock.now() + 0.05)
    device.close()


def test_a_done_without_its_end_is_a_protocol_fault(peers):
    def respond(frame, events):
        if frame.name != "PLAY":
            return None
        on = ",".join(fmt(planned(float(frame.fields["at"]))))
        body = f"!1 DONE seq={frame.seq} on={on} tamp={frame.fields['tamp']} mamp=0.3"
        return [proto.encode_ok(frame.seq), raw_frame(body)]

    device = open_device(peers, respond)
    with pytest.raises(DeviceProtocolError, match="lacks field 'end'"):
        device.play_trial(PLAN, 1.0)
    device.close()
