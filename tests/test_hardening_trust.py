"""Trust boundary (issue 11, item 5): a log header is data, never a path to open or print
unless the user names it. A FIFO stands in for "any path": opening one blocks, so a resume that
opened a path from the header would hang and fail by timeout instead of passing."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from masking_lab.commands.cli import main
from masking_lab.formats.resources import shipped

SECRET = "root:x:0:0:root:/root:/bin/bash\nsecret-line-two\n"


def interrupted_log(tmp_path: Path, **header_changes: object) -> Path:
    """A finished sim baseline cut back to its first sets (as after a crash), header edited."""
    data = tmp_path / "data"
    protocol = str(shipped("protocols", "baseline.yaml"))
    argv = ["run", protocol, "--participant", "S01", "--data", str(data), "--seed", "3"]
    argv += ["--device", "sim", "--responder", "sim", "--no-progress"]
    assert main(argv) == 0
    (log,) = (data / "S01").glob("*.jsonl")
    lines = log.read_text(encoding="utf-8").splitlines(keepends=True)
    header = json.loads(lines[0])
    header.update(header_changes)
    lines[0] = json.dumps(header, separators=(",", ":")) + "\n"
    log.write_text("".join(lines[:40]), encoding="utf-8")
    return log


def resume(log: Path, *extra: str) -> subprocess.CompletedProcess[str]:
    argv = [sys.executable, "-m", "masking_lab.commands.cli", "resume", str(log), "--no-progress"]
    return subprocess.run([*argv, *extra], capture_output=True, text=True, timeout=60)


@pytest.fixture
def fifo(tmp_path):
    path = tmp_path / "trap.yaml"
    os.mkfifo(path)
    return path


def test_a_rig_config_named_by_the_header_is_neither_opened_nor_quoted(tmp_path, fifo):
    secret = tmp_path / "secret.yaml"
    secret.write_text(SECRET, encoding="utf-8")
    for target in (fifo, secret):
        log = interrupted_log(tmp_path / target.stem, device_config=str(target))
        res = resume(log)  # a timeout here means the FIFO was opened
        assert res.returncode == 2, res.stderr
        assert "pass --device-config" in res.stderr
        assert "root:x" not in res.stderr + res.stdout and "secret-line" not in res.stderr
        assert "Traceback" not in res.stderr


def test_a_serial_port_named_by_the_header_is_not_opened(tmp_path, fifo):
    device = {"backend": "serial", "model": "M", "serial_number": "1", "firmware_version": "1",
              "port": str(fifo), "max_drive_v": {"EV": 5.0, "MV": 10.0}}  # fmt: skip
    log = interrupted_log(tmp_path, device=device)
    res = resume(log)
    assert res.returncode == 2, res.stderr
    assert "pass --device serial:PORT" in res.stderr and "Traceback" not in res.stderr


def test_a_hostile_header_value_is_quoted_short_and_escaped(tmp_path):
    log = interrupted_log(tmp_path, participant="\x1b[2J" + "A" * 5000)
    res = resume(log)
    assert res.returncode == 2 and "Traceback" not in res.stderr
    assert "\x1b" not in res.stderr and "A" * 200 not in res.stderr


def test_the_user_naming_the_config_resumes(tmp_path):
    rig = tmp_path / "rig.yaml"
    rig.write_text(shipped("protocols", "devices/default.yaml").read_text("utf-8"), "utf-8")
    log = interrupted_log(tmp_path, device_config=str(tmp_path / "elsewhere.yaml"))
    res = resume(log, "--device-config", str(rig))
    assert res.returncode == 0, res.stderr
