"""The terminal keypad responder, driven over real pseudo-terminals.

The responder reads the pty's slave side; the test plays the participant by typing into the
master side and reading the prompts from it. Ctrl-C needs the pty to be the controlling terminal
of the responder's process, so that test forks a child with ``pty.fork``.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import pty
import select
import signal
import struct
import subprocess
import sys
import termios
import textwrap
import threading
import time

import pytest
from hypothesis import given
from hypothesis import strategies as st

from masking_lab.core.errors import ResponderError
from masking_lab.core.stimulus import Stimulus
from masking_lab.core.trial import PlayResult, TrialPlan
from masking_lab.responders.base import SetInfo, TrialPresentation
from masking_lab.responders.keys import INTERRUPT, KeyReader, KeysResponder, parse_keys

TIMEOUT_S = 10.0
EXIT_TIMEOUT_S = 30.0  # a child's exit under a loaded CI machine (it failed once at 10 s)
PROMPT = b"Press 1, 2 or 3"


def presentation(trial_index: int = 0) -> TrialPresentation:
    plan = TrialPlan(target=Stimulus("EV", 270.0), target_amplitude_v=0.5, target_interval=2)
    return TrialPresentation("EV270", trial_index, plan, 0.0, -6.0, None, None)


PLAYED = PlayResult([0.6, 3.0, 5.4], [0.6, 3.0, 5.4], 0.5, 0.0)


class Participant:
    """The master side of a pty: reads what the responder prints, types keys."""

    def __init__(self, master_fd: int) -> None:
        self.master = master_fd
        self.seen = bytearray()

    def wait_for(self, done, what: str, timeout: float = TIMEOUT_S) -> None:
        """Read the terminal until ``done(seen)`` is true."""
        deadline = time.monotonic() + timeout
        while not done(bytes(self.seen)):
            left = deadline - time.monotonic()
            if left <= 0:
                raise AssertionError(f"never saw {what}; terminal showed {bytes(self.seen)!r}")
            ready, _, _ = select.select([self.master], [], [], left)
            if ready:
                try:
                    chunk = os.read(self.master, 4096)
                except OSError:  # EIO: the other side closed
                    chunk = b""
                if not chunk:
                    raise AssertionError(f"terminal closed before {what}: {bytes(self.seen)!r}")
                self.seen += chunk

    def expect(self, text: bytes, timeout: float = TIMEOUT_S) -> None:
        self.wait_for(lambda seen: text in seen, repr(text), timeout)

    def line_after(self, marker: bytes, timeout: float = TIMEOUT_S) -> bytes:
        """Wait for ``marker`` and the end of its line; return the rest of that line."""
        self.wait_for(
            lambda seen: marker in seen and b"\n" in seen.split(marker, 1)[1],
            f"a whole line after {marker!r}",
            timeout,
        )
        return bytes(self.seen).split(marker, 1)[1].split(b"\n", 1)[0].rstrip(b"\r")

    def type(self, data: bytes) -> None:
        os.write(self.master, data)


def lflag(fd: int) -> int:
    return termios.tcgetattr(fd)[3]


def pending_input(fd: int) -> int:
    """Bytes waiting in a terminal's input queue (FIONREAD)."""
    return struct.unpack("i", fcntl.ioctl(fd, termios.FIONREAD, b"\0\0\0\0"))[0]


def run_in_thread(fn):
    box: dict = {}

    def target():
        try:
            box["value"] = fn()
        except BaseException as exc:  # handed to the test thread
            box["error"] = exc

    thread = threading.Thread(target=target, daemon=True)
    thread.start()
    return thread, box


@pytest.fixture
def pty_pair():
    master, slave = os.openpty()
    yield master, slave
    for fd in (master, slave):
        with contextlib.suppress(OSError):
            os.close(fd)


# -- pure parsing -----------------------------------------------------------------------------


def test_parse_plain_keys_and_controls():
    keys, tail = parse_keys(b"x2 \r\x03\x01")
    assert keys == ["x", "2", " ", "\n", INTERRUPT, ""]
    assert tail == b""


@pytest.mark.parametrize(
    "sequence",
    [b"\x1b[15~", b"\x1b[1;5A", b"\x1b[11~", b"\x1bOP", b"\x1b1", b"\x1b[2~", b"\x1b[3~"],
    ids=["F5", "ctrl-up", "F1-vt", "F1-ss3", "alt-1", "insert", "delete"],
)
def test_escape_sequences_are_one_ignored_key(sequence):
    keys, tail = parse_keys(sequence + b"3")
    assert keys == ["", "3"]
    assert tail == b""


