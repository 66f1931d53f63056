"""Log integrity: byte-level repair of torn lines, record continuity, the lock, disk errors, fsync.

The truncation test cuts a log at every byte offset of its last two records (which hold
multi-byte UTF-8 characters) and checks that reopening keeps every complete record; real
``resume`` runs are cut inside multi-byte characters. The lock is tested with real processes;
disk-full with a real 64 kB tmpfs when this process may mount one, and by injecting ENOSPC at
the ``os.write`` boundary otherwise (and always, for the partial-write case).
"""

from __future__ import annotations

import contextlib
import errno
import io
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from runner_support import (
    assert_valid_log,
    cli,
    cli_popen,
    of_kind,
    records,
    timeless,
    write_calibration,
    write_protocol,
)

from masking_lab.core.errors import LogError, LogLockedError, LogWriteError
from masking_lab.formats import session_log
from masking_lab.formats.log_integrity import continuity_problems, split_tail
from masking_lab.formats.log_lock import LogLock
from masking_lab.formats.session_log import SessionLogWriter, parse_log, read_log
from masking_lab.session.runner import RunOptions, resume_session, run_session

CAL = {"EV270": -14.0, "MV120": -26.0}
NOTE = "capteur débranché — 5 µs trop tard ✓"


def _trial(i: int, set_id: str = "A") -> dict:
    return {"record": "trial", "set_id": set_id, "trial_index": i, "correct": bool(i % 2)}


def _write_log(path: Path) -> list[bytes]:
    """A small log whose last two records hold multi-byte characters; its lines."""
    with SessionLogWriter.create(path, {"participant": "Zoë", "session_id": "s"}) as w:
        w.append({"record": "set_start", "set_id": "A", "target": "EV270"})
        for i in range(3):
            w.append(_trial(i))
        w.append({"record": "fault", "kind": "disconnected", "message": NOTE, "set_id": "A"})
        w.append({"record": "fault", "kind": "interrupted", "message": "arrêt — " + NOTE})
    return path.read_bytes().splitlines(keepends=True)


def test_writer_numbers_records_by_line_and_the_reader_checks_them(tmp_path):
    path = tmp_path / "log.jsonl"
    lines = _write_log(path)
    assert [json.loads(line)["seq"] for line in lines] == list(range(1, len(lines) + 1))
    log = read_log(path)
    assert log.lines == list(range(2, len(lines) + 1))
    assert log.problems == [] and log.continuity_problems() == []


def test_truncation_at_every_byte_of_the_last_two_records_loses_no_complete_record(tmp_path):
    src = tmp_path / "full.jsonl"
    lines = _write_log(src)
    full = b"".join(lines)
    assert any(b >= 0x80 for b in lines[-1]) and any(b >= 0x80 for b in lines[-2])
    ends = [len(b"".join(lines[: i + 1])) for i in range(len(lines))]  # offset after each "\n"
    path = tmp_path / "cut.jsonl"
    for offset in range(ends[-3], len(full) + 1):
        path.write_bytes(full[:offset])
        # A record is complete when all of it is there; only its newline may be missing.
        kept = [ln for ln, end in zip(lines, ends, strict=True) if offset >= end - 1]
        torn = offset not in ends and offset + 1 not in ends
        writer, before = SessionLogWriter.reopen(path)
        writer.append(_trial(99, "Z"))
        writer.close()
        where = f"cut at byte {offset}"
        assert (before.truncated_tail is not None) == torn, where
        after = path.read_bytes().splitlines(keepends=True)
        assert after[:-1] == kept and len(after) == len(kept) + 1, where
        log = read_log(path)
        assert log.problems == [], where
        assert [r["seq"] for r in [log.header, *log.records]] == list(range(1, len(after) + 1))
        assert log.continuity_problems() == [
            f"line {len(after)}: trial of set Z before any set_start of it"
        ], where


def test_split_tail_never_decodes_a_cut_character():
    raw = ("{}\n" + json.dumps({"record": "fault", "message": "é"}, ensure_ascii=False)).encode()
    cut = raw[:-3]  # inside the two bytes of "é"
    tail = split_tail(cut)
    assert tail.complete_end == 3 and not tail.whole_record and tail.tail == cut[3:]


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """An uninterrupted masked session (seed 11) and its log lines."""
    folder = tmp_path_factory.mktemp("ref")
    write_calibration(folder / "data", "S01", CAL)
    protocol = write_protocol(folder)
    result = run_session(
        RunOptions(protocol, "S01", data_dir=folder / "data", seed=11), stream=io.StringIO()
    )
    assert result.exit_code == 0
    return result.log_path.read_bytes().splitlines(keepends=True), records(result.log_path)


