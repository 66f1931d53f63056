"""The demo's device: the C firmware's host build where a C compiler is found (``auto``, the
default), else the firmware emulator, with the same trials either way (real compiler, real
pseudo-terminals, real files)."""

from __future__ import annotations

import json

import pytest

from masking_lab.commands.cli import main
from masking_lab.core.errors import MaskingLabError
from masking_lab.demo import DemoSettings, run_demo
from masking_lab.device.emulator_state import build_hash

SMALL = ["--participants", "2", "--jobs", "2", "--n-boot", "200"]


def _trials(folder):
    """(participant, protocol) -> the log's header device and its trial records (without the
    host's random starting sequence numbers in device_extra)."""
    out = {}
    for path in sorted((folder / "data").rglob("*.jsonl")):
        lines = [json.loads(line) for line in path.read_text().splitlines()]
        header = lines[0]
        trials = [{k: v for k, v in r.items() if k != "device_extra"} for r in lines[1:]]
        key = (header["participant"], path.name.split("-")[0])
        out[key] = header["device"], [r for r in trials if r["record"] == "trial"]
    return out


def test_the_firmware_and_the_emulator_play_the_same_trials(tmp_path, capsys):
    assert main(["demo", "--out", str(tmp_path / "fw"), *SMALL]) == 0  # auto: a compiler is here
    said = capsys.readouterr()
    first = said.err.splitlines()[0]
    assert f"through the C firmware (host build {build_hash()}) on pseudo-terminals" in first
    assert "trials through the firmware" in said.out
    assert main(["demo", "--out", str(tmp_path / "emu"), *SMALL, "--device", "emulator"]) == 0
    fw, emu = _trials(tmp_path / "fw"), _trials(tmp_path / "emu")
    assert sorted(fw) == sorted(emu) and len(fw) == 6
    for key in fw:
        (fw_device, fw_trials), (emu_device, emu_trials) = fw[key], emu[key]
        assert (fw_device["backend"], fw_device["model"]) == ("serial", "ML-FW-2CH")
        assert fw_device["details"]["build"] == build_hash()
        assert (emu_device["backend"], emu_device["model"]) == ("emulator", "ML-EMU-2CH")
        assert len(fw_trials) > 100 and fw_trials == emu_trials, key
    summary = capsys.readouterr().out
    assert "trials through the emulator" in summary
    a = (tmp_path / "fw" / "analysis" / "anova.csv").read_text()
    assert a == (tmp_path / "emu" / "analysis" / "anova.csv").read_text()


def test_without_a_compiler_auto_runs_the_emulator_and_says_why(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("CC", "/nonexistent/cc")
    monkeypatch.setenv("MASKING_LAB_CACHE", str(tmp_path / "cache"))
    assert main(["demo", "--out", str(tmp_path / "d"), *SMALL]) == 0  # auto, the default
    out = capsys.readouterr()
    assert (
        "through the firmware emulator on a pseudo-terminal (no host build of the C firmware: "
        "no C compiler found (/nonexistent/cc))" in out.err.splitlines()[0]
    )
    assert {dev["backend"] for dev, _ in _trials(tmp_path / "d").values()} == {"emulator"}
    assert "trials through the emulator" in out.out


def test_the_firmware_asked_for_without_a_compiler_is_refused_before_anything_is_removed(
    tmp_path, monkeypatch
):
    monkeypatch.setenv("CC", "/nonexistent/cc")
    monkeypatch.setenv("MASKING_LAB_CACHE", str(tmp_path / "cache"))
    earlier = tmp_path / "d" / "data" / "S01" / "baseline-S01-20260101T000000Z.jsonl"
    earlier.parent.mkdir(parents=True)
    earlier.write_text('{"record":"header"}\n')  # an earlier demo's log, --force or not
    settings = DemoSettings(out=tmp_path / "d", participants=2, device="firmware", force=True)
    with pytest.raises(
        MaskingLabError,
        match=r"--device firmware: .*no C compiler found .*"
        r"install a C compiler \(or set CC\), or use --device emulator",
    ):
        run_demo(settings)
    assert earlier.read_text() == '{"record":"header"}\n'  # refused before it was removed
    assert sorted(p.name for p in (tmp_path / "d" / "data").rglob("*")) == ["S01", earlier.name]


def test_a_firmware_that_cannot_start_in_a_worker_is_a_device_error(tmp_path):
    """The program went missing between the demo's check and a session: the session's worker
    says which program could not start; no log is begun."""
    from masking_lab.core.errors import DeviceError
    from masking_lab.demo import _run_one

    missing = tmp_path / "gone" / "masking-fw"
    with pytest.raises(DeviceError, match=f"{missing}: cannot start the host firmware"):
        _run_one(str(tmp_path / "d"), f"firmware:{missing}", 2020, 1, 0)
    assert not (tmp_path / "d").exists()
