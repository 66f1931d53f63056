"""Device (rig) config: the reference rig loads; every malformed file is named precisely."""

from __future__ import annotations

import json

import pytest

from masking_lab.core.errors import DeviceConfigError, ProtocolError
from masking_lab.device.config import load_device_config
from masking_lab.device.rig_limits import max_level_db_sl

GOOD = """\
schema_version: 1
name: test-rig
channels:
  EV: {max_drive_v: 2.5, max_level_db_sl: 25}
  MV: {max_drive_v: 8}
serial:
  reply_timeout_s: 0.2
  boot_timeout_s: 1.0
  hello_retry_s: 0.1
  watchdog_s: 0.3
waveform: {sample_rate_hz: 10000, ramp_s: 0.005}
display: {width_mm: 300, width_px: 1920, height_px: 1080}
"""


def write(tmp_path, text, name="rig.yaml"):
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


def test_reference_rig_loads_and_has_display_and_limits():
    cfg = load_device_config()
    assert set(cfg.limits.max_drive_v) == {"EV", "MV"}
    assert all(0 < v <= 10 for v in cfg.limits.max_drive_v.values())
    assert cfg.display is not None and cfg.display.width_px > 0
    assert cfg.serial.watchdog_s > 0
    # The protocol validator reads the same file for its dB SL limits.
    assert max_level_db_sl(None) == dict(cfg.max_level_db_sl)


def test_values_are_read(tmp_path):
    cfg = load_device_config(write(tmp_path, GOOD))
    assert cfg.name == "test-rig"
    assert dict(cfg.limits.max_drive_v) == {"EV": 2.5, "MV": 8.0}
    assert dict(cfg.max_level_db_sl) == {"EV": 25.0}
    assert (cfg.serial.reply_timeout_s, cfg.serial.watchdog_s) == (0.2, 0.3)
    assert cfg.serial.baud_rate == 115200  # default kept
    assert (cfg.waveform.sample_rate_hz, cfg.waveform.ramp_s) == (10000.0, 0.005)
    assert (cfg.display.width_mm, cfg.display.width_px, cfg.display.height_px) == (300, 1920, 1080)


def test_minimal_config_gets_defaults_and_no_display(tmp_path):
    cfg = load_device_config(
        write(
            tmp_path,
            "schema_version: 1\nchannels:\n  EV: {max_drive_v: 1}\n  MV: {max_drive_v: 1}\n",
        )
    )
    assert cfg.display is None
    assert cfg.name == "rig"
    assert cfg.waveform.sample_rate_hz == 20000