@pytest.mark.parametrize("cut", [b"\x1b", b"\x1b[", b"\x1b[15", b"\x1bO"])
def test_unfinished_escape_sequence_is_kept_for_the_next_read(cut):
    keys, tail = parse_keys(b"1" + cut)
    assert keys == ["1"]
    assert tail == cut
    rest = b"\x1b[15~"[len(cut) :] if cut.startswith(b"\x1b[") else b"P"
    keys, tail = parse_keys(tail + rest + b"2")
    assert keys == ["", "2"]


def test_non_ascii_bytes_are_ignored():
    keys, _ = parse_keys("é2".encode())
    assert keys == ["", "", "2"]


@given(
    st.lists(
        st.one_of(
            st.builds(
                lambda params, final: b"\x1b[" + params.encode() + bytes([final]),
                st.text(alphabet="0123456789;", max_size=6),
                st.integers(0x40, 0x7E),
            ),
            st.binary(min_size=1, max_size=1).filter(lambda b: 0x20 <= b[0] < 0x7F),
        ),
        max_size=20,
    )
)
def test_digits_inside_escape_sequences_never_count(chunks):
    keys, tail = parse_keys(b"".join(chunks))
    plain = [c.decode() for c in chunks if not c.startswith(b"\x1b")]
    assert [k for k in keys if k] == plain
    assert tail == b""


# -- over a real pty -------------------------------------------------------------------------


def test_not_a_terminal_is_refused():
    read_fd, write_fd = os.pipe()
    try:
        with pytest.raises(ResponderError, match=r"not one.*--responder sim"):
            KeyReader(read_fd, write_fd)
    finally:
        os.close(read_fd)
        os.close(write_fd)


def test_open_tty_with_a_bad_path_says_what_to_do(tmp_path):
    with pytest.raises(ResponderError, match=r"cannot open the participant's terminal.*`tty`"):
        KeyReader.open_tty(str(tmp_path / "no-such-tty"))


def test_open_tty_refuses_a_regular_file(tmp_path):
    path = tmp_path / "file"
    path.write_text("")
    with pytest.raises(ResponderError, match="not one"):
        KeyReader.open_tty(str(path))


def test_trial_ignores_other_keys_and_restores_the_terminal(pty_pair):
    master, slave = pty_pair
    before = termios.tcgetattr(slave)
    assert before[3] & termios.ICANON and before[3] & termios.ECHO
    responder = KeysResponder(KeyReader(slave, slave), wait_for_start=False)
    participant = Participant(master)
    modes_during_play = []

    def play():
        modes_during_play.append(lflag(slave))
        return PLAYED

    def answer():
        participant.expect(PROMPT)
        # Letters, a wrong digit, F5 (ESC [ 1 5 ~ holds a "1"), arrows, then the answer.
        participant.type(b"x9\x1b[15~\x1b[A")
        participant.type(b"2")
        participant.expect(b"2\r\n")

    thread, box = run_in_thread(answer)
    result, response = responder.trial(presentation(), play)
    thread.join(TIMEOUT_S)
    assert "error" not in box, box.get("error")
    assert result is PLAYED
    assert response.interval == 2
    assert response.response_time_s >= 0
    assert response.finger_path == []
    # Keypad mode while the trial ran; the original settings afterwards.
    assert not modes_during_play[0] & (termios.ICANON | termios.ECHO)
    assert termios.tcgetattr(slave) == before
    responder.close()
    responder.close()  # idempotent


def test_keys_pressed_while_the_stimuli_play_are_discarded(pty_pair):
    master, slave = pty_pair
    responder = KeysResponder(KeyReader(slave, slave), wait_for_start=False)
    participant = Participant(master)

    def play():
        # An eager participant presses 1 during the intervals; wait until the terminal has it.
        participant.type(b"1")
        for _ in range(int(TIMEOUT_S / 0.005)):  # a hang guard, not a speed check
            if pending_input(slave):
                break
            time.sleep(0.005)
        else:
            pytest.fail("the typed key never reached the terminal")
        return PLAYED

    def answer():
        participant.expect(PROMPT)
        participant.type(b"3")

    thread, box = run_in_thread(answer)
    _, response = responder.trial(presentation(), play)
    thread.join(TIMEOUT_S)
    assert "error" not in box, box.get("error")
    assert response.interval == 3