def _interrupted(tmp_path: Path, lines: list[bytes], n: int) -> Path:
    """The first ``n`` lines plus a fault record with multi-byte characters, as a live log."""
    data = tmp_path / "data"
    write_calibration(data, "S01", CAL)
    path = data / "S01" / "exp-S01-20240101T000000Z.jsonl"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"".join(lines[:n]))
    writer, _ = SessionLogWriter.reopen(path)
    last = json.loads(lines[n - 1])
    writer.append(
        {"record": "fault", "kind": "interrupted", "message": NOTE, "set_id": last.get("set_id")}
    )
    writer.close()
    return path


def test_resume_after_a_cut_inside_a_multibyte_character_keeps_every_complete_record(
    tmp_path, reference
):
    lines, ref = reference
    n = 12  # mid first set
    template = _interrupted(tmp_path / "t", lines, n).read_bytes()
    fault_line = template.splitlines(keepends=True)[-1]
    fault_at = len(template) - len(fault_line)
    # Every cut inside or at the edges of a multi-byte character of the fault record.
    cuts = sorted(
        {fault_at + i + d for i, b in enumerate(fault_line) if b >= 0x80 for d in (0, 1)}
    )[:12]
    for k, offset in enumerate(cuts):
        case = tmp_path / f"c{k}"
        path = _interrupted(case, lines, n)
        path.write_bytes(template[:offset])
        result = resume_session(path, stream=io.StringIO())
        assert result.exit_code == 0, offset
        recs = assert_valid_log(path)
        assert path.read_bytes().startswith(template[:fault_at])  # complete records untouched
        assert timeless(recs) == timeless(ref)
        assert read_log(path).continuity_problems() == []


@pytest.mark.parametrize(
    ("edit", "expected"),
    [
        (lambda ls: [*ls[:6], *ls[7:]], "record counter jumps from 6 to 8: 1 record(s) missing"),
        (lambda ls: [*ls[:7], ls[6], *ls[7:]], "repeats record 7 (first on line 7)"),
        (lambda ls: [*ls[:6], ls[7], ls[6], *ls[8:]], "record 7 comes after record 8"),
        (lambda ls: [*ls[:6], b"#### garbage ####\n", *ls[7:]], "line 7: not valid JSON"),
        (lambda ls: [*ls[:2], ls[1], *ls[2:]], "line 3: repeats record 2 (first on line 2)"),
    ],
    ids=["deleted", "duplicated", "swapped", "corrupt middle line", "duplicated set_start"],
)
def test_damaged_logs_are_refused_by_resume_with_the_line(tmp_path, reference, edit, expected):
    lines, _ = reference
    path = _interrupted(tmp_path, lines, 12)
    damaged = edit(path.read_bytes().splitlines(keepends=True))
    path.write_bytes(b"".join(damaged))
    before = path.read_bytes()
    log = read_log(path)
    assert any(expected in p for p in log.problems + log.continuity_problems())
    # Trial damage is refused by the replay check first (its own message); the rest by the
    # continuity check, which names the line.
    with pytest.raises(LogError, match=r"line \d+: |trial indices") as info:
        resume_session(path, stream=io.StringIO())
    if "trial indices" not in str(info.value):
        assert expected in str(info.value) and "backup" in str(info.value)
    assert path.read_bytes() == before  # nothing written to a damaged log


def test_structure_checks_name_the_line():
    recs = [
        {"record": "header"},
        {"record": "set_start", "set_id": "A"},
        {"record": "trial", "set_id": "A", "trial_index": 0},
        {"record": "trial", "set_id": "A", "trial_index": 2},
        {"record": "set_end", "set_id": "A", "n_trials": 3},
        {"record": "trial", "set_id": "A", "trial_index": 2},
        {"record": "trial", "set_id": "B", "trial_index": 0},
        {"record": "session_end"},
        {"record": "fault"},
    ]
    problems = continuity_problems(list(enumerate(recs, start=1)))
    assert problems == [
        "line 4: trial index 2 in set A, expected 1 (a trial record is missing, repeated or "
        "out of order)",
        "line 5: set_end of set A counts 3 trials, the log holds 2",
        "line 6: trial of set A after its set_end (line 5)",
        "line 7: trial of set B before any set_start of it",
        "line 9: fault record after session_end (line 8)",
    ]


def test_old_logs_without_a_counter_still_read_and_resume(tmp_path, reference):
    lines, ref = reference
    stripped = [
        (json.dumps({k: v for k, v in json.loads(ln).items() if k != "seq"}) + "\n").encode()
        for ln in lines[:12]
    ]
    data = tmp_path / "data"
    write_calibration(data, "S01", CAL)
    path = data / "S01" / "old.jsonl"
    path.write_bytes(b"".join(stripped))
    assert read_log(path).continuity_problems() == []
    assert resume_session(path, stream=io.StringIO()).exit_code == 0
    log = read_log(path)
    assert log.continuity_problems() == []
    assert [r.get("seq") for r in log.records[11:]] == list(range(13, len(log.records) + 2))
    assert timeless(records(path)) == timeless(ref)


