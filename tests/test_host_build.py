"""The C firmware's host build compiled on demand (masking_lab/device/host_build.py): the real
system compiler, a real cache folder, the program started on a real pseudo-terminal."""

from __future__ import annotations

import shutil
import subprocess
import sys
import time

import pytest

from masking_lab.core.clock import VirtualClock
from masking_lab.core.errors import DeviceError
from masking_lab.device.emulator_state import build_hash
from masking_lab.device.host_build import (
    firmware_tree,
    host_firmware,
    running_host_firmware,
)
from masking_lab.device.registry import open_device


def _fake_program(path, body: str):
    path.write_text(f"#!{sys.executable}\nimport sys\n{body}\n")
    path.chmod(0o755)
    return path


def test_the_source_tree_is_found_and_its_build_id_is_the_emulators():
    tree = firmware_tree()
    assert tree is not None and (tree / "core" / "fw.c").is_file()
    assert host_firmware(cc="/nonexistent/cc", cache=None).build == build_hash()


def test_compiled_once_into_the_cache_then_served_on_a_pty(tmp_path):
    built = host_firmware(cache=tmp_path)
    assert built.reason == "" and built.program is not None
    assert built.program.parent == tmp_path / "firmware-host" / build_hash()
    # the second call compiles nothing: no compiler is needed to find it
    again = host_firmware(cache=tmp_path, cc=str(tmp_path / "no-such-cc"))
    assert again == built
    assert sorted(p.name for p in built.program.parent.iterdir()) == ["masking-fw"]
    with running_host_firmware(built.program, "--virtual-time") as port:
        dev = open_device(f"serial:{port}", None, VirtualClock())
        try:
            ident = dev.identity
            assert (ident.backend, ident.model) == ("serial", "ML-FW-2CH")
            assert ident.details["build"] == built.build
        finally:
            dev.close()
    # leaving the block stopped it
    left = subprocess.run(["pgrep", "-f", str(built.program)], capture_output=True, text=True)
    assert left.stdout.strip() == ""


def test_no_compiler_says_so_and_writes_nothing(tmp_path, monkeypatch):
    monkeypatch.setenv("CC", str(tmp_path / "missing-cc"))
    built = host_firmware(cache=tmp_path / "cache")
    assert built.program is None
    assert built.reason == f"no C compiler found ({tmp_path / 'missing-cc'})"
    assert not (tmp_path / "cache").exists()


def test_a_failed_compile_names_the_error_and_leaves_no_file(tmp_path):
    cc = _fake_program(
        tmp_path / "broken-cc",
        "print('In file included from fw.c:1:', file=sys.stderr)\n"
        "print('fw.h:3: error: the compiler says no', file=sys.stderr)\nsys.exit(1)",
    )
    built = host_firmware(cache=tmp_path / "cache", cc=str(cc))
    assert built.program is None
    assert built.reason == "broken-cc failed: fw.h:3: error: the compiler says no"
    folder = tmp_path / "cache" / "firmware-host" / built.build
    assert list(folder.iterdir()) == []  # its temporary output was removed


def test_a_tree_without_sources_is_refused(tmp_path):
    built = host_firmware(tree=tmp_path, cache=tmp_path / "cache")
    assert (built.program, built.reason) == (None, f"no firmware sources in {tmp_path}")


def test_a_copied_tree_builds_with_its_own_id(tmp_path):
    """What a plain install does: the core and the host board copied elsewhere (as
    ``masking_lab/firmware``) build the same program id as the checkout."""
    tree = firmware_tree()
    assert tree is not None
    copy = tmp_path / "masking_lab" / "firmware"
    for part in ("core", "host"):
        shutil.copytree(tree / part, copy / part)
    built = host_firmware(tree=copy, cache=tmp_path / "cache")
    assert built.program is not None and built.build == build_hash()
    with open(copy / "core" / "fw.c", "a") as f:
        f.write("\n/* one more line */\n")
    assert host_firmware(tree=copy, cache=tmp_path / "cache").build != built.build


