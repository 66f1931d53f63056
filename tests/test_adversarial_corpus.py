"""The adversarial corpus: every implementation answers every frame alike (issue 23, item 8).

Two runs of the seeded corpus (``tests/adversarial_corpus.py``):

- virtual time, 8,000 frames: the Python emulator and the host build compiled with
  ``-fsanitize=address,undefined``, both rendering every accepted trial through their output
  stage (``--vt-render`` / ``render_buffers``) at 1 kHz, so the largest sample ever output
  (DIAG ``pk_ev``/``pk_mv``) is checked against the limits; no sanitizer report;
- real time, 5,000 frames: the STM32 image under QEMU, the sanitizer host build and the
  emulator, the latter two configured from QEMU's HELLO (limits, sample rate, attenuators).

The answer compared is the reply kind and ERR code of each frame, or the FAULT code of
garbage. ``benchmarks/fw_corpus.py`` runs 100,000 frames and prints the figures.
"""

from __future__ import annotations

import pytest
from adversarial_corpus import Profile, episodes, first_mismatch, run
from firmware_support import Link, start

from masking_lab.device.config import parse_device_config
from masking_lab.device.emulator import FirmwareEmulator

VT_FRAMES = 8000
RT_FRAMES = 5000


def rig(max_ev: float, max_mv: float, fs: int, wd_s: float, ramp_s: float) -> str:
    return (
        "schema_version: 1\n"
        f"channels:\n  EV: {{max_drive_v: {max_ev}}}\n  MV: {{max_drive_v: {max_mv}}}\n"
        f"serial: {{reply_timeout_s: 0.5, watchdog_s: {wd_s}}}\n"
        f"waveform: {{sample_rate_hz: {fs}, ramp_s: {ramp_s}}}\n"
        "emulator: {model: TEST-EMU, serial_number: T-42, onset_jitter_s: 0.00005}\n"
    )


def _check(results, eps, limits):
    assert first_mismatch(results, eps) is None, first_mismatch(results, eps)
    n = sum(len(e) for e in eps)
    for r in results.values():
        assert len(r.answers) == n, (r.name, len(r.answers), n)
        assert r.peak_v["EV"] <= limits[0] and r.peak_v["MV"] <= limits[1], (r.name, r.peak_v)
    return next(iter(results.values())).answers


def test_virtual_time_corpus_emulator_and_sanitized_host_build_agree():
    config = parse_device_config(rig(2.5, 8, 1000, 0.3, 0.002), "corpus rig")
    host = start("host-asan", virtual_time=True, host_args=("--vt-render", "--fs", "1000"))
    emu = FirmwareEmulator(config, virtual_time=True, render_buffers=True).start()
    eps = episodes(seed=23, frames=VT_FRAMES, profile=Profile(2.5, 8.0, 1000, ("0", "20", "40")))
    try:
        results = run({"emulator": emu.port, "host-asan": host.port}, eps)
    finally:
        emu.close()
        stderr = host.close()
    assert "runtime error" not in stderr and "Sanitizer" not in stderr, stderr[-2000:]
    answers = _check(results, eps, (2.5, 8.0))
    # the corpus reaches every class of answer, and some trials were really rendered
    kinds = set(answers)
    assert {"OK", "ERR ARGS", "ERR LIMIT", "ERR STATE", "ERR UNKNOWN", "FAULT FRAME"} <= kinds
    assert results["host-asan"].side_events["DONE"] > 50
    assert results["host-asan"].peak_v["MV"] > 1.0


def test_real_time_corpus_qemu_sanitized_host_build_and_emulator_agree():
    qemu = start("qemu")
    link = Link(qemu.port)
    hello = link.call("HELLO")
    link.close()
    max_ev, max_mv, fs = hello.number("max_ev"), hello.number("max_mv"), int(hello.number("fs"))
    wd_ms, att = int(hello.number("wd_ms")), hello.fields["att"]
    args = ["--max-ev", hello.fields["max_ev"], "--max-mv", hello.fields["max_mv"]]
    args += ["--fs", str(fs), "--wd-ms", str(wd_ms), "--att", att, "--ramp-us", "10000"]
    host = start("host-asan", host_args=tuple(args))
    config = parse_device_config(rig(max_ev, max_mv, fs, wd_ms / 1000, 0.01), "qemu rig")
    emu = FirmwareEmulator(
        config, att_db=tuple(int(a) for a in att.split(",")), render_buffers=False
    )
    emu.start()
    eps = episodes(
        seed=8, frames=RT_FRAMES, profile=Profile(max_ev, max_mv, fs, tuple(att.split(",")), True)
    )
    try:
        results = run({"qemu": qemu.port, "host-asan": host.port, "emulator": emu.port}, eps)
    finally:
        emu.close()
        qemu.close()
        stderr = host.close()
    assert "runtime error" not in stderr and "Sanitizer" not in stderr, stderr[-2000:]
    _check(results, eps, (max_ev, max_mv))


@pytest.mark.parametrize("seed", [1, 2])
def test_the_corpus_is_deterministic_and_checksum_valid(seed):
    from masking_lab.device import protocol as proto

    profile = Profile(5.0, 10.0, 20000, ("0",))
    eps = episodes(seed, 300, profile)
    assert eps == episodes(seed, 300, profile)
    frames = [f for ep in eps for f in ep]
    crc_ok = 0
    for f in frames:
        body, _, tail = f.rstrip(b"\n").rpartition(b"*")
        crc_ok += tail == b"%04X" % proto.crc16(body)
    assert crc_ok >= 0.97 * len(frames)  # only the deliberately bad checksums differ
