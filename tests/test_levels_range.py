"""A level is played only if the hardware can play it (issue 23, item 5).

The converter model (LSB, whole-LSB rounding, attenuator step choice) against first principles;
``validate`` and ``run`` refuse a protocol whose levels a rig cannot render within 1 dB before
the first trial; the emulator over a real pty and the in-process sim device play quantised
amplitudes and log the step; ``analyze`` reports trials played more than 0.1 dB off."""

from __future__ import annotations

import json
import math

import pytest
import yaml
from hardening_support import RIG, short_plan

from masking_lab.analysis.played_levels import played_level_problems
from masking_lab.commands.cli import main
from masking_lab.core.clock import VirtualClock
from masking_lab.core.errors import DeviceProtocolError, SafetyLimitError
from masking_lab.device.config import parse_device_config
from masking_lab.device.emulator import FirmwareEmulator
from masking_lab.device.level_check import worst_in_range
from masking_lab.device.levels_range import Converter, quietest_playable_v, unplayable
from masking_lab.device.serial_device import SerialDevice
from masking_lab.device.sim import SimDevice
from masking_lab.formats.log_records import ANALYSIS_DECODER
from masking_lab.formats.resources import shipped

DAC12 = Converter(12, 10.0, (0.0, 20.0, 40.0))


# ------------------------------------------------------------------ the converter model


def test_one_lsb_and_rounding_follow_the_dac_arithmetic():
    # 12 bits over ±10 V: 4096 codes of 20/4096 V. 0.01 V at 0 dB is 2.048 codes → 2 codes.
    assert DAC12.lsb_v(0.0) == 20 / 4096
    assert DAC12.played_v(0.01, 0.0) == 2 * 20 / 4096
    # at 20 dB the converter plays 0.1 V = 20.48 codes → 20 codes, back through ÷10
    assert DAC12.played_v(0.01, 20.0) == pytest.approx(20 * 20 / 4096 / 10, rel=1e-12)
    assert DAC12.played_v(0.0024, 0.0) == 0.0  # under half an LSB: silence


@pytest.mark.parametrize(
    ("amp", "step"),
    [(5.0, 0.0), (0.5, 0.0), (0.05, 0.0), (0.04, 20.0), (0.004, 40.0), (0.0001, 40.0)],
)
def test_the_step_is_the_least_attenuation_spanning_min_lsb(amp, step):
    assert DAC12.pick_step([amp]) == step
    if step != 40.0:  # where some step reaches 10 LSB, the chosen one does and fits
        assert amp >= 10 * DAC12.lsb_v(step) and DAC12.fits(amp, step)


def test_amplitudes_sharing_a_channel_share_a_step_that_fits_their_sum():
    # 0.6 V alone would take 20 dB (6 V at the DAC); with 0.5 V beside it the sum needs 0 dB.
    assert DAC12.pick_step([0.6]) == 0.0 or DAC12.fits(0.6, DAC12.pick_step([0.6]))
    step = DAC12.pick_step([0.6, 0.5])
    assert DAC12.fits(1.1, step)


def test_the_quietest_playable_level_is_a_bound_every_louder_level_meets():
    floor = quietest_playable_v(DAC12)
    for k in range(400):
        amp = floor * 10 ** (k * 0.01)
        assert DAC12.error_db(amp, DAC12.pick_step([amp])) <= 1.0 + 1e-9
    assert unplayable(DAC12, [floor / 3])


def test_worst_in_range_finds_the_floor_of_a_rig_without_steps():
    level, err = worst_in_range(Converter(12, 10.0), -60.0, -20.0)
    assert level == -60.0 and math.isinf(err)
    level, err = worst_in_range(DAC12, -60.0, 20.0)
    assert err <= 1.0


# ------------------------------------------------------------------ validate and run


@pytest.fixture
def rig_without_steps(tmp_path):
    data = yaml.safe_load(shipped("protocols", "devices/default.yaml").read_text("utf-8"))
    for ch in ("EV", "MV"):
        data["channels"][ch]["converter"]["attenuator_steps_db"] = [0]
    path = tmp_path / "no-steps.yaml"
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    return path


@pytest.mark.parametrize(
    "name", ["baseline", "experiment1", "experiment1_questplus", "experiment2"]
)
def test_the_shipped_protocols_validate_on_the_reference_rig(name, capsys):
    assert main(["validate", str(shipped("protocols", f"{name}.yaml"))]) == 0


@pytest.mark.parametrize(
    ("name", "key"),
    [
        ("baseline", "staircase.min_level_db"),
        ("experiment1", "staircase.min_level_db"),
        ("experiment1_questplus", "procedure.min_level_db"),
    ],
)
def test_a_rig_without_attenuator_steps_cannot_play_the_floors(
    name, key, rig_without_steps, capsys
):
    path = str(shipped("protocols", f"{name}.yaml"))
    assert main(["validate", "--device-config", str(rig_without_steps), path]) == 1
    err = capsys.readouterr().err
    assert "cannot play" in err and key in err and "attenuator_steps_db" in err


