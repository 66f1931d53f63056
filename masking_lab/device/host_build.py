"""The C firmware's host build, compiled on this machine and started on a pseudo-terminal
(*shell*: a C compiler, a cache folder, child processes).

``firmware/`` holds the firmware a board runs: its portable core and, in ``host/main.c``, a
POSIX board that serves the device protocol on a new pseudo-terminal (``firmware/README.md``).
A plain install ships the core and that board as ``masking_lab.firmware``, so the firmware can be
built wherever masking_lab is installed, not only in a source checkout.

:func:`host_firmware` compiles it once per version of its sources (its ``FW_BUILD``, the
Makefile's hash; :func:`~masking_lab.device.emulator_state.build_hash`) with the Makefile's host
recipe into a per-user cache, and hands back the program, or why there is none (no C compiler,
no sources, a failed compile) so that a caller can fall back to the Python emulator, which
answers every frame alike. :func:`running_host_firmware` runs it for the length of a ``with``
block and gives its port, for ``serial:PORT``.

The demo runs its sessions on it where it can be built (``--device auto``, the default): in
virtual time a trial's round trip through the C firmware costs 0.5–0.6x the CPU it costs
through the emulator's thread in the session's process (``benchmarks/bench_device.py``, both
processes counted), and the whole demo takes 0.79–0.96x its time on the emulator
(docs/speed-accuracy.md, "Session 49").
The trial records are the same (both draw onset lateness from the same xorshift32 generator;
``tests/test_firmware_session.py``, ``tests/test_demo_devices.py``).
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from masking_lab.core.errors import DeviceError
from masking_lab.core.worker_processes import parent_death_signal
from masking_lab.device.emulator_state import build_hash

__all__ = [
    "CACHE_ENV",
    "HostFirmware",
    "firmware_tree",
    "host_firmware",
    "running_host_firmware",
]

#: Environment variable naming the cache folder (default ``$XDG_CACHE_HOME/masking_lab`` or
#: ``~/.cache/masking_lab``); each build lives in ``firmware-host/<FW_BUILD>/`` inside it.
CACHE_ENV = "MASKING_LAB_CACHE"
#: The Makefile's host recipe (``firmware/Makefile``: ``CSTD``, then ``-O2 -g``).
_FLAGS = ("-std=c11", "-Wall", "-Wextra", "-Werror", "-Wshadow", "-Wstrict-prototypes", "-O2", "-g")
_PROGRAM = "masking-fw"


@dataclass(frozen=True)
class HostFirmware:
    """The outcome of :func:`host_firmware`.

    Attributes
    ----------
    program : Path or None
        The compiled host build, or None when there is none (see ``reason``).
    build : str
        Its ``FW_BUILD`` (12 hex digits), the id its HELLO reports; ``000000000000`` without
        sources.
    reason : str
        Why ``program`` is None (empty when it is not): what was missing or what the compiler
        said.

    Examples
    --------
    >>> HostFirmware(None, "000000000000", "no C compiler found (cc)").program is None
    True
    """

    program: Path | None
    build: str
    reason: str = ""


def firmware_tree() -> Path | None:
    """The firmware's source folder: a checkout's ``firmware/``, else the installed copy.

    Returns
    -------
    Path or None
        The folder holding ``core/`` and ``host/main.c``; None if neither is there.

    Examples
    --------
    >>> tree = firmware_tree()
    >>> tree is None or (tree / "host" / "main.c").is_file()
    True
    """
    package = Path(__file__).resolve().parents[1]
    for candidate in (package.parent / "firmware", package / "firmware"):
        if (candidate / "host" / "main.c").is_file() and (candidate / "core").is_dir():
            return candidate
    return None


def _cache_root() -> Path:
    if os.environ.get(CACHE_ENV):
        return Path(os.environ[CACHE_ENV])
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "masking_lab"


def _compiler(cc: str | None) -> str | None:
    """The C compiler to use: ``cc``, else ``$CC``, else the first of cc, gcc, clang found."""
    asked = cc or os.environ.get("CC")
    for name in [asked] if asked else ["cc", "gcc", "clang"]:
        if found := shutil.which(name):
            return found
    return None


def host_firmware(
    *, tree: Path | None = None, cache: Path | None = None, cc: str | None = None
) -> HostFirmware:
    """The host build of the firmware, compiled into the cache the first time it is asked for.

    Parameters
    ----------
    tree : Path, optional
        The firmware's source folder (default: :func:`firmware_tree`).
    cache : Path, optional
        The cache folder (default: ``$MASKING_LAB_CACHE``, else ``$XDG_CACHE_HOME/masking_lab``
        or ``~/.cache/masking_lab``).
    cc : str, optional
        The C compiler (default: ``$CC``, else cc, gcc or clang, whichever is found first).

    Returns
    -------
    HostFirmware
        The program, or None and why. A compile that fails leaves nothing in the cache; two
        processes compiling at once each write their own file and the last rename wins (the
        same bytes' program either way). A cached program that does not run here is compiled
        again when a compiler is found, and is the reason otherwise.

    Examples
    --------
    >>> host_firmware(cc="/nonexistent/cc", cache=Path("/nonexistent")).reason[:25]
    'no C compiler found (/non'
    """
    tree = tree if tree is not None else firmware_tree()
    if tree is None:
        return HostFirmware(None, "000000000000", "the firmware's sources are not installed")
    if not (tree / "host" / "main.c").is_file():
        return HostFirmware(None, "000000000000", f"no firmware sources in {tree}")
    build = build_hash(tree.parent)
    folder = (cache if cache is not None else _cache_root()) / "firmware-host" / build
    program = folder / _PROGRAM
    compiler = _compiler(cc)
    if program.is_file() and os.access(program, os.X_OK):
        found = _runs(program, build)
        # one that does not run (damaged, say) is compiled again where a compiler is found
        if found.program is not None or compiler is None:
            return found
    if compiler is None:
        asked = cc or os.environ.get("CC") or "cc, gcc or clang"
        return HostFirmware(None, build, f"no C compiler found ({asked})")
    sources = [*sorted(str(p) for p in (tree / "core").glob("*.c")), str(tree / "host" / "main.c")]
    try:
        folder.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{_PROGRAM}.", dir=folder)
        os.close(fd)
    except OSError as exc:
        return HostFirmware(
            None,
            build,
            f"cannot write the cache folder {folder} ({exc.strerror}); point {CACHE_ENV} at a "
            "writable folder",
        )
    try:
        done = subprocess.run(
            [compiler, *_FLAGS, f'-DFW_BUILD="{build}"', "-o", tmp, *sources, "-lm"],
            capture_output=True,
            text=True,
            check=False,
        )
        if done.returncode != 0:
            said = (done.stderr or done.stdout).strip().splitlines()
            # the first error, not the "In file included from" lines before it
            errors = [line for line in said if "error" in line.lower()] or said
            first = errors[0][:200] if errors else f"exit status {done.returncode}"
            return HostFirmware(None, build, f"{Path(compiler).name} failed: {first}")
        os.chmod(tmp, 0o755)
        os.replace(tmp, program)
    except OSError as exc:
        return HostFirmware(None, build, f"{Path(compiler).name} could not run ({exc.strerror})")
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return _runs(program, build)


def _runs(program: Path, build: str) -> HostFirmware:
    """The program if it runs here (``--check-hello``, ~1 ms; a cache on a ``noexec`` file
    system, say, compiles but cannot run), else why not."""
    try:
        done = subprocess.run(
            [str(program), "--check-hello"], capture_output=True, text=True, check=False
        )
    except OSError as exc:
        return HostFirmware(None, build, f"{program} does not run here ({exc.strerror})")
    if done.returncode != 0:
        said = done.stderr.strip()[:200] or f"exit status {done.returncode}"
        return HostFirmware(None, build, f"{program} --check-hello failed: {said}")
    return HostFirmware(program, build)


def _stop_with_parent() -> Callable[[], None] | None:
    """A ``preexec_fn`` that has the kernel send the child SIGTERM when this process dies
    (Linux; None elsewhere)."""
    arm = parent_death_signal(signal.SIGTERM)
    if arm is None:
        return None
    parent = os.getpid()

    def stop_with_parent() -> None:
        arm()
        if os.getppid() != parent:  # the parent died before the request took effect
            os._exit(1)

    return stop_with_parent


@contextmanager
def running_host_firmware(program: Path, *options: str) -> Iterator[str]:
    """Run the host build (``--virtual-time`` and the like in ``options``) for the block; yields
    the path of its pseudo-terminal.

    Leaving the block stops it (SIGTERM: it zeroes its outputs and exits). Like a board, the
    program would outlive a client that is killed; on Linux it is told to stop when the
    process that started it dies (``PR_SET_PDEATHSIG``), so a killed demo worker leaves none
    behind.

    Raises
    ------
    DeviceError
        If it does not start or prints no port (its own message is in the error).

    Examples
    --------
    >>> built = host_firmware()
    >>> if built.program is not None:
    ...     with running_host_firmware(built.program, "--virtual-time") as port:
    ...         port.startswith("/dev/")
    ... else:
    ...     True
    True
    """
    # Its banner and last words go to stderr: kept in a file (a pipe nobody reads could fill,
    # and closed it would kill the program mid-sentence), read back only if it fails to start.
    with tempfile.TemporaryFile("w+") as said:
        try:
            proc = subprocess.Popen(
                [str(program), *options],
                stdin=subprocess.DEVNULL,
                stdout=subprocess.PIPE,
                stderr=said,
                text=True,
                preexec_fn=_stop_with_parent(),
            )
        except OSError as exc:
            raise DeviceError(
                f"{program}: cannot start the host firmware ({exc.strerror})"
            ) from None
        assert proc.stdout is not None
        try:
            port = proc.stdout.readline().strip()
            if not port.startswith("/"):
                proc.wait()
                said.seek(0)
                text = said.read().strip()[:300] or port or f"exit status {proc.returncode}"
                raise DeviceError(f"{program} {' '.join(options)} did not start: {text}")
            yield port
        finally:
            if proc.poll() is None:
                proc.terminate()
            proc.wait()
            proc.stdout.close()
