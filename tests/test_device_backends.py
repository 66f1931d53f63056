"""The device factory and the in-process and NI-DAQmx back-ends."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest

from masking_lab.core import waveforms
from masking_lab.core.clock import RealClock, VirtualClock
from masking_lab.core.errors import DeviceError, MaskingLabError, SafetyLimitError
from masking_lab.core.stimulus import parse_stimulus
from masking_lab.core.trial import TrialPlan
from masking_lab.device.config import load_device_config
from masking_lab.device.nidaq import build_output_buffer
from masking_lab.device.registry import open_device, parse_spec
from masking_lab.device.serial_device import SerialDevice
from masking_lab.device.sim import SimDevice
from masking_lab.session import opening

EV270, MV120 = parse_stimulus("EV270"), parse_stimulus("MV120")
HAVE_NIDAQMX = importlib.util.find_spec("nidaqmx") is not None


def plan(**kw) -> TrialPlan:
    base = {
        "target": EV270,
        "target_amplitude_v": 0.5,
        "target_interval": 3,
        "masker": MV120,
        "masker_amplitude_v": 0.3,
        "stimulus_s": 0.02,
        "gap_s": 0.01,
        "lead_in_s": 0.01,
    }
    base.update(kw)
    return TrialPlan(**base)


def test_sim_device_checks_limits_and_advances_the_clock():
    clock = VirtualClock(10.0)
    dev = SimDevice(load_device_config(), clock, seed=3, onset_jitter_s=1e-4)
    result = dev.play_trial(plan(stimulus_s=1.8, gap_s=0.6, lead_in_s=1.2), 12.0)
    assert clock.now() == pytest.approx(12.0 + 7.8)
    assert result.planned_onsets_s == pytest.approx([13.2, 15.6, 18.0])
    assert all(
        0 <= a - p < 0.001
        for a, p in zip(result.actual_onsets_s, result.planned_onsets_s, strict=True)
    )
    assert dev.identity.backend == "sim" and dev.identity.port is None
    limit = dev.identity.limits.max_drive_v["EV"]
    with pytest.raises(SafetyLimitError):
        dev.play_trial(plan(target_amplitude_v=limit * 1.01), 20.0)
    assert clock.now() == pytest.approx(19.8)  # a refused trial takes no time
    dev.set_amplitude("MV", MV120, 1.0)
    assert dev.outputs()["MV"] == 1.0
    dev.close()
    assert dev.outputs() == {"EV": 0.0, "MV": 0.0}
    with pytest.raises(DeviceError, match="closed"):
        dev.play_trial(plan(), 30.0)


def test_sim_device_is_reproducible_from_its_seed():
    def onsets(seed):
        dev = SimDevice(None, VirtualClock(), seed=seed, onset_jitter_s=1e-4)
        return [dev.play_trial(plan(), 1.0 + k).actual_onsets_s for k in range(3)]

    assert onsets(1) == onsets(1)
    assert onsets(1) != onsets(2)


def test_factory_opens_sim_and_an_emulator_on_a_pty():
    clock = VirtualClock()
    sim = open_device("sim", None, clock)
    assert isinstance(sim, SimDevice)
    dev = open_device("emulator", None, clock, emulator_options={"watchdog_s": 0.5})
    try:
        assert isinstance(dev, SerialDevice)
        assert dev.identity.backend == "emulator" and dev.identity.port.startswith("/dev/")
        assert dev.emulator.virtual_time and dev.emulator.watchdog_s == 0.5
        dev.play_trial(plan(), 1.0)
    finally:
        dev.close()
    snap = dev.emulator.outputs()
    assert snap.zero and not snap.connected  # closing the device closed its emulator


def test_factory_serial_spec_reaches_a_running_emulator():
    from masking_lab.device.emulator import FirmwareEmulator

    with FirmwareEmulator(virtual_time=True) as emu:
        dev = open_device(f"serial:{emu.port}", None, VirtualClock())
        try:
            assert dev.identity.backend == "serial" and dev.identity.port == emu.port
        finally:
            dev.close()
        assert emu.outputs().connected  # a device we did not start stays up


def test_factory_loads_a_config_path(tmp_path):
    cfg = tmp_path / "rig.yaml"
    cfg.write_text("schema_version: 1\nchannels: {EV: {max_drive_v: 0.7}, MV: {max_drive_v: 1}}\n")
    dev = open_device("sim", cfg, VirtualClock())
    assert dev.identity.limits.max_drive_v == {"EV": 0.7, "MV": 1.0}


BAD_SPECS = [
    "",
    "serial",
    "serial:",
    "usb:/dev/x",
    "sim:extra",
    "emulators",
    "nidaq:",
    "serial:a\tb",
]


@pytest.mark.parametrize("spec", BAD_SPECS)
def test_factory_and_session_refuse_bad_specs_with_the_registrys_one_message(spec):
    # one grammar: the session's early check is the registry's, word for word
    with pytest.raises(MaskingLabError, match="choose sim, emulator, serial:PORT") as opened:
        open_device(spec, None, VirtualClock())
    with pytest.raises(MaskingLabError) as checked:
        opening.check_device_spec(spec)
    assert str(opened.value) == str(checked.value)
    assert not isinstance(opened.value, DeviceError)  # bad input (exit 2), not a device fault
    assert "serial:auto" in str(opened.value) and "nidaq[:DEVICE]" in str(opened.value)


FORMS = {  # spec: (back-end, argument)
    "sim": ("sim", ""),
    " emulator\n": ("emulator", ""),
    "serial:/dev/pts/3": ("serial", "/dev/pts/3"),
    "serial:auto": ("serial", "auto"),
    "nidaq": ("nidaq", ""),
    "nidaq:Dev1/ao0:1": ("nidaq", "Dev1/ao0:1"),
}


@pytest.mark.parametrize("spec", FORMS)
def test_registry_parses_every_form(spec):
    backend, arg = parse_spec(spec)
    assert (backend.name, arg) == FORMS[spec]
    assert opening.check_device_spec(spec) == spec.strip()


def test_factory_closes_its_emulator_when_the_handshake_fails():
    import threading

    def emulator_threads():
        return [t for t in threading.enumerate() if t.name == "firmware-emulator"]

    before = len(emulator_threads())
    with pytest.raises(DeviceError, match="runs in virtual time"):
        # force a mismatch the factory would never make by itself
        open_device("emulator", None, RealClock(), emulator_options={"virtual_time": True})
    assert len(emulator_threads()) == before


@pytest.mark.skipif(HAVE_NIDAQMX, reason="nidaqmx is installed here")
def test_choosing_nidaq_without_nidaqmx_says_how_to_install_it():
    with pytest.raises(DeviceError, match=r"pip install 'masking-lab\[nidaq\]'"):
        open_device("nidaq:cDAQ1Mod1", None, RealClock())


def test_nidaq_refuses_a_virtual_clock():
    with pytest.raises(DeviceError, match="needs a real clock"):
        open_device("nidaq", None, VirtualClock())


def test_nidaq_buffers_are_the_shared_waveforms_and_end_on_zero():
    cfg = load_device_config()
    p = plan()
    data = build_output_buffer(p, cfg)
    expected = waveforms.trial_buffers(p, cfg.waveform.sample_rate_hz, ramp_s=cfg.waveform.ramp_s)
    assert data.shape == (2, len(expected.ev_v))
    np.testing.assert_array_equal(data[0], expected.ev_v)
    np.testing.assert_array_equal(data[1], expected.mv_v)
    assert np.all(data[:, -1] == 0.0)
    assert np.max(np.abs(data[0])) == 0.5 and np.max(np.abs(data[1])) == 0.3


def test_nidaq_buffer_is_never_built_above_the_limit():
    cfg = load_device_config()
    with pytest.raises(SafetyLimitError):
        build_output_buffer(plan(masker_amplitude_v=cfg.limits.max_drive_v["MV"] + 0.1), cfg)