def test_a_second_process_cannot_write_a_locked_log(tmp_path):
    path = tmp_path / "log.jsonl"
    _write_log(path)
    holder = subprocess.Popen(
        [sys.executable, "-c", "import fcntl,os,sys,time; fd=os.open(sys.argv[1], os.O_RDWR); "
         "fcntl.flock(fd, fcntl.LOCK_EX); print('locked', flush=True); time.sleep(60)", str(path)],
        stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert holder.stdout.readline().strip() == "locked"
        with pytest.raises(LogLockedError, match="another masking-lab process"):
            SessionLogWriter.reopen(path)
    finally:
        holder.kill()
        holder.wait()
    SessionLogWriter.reopen(path)[0].close()  # the lock died with its process


def _wait_for(path: Path, predicate, proc, timeout: float = 30.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if path.exists() and predicate(records(path)):
            return
        assert proc.poll() is None, proc.communicate()
        time.sleep(0.02)
    raise AssertionError("timed out waiting for the log")


def test_two_real_resumes_of_one_log_the_second_exits_2(tmp_path):
    data = tmp_path / "data"
    write_calibration(data, "S01", CAL)
    # One set on the real clock: ~0.35 s a trial, so each process runs for several seconds.
    slow = write_protocol(
        tmp_path,
        sets=[{"id": "A10", "masker": "MV120", "masker_level_db_sl": 10}],
        timing={"stimulus_s": 0.1, "gap_s": 0.05, "lead_in_s": 0.05},
    )
    run = cli_popen(
        "run", str(slow), "--participant", "S01", "--device", "sim", "--responder", "sim",
        "--real-time", "--seed", "5", "--data", str(data),
    )  # fmt: skip
    folder = data / "S01"
    deadline = time.monotonic() + 30
    while not list(folder.glob("*.jsonl")) and time.monotonic() < deadline:
        time.sleep(0.02)
    (log,) = folder.glob("*.jsonl")
    _wait_for(log, lambda rs: len(of_kind(rs, "trial")) >= 2, run)
    # While `run` writes the log, a resume is refused.
    second = cli("resume", str(log), timeout=60)
    assert second.returncode == 2, second.stderr
    assert "another masking-lab process" in second.stderr and "Traceback" not in second.stderr
    run.send_signal(signal.SIGTERM)
    run.communicate(timeout=20)
    assert run.returncode == 130
    first = cli_popen("resume", str(log))
    _wait_for(log, lambda rs: len(of_kind(rs, "resume")) == 1, first)
    second = cli("resume", str(log), timeout=60)
    _, err = first.communicate(timeout=120)
    assert first.returncode == 0, err
    assert second.returncode == 2, second.stderr
    assert "another masking-lab process" in second.stderr and "Traceback" not in second.stderr
    recs = assert_valid_log(log)
    assert len(of_kind(recs, "resume")) == 1
    assert read_log(log).continuity_problems() == []


def _enospc_after(limit: int):
    """An os.write that accepts ``limit`` more bytes, then writes part and fails with ENOSPC."""
    state = {"left": limit}

    def write(fd: int, data) -> int:
        if state["left"] <= 0:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        n = min(len(data), state["left"])
        state["left"] -= n
        return os.write(fd, bytes(data[:n]))

    return write


def test_injected_enospc_mid_line_leaves_no_torn_line_and_a_clean_error(tmp_path, monkeypatch):
    path = tmp_path / "log.jsonl"
    writer = SessionLogWriter.create(path, {"participant": "S01"})
    writer.append({"record": "set_start", "set_id": "A"})
    good = path.read_bytes()
    monkeypatch.setattr(session_log, "_write", _enospc_after(20))
    with pytest.raises(LogWriteError, match=r"No space left on device.*masking-lab resume"):
        writer.append(_trial(0))
    assert path.read_bytes() == good  # the partial line was removed
    monkeypatch.setattr(session_log, "_write", os.write)
    writer.append(_trial(0))  # space again: the counter did not advance on the failure
    writer.close()
    assert read_log(path).continuity_problems() == []


@pytest.fixture
def tiny_fs(tmp_path):
    """A real 64 kB tmpfs (needs CAP_SYS_ADMIN; skipped otherwise)."""
    mount = tmp_path / "tiny"
    mount.mkdir()
    done = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(mount)],
        capture_output=True, text=True, check=False,
    )  # fmt: skip
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {done.stderr.strip()[:100]}")
    try:
        yield mount
    finally:
        subprocess.run(["umount", "-l", str(mount)], check=False)