BAD = {
    "unknown_key": (
        ("  MV: {max_drive_v: 8}", "  MV: {max_drive_v: 8, max_drive: 3}"),
        "channels.MV.max_drive (line 5)",
        "unknown key 'max_drive'",
    ),
    "missing_limit": (
        ("  MV: {max_drive_v: 8}", "  MV: {}"),
        "channels.MV (line 5)",
        "missing required key 'max_drive_v' (peak V at the board output); or give "
        "amplifier.max_input_v",
    ),
    "missing_channel": (("  MV: {max_drive_v: 8}\n", ""), "channels (line 3)", "'MV'"),
    "above_dac_range": (
        ("max_drive_v: 2.5", "max_drive_v: 400"),
        "channels.EV.max_drive_v (line 4)",
        "above 10 V",
    ),
    "zero_limit": (
        ("max_drive_v: 2.5", "max_drive_v: 0"),
        "channels.EV.max_drive_v (line 4)",
        "must be > 0",
    ),
    "wrong_type": (
        ("reply_timeout_s: 0.2", "reply_timeout_s: fast"),
        "serial.reply_timeout_s (line 7)",
        "must be of type number",
    ),
    "bad_schema_version": (
        ("schema_version: 1", "schema_version: 2"),
        "schema_version (line 1)",
        "must be 1",
    ),
    "display_incomplete": ((", height_px: 1080", ""), "display (line 12)", "'height_px'"),
    "retry_longer_than_boot": (
        ("hello_retry_s: 0.1", "hello_retry_s: 5"),
        "serial.hello_retry_s",
        "must not exceed serial.boot_timeout_s",
    ),
    "same_ao_line": (
        (GOOD, GOOD + "nidaq: {channels: {EV: cDAQ1Mod1/ao0, MV: cDAQ1Mod1/ao0}}\n"),
        "nidaq.channels (line 13)",
        "its own analog output",
    ),
    "old_ao_channels_key": (
        (GOOD, GOOD + "nidaq: {device: cDAQ1Mod1, ao_channels: {EV: ao0, MV: ao1}}\n"),
        "nidaq.ao_channels (line 13)",
        "replaced by nidaq.channels",
    ),
    "line_without_device": (
        (GOOD, GOOD + "nidaq: {channels: {EV: ao0, MV: cDAQ1Mod2/ao0}}\n"),
        "nidaq.channels.EV (line 13)",
        "write DEVICE/aoN",
    ),
    "nan_limit": (
        ("max_drive_v: 2.5", "max_drive_v: .nan"),
        "channels.EV.max_drive_v (line 4)",
        "not a finite number",
    ),
    "infinite_gain": (
        (
            GOOD,
            GOOD.replace(
                "MV: {max_drive_v: 8}", "MV: {max_drive_v: 8, amplifier: {model: X, gain_db: .inf}}"
            ),
        ),
        "channels.MV.amplifier.gain_db (line 5)",
        "not a finite number",
    ),
    "limit_above_amplifier_input": (
        (
            "MV: {max_drive_v: 8}",
            "MV: {max_drive_v: 8, amplifier: {model: TI DRV8662, max_input_v: 1.8}}",
        ),
        "channels.MV.max_drive_v (line 5)",
        "8 V at the input of the TI DRV8662 exceeds its max_input_v of 1.8 V; lower max_drive_v "
        "to at most 1.8 V",
    ),
    "limit_above_amplifier_input_through_attenuator": (
        (
            "MV: {max_drive_v: 8}",
            "MV: {max_drive_v: 8, amplifier: {model: A, max_input_v: 1.8},"
            " attenuator: {model: divider, ratio: 0.5}}",
        ),
        "channels.MV.max_drive_v (line 5)",
        "attenuator ratio 0.5 = 4 V at the input of the A exceeds its max_input_v of 1.8 V; "
        "lower max_drive_v to at most 3.6 V",
    ),
    "attenuator_gain_above_one": (
        ("MV: {max_drive_v: 8}", "MV: {max_drive_v: 8, attenuator: {model: amp, ratio: 2}}"),
        "channels.MV.attenuator.ratio (line 5)",
        "ratio 2 is not in (0, 1]",
    ),
    "no_limit_and_no_amplifier_input": (
        ("MV: {max_drive_v: 8}", "MV: {amplifier: {model: A}}"),
        "channels.MV (line 5)",
        "missing required key 'max_drive_v'",
    ),
    "same_carrier_measured_twice": (
        (
            "MV: {max_drive_v: 8}",
            "MV: {max_drive_v: 8, measured_gain: [{frequency_hz: 120, v_out_per_v_in: 50},"
            " {frequency_hz: 120, v_out_per_v_in: 51}]}",
        ),
        "channels.MV.measured_gain[1].frequency_hz (line 5)",
        "120 Hz is measured twice",
    ),
    "bad_yaml": (("name: test-rig", "name: [unclosed"), "line", "malformed YAML"),
    "python_tag": (
        ("name: test-rig", "name: !!python/object/apply:os.system [ls]"),
        "line 2",
        "not allowed",
    ),
    "not_a_mapping": ((GOOD, "- a\n- b\n"), "line 1", "YAML mapping"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_malformed_config_names_file_key_and_line(tmp_path, case):
    (old, new), where, what = BAD[case]
    assert old in GOOD, f"test setup: {old!r} not in GOOD"
    path = write(tmp_path, GOOD.replace(old, new, 1))
    with pytest.raises(DeviceConfigError) as info:
        load_device_config(path)
    err = info.value
    assert isinstance(err, ProtocolError)  # the CLI prints it like any config error
    assert err.file == str(path)
    assert where in err.where or where in str(err), str(err)
    assert what in str(err), str(err)


def test_unreadable_file(tmp_path):
    with pytest.raises(DeviceConfigError, match="cannot read the device config"):
        load_device_config(tmp_path / "missing.yaml")


RIG = """\
schema_version: 1
name: rig-with-record
channels:
  EV:
    max_drive_v: 2.0
    amplifier: {model: HV amp, gain_db: 40}
    transducer: touch panel
    measured_gain:
      - {frequency_hz: 270, v_out_per_v_in: 98.5}
  MV:
    amplifier: {model: TI DRV8662, gain_db: 40.7, max_input_v: 1.8, setting: GAIN1=1 GAIN0=1}
    attenuator: {model: 2:1 divider, ratio: 0.5}
    transducer: 4 piezo actuators
    measured_gain:
      - {frequency_hz: 270, v_out_per_v_in: 40.0}
      - {frequency_hz: 120, v_out_per_v_in: 52.0}
"""


def test_reference_rig_limits_match_the_papers_parts():
    cfg = load_device_config()
    # TI DRV8662: every gain setting reaches its full output from a 1.8 V peak input; the
    # reference rig reaches it from a 10 V board output through its 0.18 divider.
    mv = cfg.rig["MV"]
    assert mv.attenuator is not None
    assert cfg.limits.max_drive_v["MV"] * mv.attenuator.ratio == pytest.approx(1.8)
    assert mv.amplifier is not None and mv.amplifier.model == "Texas Instruments DRV8662"
    assert (mv.amplifier.gain_db, mv.amplifier.max_input_v) == (40.7, 1.8)
    assert "SQV 3/500" in cfg.rig["EV"].amplifier.model
    assert cfg.nidaq.channels == {"EV": "cDAQ1Mod1/ao0", "MV": "cDAQ1Mod2/ao0"}
    assert cfg.nidaq.watchdog_s > 0


def test_attenuator_scales_the_derived_board_limit(tmp_path):
    cfg = load_device_config(write(tmp_path, RIG))
    # No max_drive_v for MV: 1.8 V at the driver input through a 0.5 divider is 3.6 V out.
    assert cfg.limits.max_drive_v == {"EV": 2.0, "MV": 3.6}


def test_derived_limit_never_exceeds_the_board_range(tmp_path):
    text = RIG.replace("ratio: 0.5", "ratio: 0.1")
    assert load_device_config(write(tmp_path, text)).limits.max_drive_v["MV"] == 10.0


def test_rig_record_is_plain_json_with_every_field(tmp_path):
    record = load_device_config(write(tmp_path, RIG)).rig_record()
    assert json.loads(json.dumps(record)) == record
    assert record["name"] == "rig-with-record" and record["config"].endswith("rig.yaml")
    ev, mv = record["channels"]["EV"], record["channels"]["MV"]
    assert ev == {
        "max_drive_v": 2.0,
        "amplifier": {
            "model": "HV amp",
            "gain_db": 40.0,
            "gain_v_per_v": 100.0,
            "max_input_v": None,
            "setting": "",
        },
        "attenuator": None,
        "transducer": "touch panel",
        "measured_gain": [{"frequency_hz": 270.0, "v_out_per_v_in": 98.5}],
        "converter": None,
    }
    assert mv["max_drive_v"] == 3.6
    assert mv["attenuator"] == {"model": "2:1 divider", "ratio": 0.5}
    assert mv["amplifier"]["gain_v_per_v"] == pytest.approx(108.39, abs=0.01)
    assert mv["amplifier"]["setting"] == "GAIN1=1 GAIN0=1"
    # Sorted by carrier frequency.
    assert [p["frequency_hz"] for p in mv["measured_gain"]] == [120.0, 270.0]


def test_rig_record_without_rig_fields_still_has_every_key(tmp_path):
    cfg = load_device_config(
        write(
            tmp_path,
            "schema_version: 1\nchannels:\n  EV: {max_drive_v: 1}\n  MV: {max_drive_v: 1}\n",
        )
    )
    channel = cfg.rig_record()["channels"]["EV"]
    assert channel == {
        "max_drive_v": 1.0,
        "amplifier": None,
        "attenuator": None,
        "transducer": "",
        "measured_gain": [],
        "converter": None,
    }


CONVERTER_RIG = """\
schema_version: 1
channels:
  EV: {max_drive_v: 5, converter: {bits: 12, full_scale_v: 10, attenuator_steps_db: [0, 20, 40]}}
  MV: {max_drive_v: 5, converter: {bits: 16, full_scale_v: 10, min_lsb: 40}}
"""


def test_converter_and_attenuator_steps_are_read_and_recorded(tmp_path):
    cfg = load_device_config(write(tmp_path, CONVERTER_RIG))
    ev, mv = cfg.converters["EV"], cfg.converters["MV"]
    assert (ev.bits, ev.full_scale_v, ev.steps_db, ev.min_lsb) == (12, 10.0, (0.0, 20.0, 40.0), 10)
    assert (mv.bits, mv.steps_db, mv.min_lsb) == (16, (0.0,), 40.0)
    record = cfg.rig_record()["channels"]["EV"]["converter"]
    assert record == {
        "bits": 12,
        "full_scale_v": 10.0,
        "attenuator_steps_db": [0.0, 20.0, 40.0],
        "min_lsb": 10.0,
    }


@pytest.mark.parametrize(
    ("steps", "message"),
    [
        ("[20, 40]", "must start at 0 dB and ascend"),
        ("[0, 40, 20]", "must start at 0 dB and ascend"),
        ("[0, 20, 20]", "must start at 0 dB and ascend"),
        ("[0, -20]", "must be ≥ 0, got -20"),
    ],
)
def test_attenuator_steps_that_do_not_ascend_from_0_are_refused(tmp_path, steps, message):
    text = CONVERTER_RIG.replace("[0, 20, 40]", steps)
    with pytest.raises(DeviceConfigError, match=message) as info:
        load_device_config(write(tmp_path, text))
    assert "channels.EV.converter" in str(info.value)


def test_the_reference_rig_describes_its_converters():
    cfg = load_device_config(None)
    assert {ch: c.steps_db for ch, c in cfg.converters.items()} == {
        "EV": (0.0, 20.0, 40.0),
        "MV": (0.0, 20.0, 40.0),
    }
