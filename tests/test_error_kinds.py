"""Error types by meaning (core.errors) and the exit code each failure gives on the command line:
a procedure error is not a staircase error, a responder failure is not a device failure, and
both stop a session with exit 3."""

from __future__ import annotations

import pytest
from runner_support import write_protocol

from masking_lab.commands.cli import main
from masking_lab.core.errors import (
    DeviceError,
    DeviceTimeoutError,
    MaskingLabError,
    ProcedureError,
    ResponderError,
    StaircaseError,
)
from masking_lab.procedures.base import replay
from masking_lab.procedures.quest_plus import QuestPlusSettings
from masking_lab.procedures.staircase import StaircaseSettings
from masking_lab.session.shell import fault_kind


def test_every_procedures_error_is_a_procedure_error_and_only_the_staircases_a_staircase_error():
    assert issubclass(StaircaseError, ProcedureError) and issubclass(ProcedureError, ValueError)
    assert not issubclass(ProcedureError, StaircaseError)
    with pytest.raises(StaircaseError):
        StaircaseSettings(start_level_db=0.0, n_down=0)
    with pytest.raises(ProcedureError) as info:
        QuestPlusSettings(min_level_db=10.0, max_level_db=0.0)
    assert not isinstance(info.value, StaircaseError)
    finished = StaircaseSettings(start_level_db=0.0, max_trials=1)
    with pytest.raises(ProcedureError, match="after the staircase finished") as info:
        replay(finished, [True, True])
    assert not isinstance(info.value, StaircaseError)  # replay is shared by every procedure


def test_a_responder_error_is_not_a_device_error_but_is_logged_as_a_responder_fault():
    assert issubclass(ResponderError, MaskingLabError)
    assert not issubclass(ResponderError, DeviceError)
    assert fault_kind(ResponderError("the terminal went away")) == "responder"
    assert fault_kind(DeviceTimeoutError("no reply")) == "timeout"


def _run(tmp_path, device: str, responder: list[str]) -> int:
    protocol = write_protocol(tmp_path, kind="baseline")
    argv = ["run", str(protocol), "--participant", "S01", "--device", device]
    return main([*argv, *responder, "--data", str(tmp_path / "d")])


def test_exit_code_of_a_responder_failure_is_3_and_names_the_responder(tmp_path, capsys):
    not_a_terminal = tmp_path / "not-a-tty"
    not_a_terminal.write_text("")
    code = _run(tmp_path, "sim", ["--responder", "keys", "--participant-tty", str(not_a_terminal)])
    err = capsys.readouterr().err
    assert code == 3
    assert "masking-lab run: responder error:" in err and "device error" not in err
    assert "fix the participant's terminal or window" in err and "Traceback" not in err


def test_exit_code_of_a_device_failure_is_3_and_names_the_device(tmp_path, capsys):
    code = _run(tmp_path, f"serial:{tmp_path}/no-such-port", ["--responder", "sim"])
    err = capsys.readouterr().err
    assert code == 3
    assert "masking-lab run: device error: cannot open serial port" in err
    assert "responder error" not in err and "fix the device" in err and "Traceback" not in err


def test_bad_values_a_user_can_give_are_core_errors_naming_the_field():
    from masking_lab.core.errors import InputError, LevelError
    from masking_lab.core.psychometric import Psychometric
    from masking_lab.core.stimulus import Stimulus, as_channel, parse_stimulus
    from masking_lab.core.waveforms import tone
    from masking_lab.responders.cue import TrialTiming

    cases = [
        (lambda: parse_stimulus("LRA170"), InputError, "not a stimulus name"),
        (lambda: as_channel("LRA", "channel"), InputError, "write EV or MV"),
        (lambda: Stimulus("MV", 0), InputError, "carrier_hz"),
        (lambda: Psychometric(0.0, -1.5, 1 / 3, 0.02), InputError, "scale_db"),
        (lambda: TrialTiming(0.5, 0.0, 0.5), InputError, "stimulus_s"),
        (lambda: tone(270.0, float("nan"), 0.1, 10_000.0), LevelError, "amplitude"),
    ]
    for make, kind, field in cases:
        with pytest.raises(kind, match=field) as info:
            make()
        assert isinstance(info.value, MaskingLabError) and isinstance(info.value, ValueError)
