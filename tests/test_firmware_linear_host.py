"""The host's side of the output's linear range: HELLO ``lin`` is range-checked, the converter
in force takes it, and a level the board could play only clipped is stepped to another
attenuator step or refused before a frame is sent (naming the level and the range)."""

from __future__ import annotations

import pytest
from hardening_support import HELLO, RIG, ScriptedPeer, raw_frame, short_plan

from masking_lab.core.clock import VirtualClock
from masking_lab.core.errors import DeviceProtocolError, SafetyLimitError
from masking_lab.core.stimulus import parse_stimulus
from masking_lab.device import protocol as proto
from masking_lab.device.config import parse_device_config
from masking_lab.device.levels_range import Converter, unplayable
from masking_lab.device.serial_checks import choose_steps, converters_from
from masking_lab.device.serial_device import SerialDevice

REF = Converter(12, 10.0, (0.0, 20.0, 40.0), linear_codes=1798)


def hello_frame(**fields: object) -> proto.Frame:
    base = {**HELLO, "bits_ev": 12, "bits_mv": 12, "att": "0,20,40", **fields}
    return proto.decode(proto.encode_ok(1, base))


# ------------------------------------------------------------------ HELLO lin


def test_hello_lin_is_read_per_channel_and_absent_means_the_whole_converter():
    assert proto.parse_hello(hello_frame(lin="1798,2047")).linear_codes == {
        "EV": 1798,
        "MV": 2047,
    }
    assert proto.parse_hello(hello_frame()).linear_codes == {}  # firmware before the field


@pytest.mark.parametrize(
    "value",
    ["0,1798", "1798,2048", "1798", "1798,1798,1798", "a,b", "1798.5,1798", "nan,1", "-1798,1798"],
)
def test_a_hello_lin_out_of_range_is_a_frame_error(value):
    with pytest.raises(proto.FrameError, match=r"lin=.* must be two whole code counts"):
        proto.parse_hello(hello_frame(lin=value))


def test_a_board_sending_a_bad_lin_is_a_clean_protocol_fault():
    def respond(frame, events):
        if frame.name == "HELLO":
            fields = {**HELLO, "lin": "1798,0"}
            body = " ".join(f"{k}={v}" for k, v in fields.items())
            return [raw_frame(f"{frame.seq} OK {body}")]
        return None

    peer = ScriptedPeer(respond)
    try:
        with pytest.raises(DeviceProtocolError, match=r"malformed HELLO.*lin='1798,0'"):
            SerialDevice(peer.port, parse_device_config(RIG, "rig"), VirtualClock())
    finally:
        peer.close()


def test_the_converter_in_force_takes_the_board_lin_and_refuses_a_config_beyond_it():
    hello = proto.parse_hello(hello_frame(lin="1798,1798"))
    # a config without a converter, or without linear_codes: the board's
    board_only = converters_from("/dev/x", hello, {}, "rig.yaml")
    assert board_only["MV"].max_code == 1798
    plain = Converter(12, 10.0, (0.0, 20.0, 40.0), min_lsb=50)
    adopted = converters_from("/dev/x", hello, {"EV": plain, "MV": plain}, "rig.yaml")
    assert adopted["EV"].max_code == 1798 and adopted["EV"].min_lsb == 50
    # a config narrower than the board stays; one wider could clip: a mismatch
    narrow = Converter(12, 10.0, (0.0, 20.0, 40.0), linear_codes=1500)
    assert converters_from("/dev/x", hello, {"MV": narrow}, "rig.yaml")["MV"].max_code == 1500
    wide = Converter(12, 10.0, (0.0, 20.0, 40.0), linear_codes=2000)
    with pytest.raises(DeviceProtocolError, match=r"MV: linear range 1798 codes \(config 2000\)"):
        converters_from("/dev/x", hello, {"MV": wide}, "rig.yaml")


def test_the_rig_config_reads_linear_codes():
    rig = RIG.replace(
        "MV: {max_drive_v: 8}",
        "MV: {max_drive_v: 8, converter: {bits: 12, full_scale_v: 10, linear_codes: 1798}}",
    )
    config = parse_device_config(rig, "rig")
    assert config.converters["MV"].linear_codes == 1798
    assert config.rig_record()["channels"]["MV"]["converter"]["linear_codes"] == 1798


# ------------------------------------------------------------------ step choice and refusal


def test_fits_counts_codes_as_the_firmware_rounds_them():
    assert REF.fits(0.0878, 40.0) and not REF.fits(0.08783, 40.0)  # 1798 / 1799 codes
    assert REF.fits(8.779, 0.0) and not REF.fits(8.7818, 0.0)
    # one channel's target and masker: rounded one by one, then added
    assert REF.fits([0.043945, 0.043848], 40.0)  # 900 + 898
    assert not REF.fits([0.043945, 0.043896], 40.0)  # 900 + 899
    # without a linear range the converter's 2047 codes bound it
    assert Converter(12, 10.0, (0.0, 40.0)).fits(0.0999, 40.0)


def test_a_pair_beyond_the_linear_range_at_the_deep_step_is_stepped_up():
    # MV target 30 mV spans 6 LSBs at 0 dB, so the host aims for 20 dB; with the 0.86 V masker
    # on the same channel that needs 61 + 1761 = 1822 codes there: beyond 1798, so 0 dB.
    plan = short_plan(
        target=parse_stimulus("MV270"),
        target_amplitude_v=0.03,
        masker=parse_stimulus("MV120"),
        masker_amplitude_v=0.86,
    )
    whole = Converter(12, 10.0, (0.0, 20.0, 40.0))
    assert choose_steps(plan, {"EV": whole, "MV": whole}, "trial 1").target_db == 20.0
    steps = choose_steps(plan, {"EV": REF, "MV": REF}, "trial 1")
    assert (steps.target_db, steps.masker_db) == (0.0, 0.0)


def test_a_level_beyond_the_linear_range_at_every_step_is_refused_before_sending():
    plan = short_plan(target=parse_stimulus("MV270"), target_amplitude_v=9.0, masker=None)
    with pytest.raises(SafetyLimitError) as info:
        choose_steps(plan, {"EV": REF, "MV": REF}, "trial 7")
    text = str(info.value)
    assert text.startswith("trial 7: MV amplitude 9 V exceeds the output's linear range")
    assert "1798 codes, 8.7793 V" in text and "nothing was sent" in text


def test_unplayable_survives_a_level_no_step_plays_linearly():
    assert unplayable(REF, [9.0]) == [(9.0, float("inf"))]


def test_the_emulator_refuses_a_linear_range_its_converter_cannot_have():
    from masking_lab.device.emulator import FirmwareEmulator

    with pytest.raises(ValueError, match=r"linear_codes=2048 must be .* in 1\.\.2047"):
        FirmwareEmulator(linear_codes=2048)
    assert FirmwareEmulator(linear_codes=1500).checker.converters["EV"].lin == 1500
