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
from adversarial_corpus import CorpusRun, Profile, episodes, real_time_run, virtual_time_run

VT_FRAMES = 8000
RT_FRAMES = 5000


def _check(run: CorpusRun) -> list[str]:
    assert "runtime error" not in run.stderr and "Sanitizer" not in run.stderr, run.stderr[-2000:]
    assert run.mismatch is None, run.mismatch
    for r in run.results.values():
        assert len(r.answers) == run.frames, (r.name, len(r.answers), run.frames)
        assert r.peak_v["EV"] <= run.limits[0] and r.peak_v["MV"] <= run.limits[1], r.peak_v
    return next(iter(run.results.values())).answers


def test_virtual_time_corpus_emulator_and_sanitized_host_build_agree():
    run = virtual_time_run(VT_FRAMES, seed=23)
    answers = _check(run)
    # the corpus reaches every class of answer, and many trials were really rendered
    assert {"OK", "ERR ARGS", "ERR LIMIT", "ERR STATE", "ERR UNKNOWN", "FAULT FRAME"} <= set(
        answers
    )
    assert run.results["host-asan"].side_events["DONE"] > 500
    assert run.results["host-asan"].peak_v["MV"] > 1.0


def test_real_time_corpus_qemu_sanitized_host_build_and_emulator_agree():
    run = real_time_run(RT_FRAMES, seed=8)
    answers = _check(run)
    assert {"OK", "ERR ARGS", "ERR LIMIT", "FAULT FRAME"} <= set(answers)
    assert run.results["qemu"].side_events["ABORTED"] > 200  # trials started, then STOPped


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
