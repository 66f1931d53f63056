"""The ``masking-lab`` console script: :func:`~masking_lab.commands.cli.console_main`.

It runs :func:`~masking_lab.commands.cli.main`, then freezes what the run made out of the
interpreter's last garbage collections. Each case runs in a child Python, so that this test
process (which calls ``main`` many times) is never frozen.
"""

from __future__ import annotations

import subprocess
import sys
from importlib.metadata import entry_points
from pathlib import Path

from masking_lab.commands import cli

ROOT = Path(__file__).resolve().parents[1]

# The console script's body, then what the process looks like after it returned.
CHILD = (
    "import gc, sys; from masking_lab.commands.cli import console_main; "
    "sys.argv[1:] = {argv!r}; code = console_main(); "
    "print('FROZEN', gc.get_freeze_count(), flush=True); sys.exit(code)"
)


def run_console(argv: list[str], cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-c", CHILD.format(argv=argv)],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=120,
    )


def frozen(stdout: str) -> int:
    return int(stdout.split("FROZEN ", 1)[1].split()[0])


def test_the_installed_command_is_console_main():
    (script,) = [e for e in entry_points(group="console_scripts") if e.name == "masking-lab"]
    assert script.value == "masking_lab.commands.cli:console_main"
    assert script.load() is cli.console_main


def test_a_run_returns_mains_status_and_is_frozen_out_of_the_last_collections():
    done = run_console(["validate", "protocols/baseline.yaml"], ROOT)
    assert done.returncode == 0, done.stderr
    assert "ok      protocols/baseline.yaml" in done.stdout
    assert frozen(done.stdout) > 10_000  # the modules' objects: argparse, yaml, the protocol


def test_an_input_error_keeps_its_status_and_message(tmp_path):
    done = run_console(["analyze", str(tmp_path / "missing"), "--out", str(tmp_path / "out")], ROOT)
    assert done.returncode == 2
    assert "masking-lab analyze: error:" in done.stderr
    assert "missing" in done.stderr
    assert frozen(done.stdout) > 0
    assert not (tmp_path / "out").exists()


def test_outputs_written_by_a_frozen_run_are_those_main_writes(tmp_path):
    # The paper's Table 2 fitted twice: by the console script (frozen, quick exit) in a child,
    # and by main() here. Every file is whole and the same, byte for byte.
    table2 = str(ROOT / "data_schema" / "shifts.csv")
    args = ["fit", table2, "--quiet", "--figures", "none", "--out"]
    done = run_console([*args, str(tmp_path / "console")], ROOT)
    assert done.returncode == 0, done.stderr
    assert frozen(done.stdout) > 0
    assert cli.main([*args, str(tmp_path / "main")]) == 0
    console = sorted(p.relative_to(tmp_path / "console") for p in (tmp_path / "console").rglob("*"))
    assert console == sorted(
        p.relative_to(tmp_path / "main") for p in (tmp_path / "main").rglob("*")
    )
    assert len(console) >= 5
    for rel in console:
        a, b = tmp_path / "console" / rel, tmp_path / "main" / rel
        assert a.is_dir() or a.read_bytes() == b.read_bytes(), rel


def test_main_itself_never_freezes():
    code = (
        "import gc; from masking_lab.commands.cli import main; "
        "main(['validate', 'protocols/baseline.yaml']); print('FROZEN', gc.get_freeze_count())"
    )
    done = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr
    assert frozen(done.stdout) == 0