def test_a_program_that_does_not_start_is_a_device_error(tmp_path):
    prog = _fake_program(
        tmp_path / "fw", "print('masking-fw: --lin-ev too large', file=sys.stderr)\nsys.exit(2)"
    )
    with (
        pytest.raises(DeviceError, match="did not start: masking-fw: --lin-ev too large"),
        running_host_firmware(prog, "--virtual-time"),
    ):
        pass
    with (
        pytest.raises(DeviceError, match="cannot start the host firmware"),
        running_host_firmware(tmp_path / "absent"),
    ):
        pass


def test_a_killed_client_leaves_no_firmware_running(tmp_path):
    """SIGKILL of the process that started the firmware (a demo worker killed from outside):
    the firmware is told to stop with it, zeroing its outputs, instead of running on."""
    cache = tmp_path / "cache"
    built = host_firmware(cache=cache)
    assert built.program is not None
    client = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys, time\n"
            "from pathlib import Path\n"
            "from masking_lab.device.host_build import running_host_firmware\n"
            "with running_host_firmware(Path(sys.argv[1]), '--virtual-time') as port:\n"
            "    print(port, flush=True)\n"
            "    time.sleep(600)\n",
            str(built.program),
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    assert client.stdout.readline().startswith("/dev/")
    running = subprocess.run(["pgrep", "-f", str(built.program)], capture_output=True, text=True)
    assert running.stdout.split(), "the firmware was not running"
    client.kill()
    client.wait()
    # The kernel sends SIGTERM at the client's death; the firmware zeroes and exits within
    # one poll (≤ 100 ms). The loop bounds a failure, it is not the measurement.
    for _ in range(200):
        left = subprocess.run(["pgrep", "-f", str(built.program)], capture_output=True, text=True)
        if not left.stdout.strip():
            break
        time.sleep(0.05)
    assert left.stdout.strip() == "", "the firmware outlived the killed client"


def test_a_cache_that_cannot_be_written_is_a_reason_not_a_traceback(tmp_path):
    blocker = tmp_path / "not-a-folder"
    blocker.write_text("a file where the cache folder would go\n")
    built = host_firmware(cache=blocker)
    assert built.program is None
    assert built.reason.startswith(f"cannot write the cache folder {blocker}/firmware-host/")
    assert built.reason.endswith("; point MASKING_LAB_CACHE at a writable folder")


def test_a_cached_program_that_cannot_run_here_is_a_reason(tmp_path):
    """A cache on a noexec file system, or a program that is no program: found, tried with
    ``--check-hello``, and refused with why, so the demo takes the emulator."""
    folder = tmp_path / "firmware-host" / build_hash()
    folder.mkdir(parents=True)
    program = folder / "masking-fw"
    program.write_bytes(b"\x00not an executable\n")
    program.chmod(0o755)
    built = host_firmware(cache=tmp_path, cc=str(tmp_path / "no-cc"))
    assert built.program is None
    assert built.reason.startswith(f"{program} does not run here (Exec format error")
    _fake_program(program, "print('masking-fw: HELLO too long', file=sys.stderr)\nsys.exit(2)")
    built = host_firmware(cache=tmp_path, cc=str(tmp_path / "no-cc"))
    assert built.reason == f"{program} --check-hello failed: masking-fw: HELLO too long"


def test_a_damaged_cached_program_is_compiled_again_where_a_compiler_is_found(tmp_path):
    folder = tmp_path / "firmware-host" / build_hash()
    folder.mkdir(parents=True)
    program = folder / "masking-fw"
    program.write_bytes(b"\x00half a program\n")  # a damaged cache, say
    program.chmod(0o755)
    built = host_firmware(cache=tmp_path)
    assert built.reason == "" and built.program == program
    assert b"half a program" not in program.read_bytes()
    with running_host_firmware(program, "--virtual-time") as port:
        assert port.startswith("/dev/")
