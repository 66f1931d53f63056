"""Device (rig) config: the reference rig loads; every malformed file is named precisely."""

from __future__ import annotations

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
        "missing required key 'max_drive_v'",
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
        (GOOD, GOOD + "nidaq: {ao_channels: {EV: ao0, MV: ao0}}\n"),
        "nidaq.ao_channels",
        "different outputs",
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