def test_start_set_waits_for_the_space_bar(pty_pair):
    master, slave = pty_pair
    responder = KeysResponder(KeyReader(slave, slave), wait_for_start=True)
    participant = Participant(master)
    info = SetInfo("MV120_10", 2, 15, Stimulus("EV", 270.0), Stimulus("MV", 120.0), 10.0)
    thread, box = run_in_thread(lambda: responder.start_set(info))
    participant.expect(b"space bar")
    participant.type(b"1x\r")  # not the space bar: still waiting
    time.sleep(0.2)
    assert thread.is_alive()
    participant.type(b" ")
    thread.join(TIMEOUT_S)
    assert not thread.is_alive()
    assert "error" not in box, box.get("error")
    assert b"Set 2 of 15" in participant.seen


def test_open_tty_reads_the_named_terminal(pty_pair):
    master, slave = pty_pair
    responder = KeysResponder(KeyReader.open_tty(os.ttyname(slave)), wait_for_start=False)
    participant = Participant(master)

    def answer():
        participant.expect(PROMPT)
        participant.type(b"1")

    thread, box = run_in_thread(answer)
    _, response = responder.trial(presentation(4), lambda: PLAYED)
    thread.join(TIMEOUT_S)
    assert "error" not in box, box.get("error")
    assert response.interval == 1
    assert b"Trial 5" in participant.seen
    responder.close()
    with pytest.raises(OSError):
        os.fstat(responder.keys.in_fd)  # the responder closed the fd it opened


CHILD = textwrap.dedent(
    """
    import json, os, signal, sys
    # As launched from a terminal's shell: Ctrl-C raises KeyboardInterrupt. A test process can
    # inherit SIGINT ignored (exec keeps an ignored signal ignored; Python then installs no
    # handler), and then the child would never see the Ctrl-C typed below.
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    from masking_lab.core.trial import PlayResult, TrialPlan
    from masking_lab.core.errors import ResponderError
    from masking_lab.responders.base import TrialPresentation
    from masking_lab.responders.keys import KeyReader, KeysResponder
    from masking_lab.core.stimulus import Stimulus

    plan = TrialPlan(target=Stimulus("EV", 270.0), target_amplitude_v=0.5, target_interval=1)
    pres = TrialPresentation("EV270", 0, plan, 0.0, -6.0, None, None)
    responder = KeysResponder(KeyReader(0, 1), wait_for_start=False)
    print("TTY", os.ttyname(0), flush=True)
    try:
        _, response = responder.trial(pres, lambda: PlayResult([0.0] * 3, [0.0] * 3, 0.5, 0.0))
    except KeyboardInterrupt:
        print("INTERRUPTED", flush=True)
        sys.exit(130)
    except ResponderError as exc:
        print("RESPONDER_ERROR", exc, file=sys.stderr, flush=True)
        sys.exit(3)
    print("ANSWER", json.dumps(response.interval), flush=True)
    """
)


def child_state(pid: int) -> str:
    """What /proc says about a child that is still running: its state, signals and wait channel."""
    try:
        with open(f"/proc/{pid}/status") as status:
            fields = [
                line.strip()
                for line in status
                if line.startswith(
                    ("State:", "SigPnd:", "ShdPnd:", "SigBlk:", "SigIgn:", "SigCgt:")
                )
            ]
        with open(f"/proc/{pid}/wchan") as wchan:
            fields.append(f"wchan: {wchan.read()}")
    except OSError as exc:
        return f"no /proc entry ({exc})"
    return "; ".join(fields)


def wait_exit(
    pid: int, timeout: float = EXIT_TIMEOUT_S, terminal: Participant | None = None
) -> int:
    """The child's exit code, once it exits; a child still running after ``timeout`` (s) fails.

    The bound is wall time on a shared machine, so it is generous, and a failure says what the
    child was doing (from /proc) and what its terminal showed.
    """
    deadline = time.monotonic() + timeout
    while True:
        done, status = os.waitpid(pid, os.WNOHANG)
        if done:
            return os.waitstatus_to_exitcode(status)
        if time.monotonic() >= deadline:  # checked after waitpid: a stalled test still looks once
            break
        time.sleep(0.01)
    state = child_state(pid)
    if terminal is not None:
        with contextlib.suppress(AssertionError):  # whatever arrives in a moment, for the message
            terminal.wait_for(lambda seen: False, "more output", timeout=0.5)
    os.kill(pid, signal.SIGKILL)
    os.waitpid(pid, 0)
    shown = bytes(terminal.seen) if terminal is not None else b"(not read)"
    raise AssertionError(f"child did not exit in {timeout} s: {state}; terminal showed {shown!r}")


