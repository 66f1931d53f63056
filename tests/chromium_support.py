"""Open an HTML file in real headless Chromium: the rendered DOM, a screenshot, console lines.

Debian's ``chromium`` package (installed by ``.ci/system-deps.sh``). As root it needs
``--no-sandbox``. Console messages (``console.error``, uncaught exceptions) are printed by
``--enable-logging=stderr`` as ``INFO:CONSOLE...`` lines; :func:`open_in_chromium` returns them.
"""

from __future__ import annotations

import os
import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path

import numpy as np


@dataclass(frozen=True)
class Rendered:
    dom: str
    screenshot: Path
    console: list[str]


def chromium() -> str:
    """The chromium executable; fails (never skips) when it is missing."""
    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    assert exe, "chromium is not installed: run .ci/system-deps.sh (Debian package 'chromium')"
    return exe


def _run(args: list[str], profile: Path) -> subprocess.CompletedProcess:
    flags = [
        chromium(),
        "--headless",
        "--disable-gpu",
        "--hide-scrollbars",
        "--enable-logging=stderr",
        "--v=0",
        f"--user-data-dir={profile}",
        "--window-size=1280,2400",
    ]
    if os.geteuid() == 0:
        flags.append("--no-sandbox")
    return subprocess.run([*flags, *args], capture_output=True, text=True, timeout=120, check=False)


def open_in_chromium(page: Path, work: Path) -> Rendered:
    """Render ``page``: its DOM after load, a PNG screenshot and every console line."""
    url = page.resolve().as_uri()
    shot = work / f"{page.stem}_screenshot.png"
    dom = _run(["--dump-dom", url], work / "profile-dom")
    assert dom.returncode == 0, dom.stderr[-2000:]
    snap = _run([f"--screenshot={shot}", url], work / "profile-shot")
    assert snap.returncode == 0, snap.stderr[-2000:]
    console = [line for line in (dom.stderr + snap.stderr).splitlines() if ":CONSOLE" in line]
    return Rendered(dom.stdout, shot, console)


def screenshot_pixels(path: Path) -> np.ndarray:
    """The screenshot as an RGB(A) array (matplotlib reads PNG without extra packages)."""
    import matplotlib.image

    return matplotlib.image.imread(str(path))
