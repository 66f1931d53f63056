"""`masking-lab device check` (issue 23, item 7): the bring-up self-test against the firmware
emulator and scripted boards on real pseudo-terminals; `--device serial:auto` finds a board by
its HELLO; a board with an older protocol or firmware is refused with "flash"."""

from __future__ import annotations

import pytest
from hardening_support import HELLO, RIG, ScriptedPeer, standard

from masking_lab.commands.cli import main
from masking_lab.device import discovery
from masking_lab.device import protocol as proto
from masking_lab.device.check import run_checks
from masking_lab.device.config import parse_device_config
from masking_lab.device.emulator import FirmwareEmulator
from masking_lab.device.emulator_state import build_hash

# Real time (a board), a short boot budget so probing a silent port ends soon; the emulator's
# converter described (the scripted boards' is not: the check warns that it took the board's).
CHECK_RIG = RIG.replace("boot_timeout_s: 0", "boot_timeout_s: 0.5")
CONVERTER = "converter: {bits: 12, full_scale_v: 10, attenuator_steps_db: [0, 20, 40]}"
EMU_RIG = CHECK_RIG.replace("{max_drive_v: 2.5}", "{max_drive_v: 2.5, " + CONVERTER + "}").replace(
    "{max_drive_v: 8}", "{max_drive_v: 8, " + CONVERTER + "}"
)


@pytest.fixture
def rig_file(tmp_path):
    path = tmp_path / "rig.yaml"
    path.write_text(CHECK_RIG, encoding="utf-8")
    return path


@pytest.fixture
def closing():
    items: list = []
    yield items
    for item in reversed(items):
        item.close()


def board(closing, **hello) -> ScriptedPeer:
    """A real-time scripted board whose HELLO carries ``hello`` on top of the standard one."""
    fields = {**HELLO, "vt": 0, "wd_ms": 300, **hello}

    def respond(frame, events):
        if frame.name == "HELLO":
            return [proto.encode_ok(frame.seq, fields)]
        return None

    peer = ScriptedPeer(respond)
    closing.append(peer)
    return peer


def test_check_against_the_emulator_reports_every_item(tmp_path, closing, capsys):
    rig_file = tmp_path / "emu-rig.yaml"
    rig_file.write_text(EMU_RIG, encoding="utf-8")
    emu = FirmwareEmulator(parse_device_config(EMU_RIG, "fw")).start()
    closing.append(emu)
    assert (
        main(["device", "check", emu.port, "--device-config", str(rig_file), "--no-watchdog"]) == 0
    )
    out = capsys.readouterr().out
    for item in (
        "handshake",
        "clock source",
        "reset cause",
        "limits",
        "converter",
        "interlock",
        "PING latency",
        "PLAY latency",
    ):
        assert f"ok    {item}" in out, out
    assert f"protocol 2, firmware fw-2.0.0, build {build_hash()}" in out
    assert "EV 2.5 V (config 2.5 V, in force 2.5 V)" in out
    assert out.rstrip().endswith("all 8 checks passed")
    assert emu.outputs().zero


def test_the_watchdog_trip_time_is_measured_and_judged(closing):
    rig = parse_device_config(CHECK_RIG, "rig")

    def tripping(quiet_ms):
        def respond(frame, events):
            if frame.name == "HELLO":
                return [proto.encode_ok(frame.seq, {**HELLO, "vt": 0, "wd_ms": 300})]
            if frame.name == "SETUP" and quiet_ms is not None:
                events[0] += 1
                trip = proto.encode_event(events[0], "WATCHDOG", {"quiet_ms": quiet_ms})
                return [proto.encode_ok(frame.seq), trip]
            return standard(frame, events)

        peer = ScriptedPeer(respond)
        closing.append(peer)
        return {c.name: c for c in run_checks(peer.port, rig)}["watchdog"]

    on_time = tripping(301)
    assert (
        on_time.status == "ok" and "tripped after quiet_ms=301 (allowed 300..350)" in on_time.detail
    )
    late = tripping(900)
    assert late.status == "FAIL" and "quiet_ms=900" in late.detail
    never = tripping(None)
    assert never.status == "FAIL" and "the output stayed on" in never.detail