def test_disk_full_on_a_real_tiny_filesystem_exits_2_with_a_fault_record(tmp_path, tiny_fs):
    data = tiny_fs / "data"
    write_calibration(data, "S01", CAL)
    protocol = write_protocol(tmp_path)
    # Fill the filesystem but for a few kB: the header fits, the session runs out of space.
    filler = tiny_fs / "filler"
    fd = os.open(filler, os.O_WRONLY | os.O_CREAT)
    with contextlib.suppress(OSError):
        while os.write(fd, b"x" * 4096):
            pass
    os.close(fd)
    size = filler.stat().st_size
    os.truncate(filler, size - 12 * 1024)
    done = cli(
        "run", str(protocol), "--participant", "S01", "--device", "sim", "--responder", "sim",
        "--seed", "3", "--data", str(data), timeout=120,
    )  # fmt: skip
    assert done.returncode == 2, done.stderr
    assert "No space left on device" in done.stderr and "Traceback" not in done.stderr
    (log,) = (data / "S01").glob("*.jsonl")
    parsed = parse_log(log.read_bytes(), log)
    assert parsed.truncated_tail is None and parsed.problems == []
    assert parsed.continuity_problems() == []
    # No space even for the fault record (stderr says so); with space again, resume goes on and
    # records the unexplained stop.
    assert "could not log the fault" in done.stderr or of_kind(records(log), "fault")
    filler.unlink()
    assert cli("resume", str(log), timeout=120).returncode == 0
    assert read_log(log).continuity_problems() == []


def test_injected_enospc_in_a_session_records_the_fault_when_space_allows(tmp_path, monkeypatch):
    write_calibration(tmp_path / "data", "S01", CAL)
    protocol = write_protocol(tmp_path)
    calls = {"n": 0}

    def fail_once(fd: int, data) -> int:
        calls["n"] += 1
        if calls["n"] == 10:  # one trial record meets a full disk; the fault then fits
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return os.write(fd, data)

    monkeypatch.setattr(session_log, "_write", fail_once)
    with pytest.raises(LogWriteError, match="No space left on device"):
        run_session(
            RunOptions(protocol, "S01", data_dir=tmp_path / "data", seed=4), stream=io.StringIO()
        )
    (log,) = (tmp_path / "data" / "S01").glob("*.jsonl")
    last = records(log)[-1]
    assert last["record"] == "fault" and last["kind"] == "log_write"
    assert "No space left on device" in last["message"]
    assert read_log(log).continuity_problems() == []
    monkeypatch.setattr(session_log, "_write", os.write)
    assert resume_session(log, stream=io.StringIO()).exit_code == 0


@pytest.mark.parametrize(("virtual", "n_synced"), [(True, 2), (False, 6)])
def test_fsync_per_set_in_virtual_time_per_record_in_real_time(
    tmp_path, monkeypatch, virtual, n_synced
):
    from masking_lab.session.opening import sync_policy

    synced: list[int] = []
    real_fsync = os.fsync
    monkeypatch.setattr(session_log.os, "fsync", lambda fd: (synced.append(fd), real_fsync(fd)))
    path = tmp_path / "log.jsonl"
    with SessionLogWriter.create(path, {"participant": "S01"}, sync=sync_policy(virtual)) as w:
        n_before = len(synced)
        w.append({"record": "set_start", "set_id": "A"})
        for i in range(3):
            w.append(_trial(i))
        w.append({"record": "set_end", "set_id": "A", "n_trials": 3})
        w.append({"record": "session_end", "status": "completed"})
        # Virtual time: set_end and session_end only; real time: every record.
        assert len(synced) - n_before == n_synced
    assert read_log(path).continuity_problems() == []


def test_the_frame_chooses_the_sync_policy_from_the_clock(tmp_path, reference, monkeypatch):
    calls: list[str] = []
    original = SessionLogWriter.__init__

    def spy(self, lock, next_seq, sync="record"):
        calls.append(sync)
        original(self, lock, next_seq, sync)

    monkeypatch.setattr(SessionLogWriter, "__init__", spy)
    write_calibration(tmp_path / "data", "S01", CAL)
    protocol = write_protocol(tmp_path)
    result = run_session(
        RunOptions(protocol, "S01", data_dir=tmp_path / "data", seed=2), stream=io.StringIO()
    )
    assert result.exit_code == 0 and calls == ["set"]  # sim device, sim responder: virtual


def test_a_lock_is_released_with_the_writer(tmp_path):
    path = tmp_path / "log.jsonl"
    writer = SessionLogWriter.create(path, {"participant": "S01"})
    with pytest.raises(LogLockedError):
        LogLock.acquire(path)
    writer.close()
    LogLock.acquire(path).release()