def test_run_refuses_unplayable_levels_before_the_first_trial(rig_without_steps, tmp_path, capsys):
    data = tmp_path / "data"
    code = main(
        [
            "run",
            str(shipped("protocols", "baseline.yaml")),
            "--participant",
            "S01",
            "--device",
            "sim",
            "--responder",
            "sim",
            "--data",
            str(data),
            "--device-config",
            str(rig_without_steps),
        ]
    )
    assert code == 2
    assert "refused before the first trial" in capsys.readouterr().err
    assert not list(data.rglob("*.jsonl"))  # no session was started


# ------------------------------------------------------------------ devices


def test_the_emulator_plays_quantised_amplitudes_and_the_host_logs_the_step(tmp_path):
    text = RIG.replace(
        "EV: {max_drive_v: 2.5}",
        "EV: {max_drive_v: 2.5, converter: {bits: 12, full_scale_v: 10, "
        "attenuator_steps_db: [0, 20, 40]}}",
    ).replace(
        "MV: {max_drive_v: 8}",
        "MV: {max_drive_v: 8, converter: {bits: 12, full_scale_v: 10, "
        "attenuator_steps_db: [0, 20, 40]}}",
    )
    rig = parse_device_config(text, "rig")
    emu = FirmwareEmulator(rig, virtual_time=True).start()
    try:
        dev = SerialDevice(emu.port, rig, VirtualClock())
        result = dev.play_trial(short_plan(target_amplitude_v=0.004), 1.0)
        assert result.extra["target_att_db"] == 40.0  # 0.004 V spans 82 LSB only at 40 dB
        assert result.extra["requested_target_v"] == 0.004
        assert result.played_target_v == pytest.approx(DAC12.played_v(0.004, 40.0), abs=1e-6)
        assert result.played_target_v != 0.004
        dev.close()
    finally:
        emu.close()


def test_a_board_whose_converter_differs_from_the_config_is_refused(tmp_path):
    text = RIG.replace(
        "EV: {max_drive_v: 2.5}",
        "EV: {max_drive_v: 2.5, converter: {bits: 16, full_scale_v: 10, "
        "attenuator_steps_db: [0, 20]}}",
    )
    emu = FirmwareEmulator(parse_device_config(RIG, "fw"), virtual_time=True).start()
    try:
        with pytest.raises(DeviceProtocolError, match=r"bits 12 \(config 16\).*attenuator steps"):
            SerialDevice(emu.port, parse_device_config(text, "host"), VirtualClock())
    finally:
        emu.close()


def test_the_sim_device_quantises_like_the_rig(tmp_path):
    sim = SimDevice(None, VirtualClock())  # the reference rig: 12 bits, steps 0/20/40 dB
    result = sim.play_trial(short_plan(target_amplitude_v=0.0123), 0.0)
    step = result.extra["target_att_db"]
    assert step == 40.0  # the reference rig asks for 50 LSB: 20 dB gives 25, 40 dB gives 252
    assert result.played_target_v == pytest.approx(DAC12.played_v(0.0123, step), abs=1e-12)


def test_a_level_no_step_renders_is_refused_before_anything_is_sent():
    sim = SimDevice(
        parse_device_config(
            RIG.replace(
                "EV: {max_drive_v: 2.5}",
                "EV: {max_drive_v: 2.5, converter: {bits: 8, full_scale_v: 10}}",
            ).replace(
                "MV: {max_drive_v: 8}",
                "MV: {max_drive_v: 8, converter: {bits: 8, full_scale_v: 10}}",
            ),
            "rig",
        ),
        VirtualClock(),
    )
    with pytest.raises(SafetyLimitError, match=r"cannot be played within 1 dB"):
        sim.play_trial(short_plan(target_amplitude_v=0.05), 0.0)
    assert sim.trials_played == 0


# ------------------------------------------------------------------ analyze


def test_analyze_notes_trials_played_off_their_request():
    line = (
        json.dumps(
            {
                "record": "trial",
                "set_id": "A",
                "trial_index": 3,
                "level_db_v": -40.0,
                "played_target_v": 0.0,
            }
        ).encode()
        + b"\n"
    )
    typed = ANALYSIS_DECODER.decode_lines(line)  # the view analyze reads logs through
    (note,) = played_level_problems(typed, [7])
    assert (
        note.startswith("line 7: 1 trial(s)") and "as silence" in note and "set A trial 3" in note
    )
    exact = json.loads(line) | {"played_target_v": 0.01}
    assert played_level_problems([exact], [7]) == []


def test_plan_flags_a_floor_below_the_rigs_resolution(rig_without_steps, tmp_path, capsys):
    args = ["plan", str(shipped("protocols", "baseline.yaml")), "--replicates", "20"]
    args += ["--ml-replicates", "0", "--quest-replicates", "0", "--out", str(tmp_path / "p")]
    assert main([*args, "--device-config", str(rig_without_steps)]) == 0
    flagged = capsys.readouterr().out
    assert "FLAGGED, 4 setting(s) below the rig's resolution" in flagged
    assert "set EV270: target EV270 at -60.0 dB re 1 V (1 mV) plays as silence" in flagged
    assert main([*args, "--force"]) == 0  # the reference rig, with its 20 and 40 dB steps
    assert "every level of every set plays within 1 dB" in capsys.readouterr().out