@pytest.mark.parametrize(
    ("hello", "message"),
    [
        ({"proto": 1, "fw": "fw-1.4.0"}, "protocol version 1 is not 2"),
        ({"fw": "fw-1.9.9"}, "fw-1.9.9 is older than fw-2.0.0"),
    ],
)
def test_an_old_board_is_refused_with_a_flash_hint(rig_file, closing, capsys, hello, message):
    peer = board(closing, **hello)
    assert main(["device", "check", peer.port, "--device-config", str(rig_file)]) == 3
    out = capsys.readouterr().out
    assert "FAIL  handshake" in out and message in out and "flash firmware >= fw-2.0.0" in out


def test_an_open_interlock_fails_the_check(rig_file, closing, capsys):
    emu = FirmwareEmulator(parse_device_config(CHECK_RIG, "fw"), interlock_open=True).start()
    closing.append(emu)
    assert main(["device", "check", emu.port, "--device-config", str(rig_file)]) == 1
    assert "FAIL  interlock" in capsys.readouterr().out


def test_hsi_clock_and_a_watchdog_reset_are_warnings(rig_file, closing, capsys):
    peer = board(closing, clk="hsi", rst="watchdog")
    code = main(["device", "check", peer.port, "--device-config", str(rig_file), "--no-watchdog"])
    out = capsys.readouterr().out
    assert code == 0, out
    assert "warn  clock source   hsi: the 8 MHz HSE did not start" in out
    assert "warn  reset cause    watchdog" in out
    assert "warn  converter" in out and "rig config gives none" in out
    assert "(3 warning(s))" in out


def test_serial_auto_finds_the_board_by_its_hello(rig_file, closing, capsys, monkeypatch):
    silent = ScriptedPeer(lambda frame, events: [])
    closing.append(silent)
    emu = FirmwareEmulator(parse_device_config(CHECK_RIG, "fw")).start()
    closing.append(emu)
    monkeypatch.setattr(
        discovery, "candidate_ports", lambda: ["/dev/nonexistent-tty", silent.port, emu.port]
    )
    args = ["device", "check", "--device", "serial:auto", "--device-config", str(rig_file)]
    assert main([*args, "--no-watchdog"]) == 0
    out = capsys.readouterr().out
    assert f"found a masking-lab board on {emu.port}" in out


def test_serial_auto_without_a_board_names_the_ports_it_tried(
    rig_file, closing, capsys, monkeypatch
):
    silent = ScriptedPeer(lambda frame, events: [])
    closing.append(silent)
    monkeypatch.setattr(discovery, "candidate_ports", lambda: [silent.port])
    args = ["device", "check", "--device", "serial:auto", "--device-config", str(rig_file)]
    assert main(args) == 3
    err = capsys.readouterr().err
    assert f"{silent.port} (no masking-lab HELLO)" in err and "or give serial:PORT" in err


def test_check_against_the_host_build_of_the_c_firmware(tmp_path, capsys):
    # The real C firmware built for the host, on its own pty (needs fw-core's protocol-2
    # firmware: before that merge the check refuses the fw-1.0.0 board, exit 3).
    import firmware_support

    firmware_support.require_build("host")
    board = firmware_support.start("host")
    rig_file = tmp_path / "rig.yaml"
    rig_file.write_text(firmware_support.RIG, encoding="utf-8")
    try:
        code = main(
            ["device", "check", board.port, "--device-config", str(rig_file), "--no-watchdog"]
        )
    finally:
        board.close()
    out = capsys.readouterr().out
    assert code == 0, out
    assert "protocol 2, firmware fw-2." in out and "ok    PLAY latency" in out


@pytest.mark.parametrize(
    "argv", [[], ["--device", "sim"], ["--device", "serial:"], ["--device", "x"]]
)
def test_device_check_takes_only_a_serial_spec_by_the_registrys_grammar(argv, capsys):
    assert main(["device", "check", *argv]) == 2
    assert "give PORT" in capsys.readouterr().err