def test_ctrl_c_interrupts_and_restores_the_terminal():
    pid, master = pty.fork()
    if pid == 0:  # child: the pty is its controlling terminal
        os.execv(sys.executable, [sys.executable, "-c", CHILD])
    try:
        participant = Participant(master)
        # "TTY /dev/pts/N" once Python has started
        tty_path = participant.line_after(b"TTY ", timeout=30).decode()
        watcher = os.open(tty_path, os.O_RDWR | os.O_NOCTTY)
        try:
            participant.expect(PROMPT)
            assert not lflag(watcher) & termios.ICANON  # keypad mode is on
            participant.type(b"\x03")  # Ctrl-C → SIGINT to the child
            # The exit status, not the child's "INTERRUPTED", says the interrupt was handled:
            # raising SIGINT, the line discipline also flushes the terminal's queues, which
            # can drop what the child wrote before the flush ran.
            assert (
                wait_exit(pid, terminal=participant) == 130
            )  # sys.exit(130) in its KeyboardInterrupt handler
            assert lflag(watcher) & termios.ICANON  # the terminal it left behind
            assert lflag(watcher) & termios.ECHO
        finally:
            os.close(watcher)
    finally:
        os.close(master)


LATE_SIGINT_CHILD = textwrap.dedent(
    """
    import os, signal, sys, threading, time
    from masking_lab.responders.keys import KeyReader

    signal.signal(signal.SIGINT, signal.default_int_handler)
    participant, rig = os.openpty()
    keys = KeyReader(rig, rig)
    main = threading.get_native_id()

    def in_select():
        with open(f"/proc/self/task/{main}/wchan") as wchan:
            return wchan.read().startswith("poll_schedule")

    def reader_waiting():  # a kernel that hides wait channels: the signal goes after 5 s
        seen_from = time.monotonic()
        while not in_select() and time.monotonic() - seen_from < 5:
            time.sleep(0.001)

    def late_ctrl_c():
        # SIGINT is blocked on the waiting thread, so the kernel hands it to this one: Python's
        # C handler notes it, but the wait is not interrupted, as when a Ctrl-C lands just
        # before the wait begins. Sent only once the reader sits in its wait.
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})  # inherited blocked
        reader_waiting()
        os.kill(os.getpid(), signal.SIGINT)
        if not done.wait(10):  # a reader that never noticed: end its wait with a key instead
            typed.set()
            os.write(participant, b"1")

    done, typed = threading.Event(), threading.Event()
    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    threading.Thread(target=late_ctrl_c, daemon=True).start()
    try:
        with keys.keypad():
            key = keys.read_key(frozenset("123"))
    except KeyboardInterrupt:
        done.set()
        sys.exit(3 if typed.is_set() else 130)  # 3: noticed only once a key ended the wait
    print("ANSWERED", key, flush=True)
    """
)


def test_ctrl_c_that_interrupts_no_wait_still_ends_the_wait_for_a_key():
    child = subprocess.run(
        [sys.executable, "-c", LATE_SIGINT_CHILD], capture_output=True, timeout=60
    )
    assert child.returncode == 130, (child.stdout, child.stderr)


def test_answer_in_a_child_process_on_its_controlling_terminal():
    pid, master = pty.fork()
    if pid == 0:
        os.execv(sys.executable, [sys.executable, "-c", CHILD])
    try:
        participant = Participant(master)
        participant.expect(PROMPT, timeout=30)
        participant.type(b"\x1bOQ3")  # F2 (SS3), then 3
        assert json.loads(participant.line_after(b"ANSWER ")) == 3
        assert wait_exit(pid, terminal=participant) == 0
    finally:
        os.close(master)


def test_terminal_hangup_is_a_responder_error():
    master, slave = os.openpty()
    # No controlling terminal (new session, inherited fds): a hangup is EIO/EOF, not SIGHUP.
    proc = subprocess.Popen(
        [sys.executable, "-c", CHILD],
        stdin=slave,
        stdout=slave,
        stderr=subprocess.PIPE,
        start_new_session=True,
    )
    os.close(slave)
    try:
        participant = Participant(master)
        participant.expect(PROMPT, timeout=30)
        os.close(master)
        master = -1
        _, err = proc.communicate(timeout=TIMEOUT_S)
        assert proc.returncode == 3, err
        assert b"RESPONDER_ERROR" in err
        assert b"went away" in err or b"cannot write" in err
        assert b"resume" in err
    finally:
        if master >= 0:
            os.close(master)
        if proc.poll() is None:
            proc.kill()
            proc.wait()
