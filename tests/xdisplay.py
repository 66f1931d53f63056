"""One virtual X display (Xvfb) per test process, for the tests that open real windows.

pyglet keeps its first X connection for the life of a process: a window opened after that
display's server has gone fails with an X I/O error, even on a new server with the same number.
So the display lives as long as the pytest process (the session fixture ``x_display`` in
conftest.py); each xdist worker, a process of its own, starts its own server, and ``-displayfd``
lets Xvfb pick a free display number.
"""

from __future__ import annotations

import os
import select
import shutil
import subprocess
import time
from collections.abc import Iterator

import pytest

REQUIRE = os.environ.get("MASKING_LAB_REQUIRE_DISPLAY") == "1"


def unavailable(reason: str) -> None:
    """Skip, or fail where MASKING_LAB_REQUIRE_DISPLAY=1 (CI) says the window tests must run."""
    if REQUIRE:
        pytest.fail(
            f"{reason}, but MASKING_LAB_REQUIRE_DISPLAY=1 says this test must run: install Xvfb "
            "and xdotool (bash .ci/system-deps.sh as root)"
        )
    pytest.skip(reason)


def virtual_display() -> Iterator[str]:
    """Start Xvfb (or use DISPLAY without it), yield the display name, stop the server."""
    try:
        import psychopy  # noqa: F401
    except ImportError as exc:
        unavailable(f"PsychoPy is not installed ({exc})")
    if shutil.which("xdotool") is None:
        unavailable("xdotool is not installed (needed to type keys into the window)")
    xvfb = shutil.which("Xvfb")
    proc = None
    if xvfb:
        read_fd, write_fd = os.pipe()
        proc = subprocess.Popen(
            [xvfb, "-displayfd", str(write_fd), "-screen", "0", "1280x800x24", "-nolisten", "tcp"],
            pass_fds=(write_fd,),
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        os.close(write_fd)
        # Xvfb writes the number, then "\n", in two writes: read to the newline before closing
        # the pipe, or the second write fails and the server quits.
        reply = b""
        deadline = time.monotonic() + 20.0
        while not reply.endswith(b"\n") and time.monotonic() < deadline:
            ready, _, _ = select.select([read_fd], [], [], deadline - time.monotonic())
            chunk = os.read(read_fd, 32) if ready else b""
            if not chunk:
                break
            reply += chunk
        os.close(read_fd)
        number = reply.decode().strip() if reply.endswith(b"\n") else ""
        if not number:
            proc.kill()
            proc.wait()
            pytest.fail("Xvfb did not report a display number within 20 s")
        display = f":{number}"
    elif os.environ.get("DISPLAY"):
        display = os.environ["DISPLAY"]
    else:
        unavailable("no Xvfb and no DISPLAY: cannot open a window")
    patch = pytest.MonkeyPatch()
    patch.setenv("DISPLAY", display)
    try:
        yield display
    finally:
        patch.undo()
        if proc is not None:
            proc.terminate()
            proc.wait(timeout=10)
