"""mypy over the package reports no error, under the configuration in pyproject.toml.

The first test is the check itself (`mypy masking_lab`): about 40 s on a cold cache and a few
seconds once ``.mypy_cache/`` holds the last run. The second shows that the configuration has
teeth: a small module with the kinds of drift the package had (an unchecked body, a str passed
for a Literal, an ``int < None``, a stale ``type: ignore``) fails it.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "pyproject.toml"
CACHE = ROOT / ".mypy_cache"  # the one `mypy masking_lab` run from the checkout uses


def _mypy(*targets: str, cache: Path = CACHE) -> tuple[str, int]:
    # In a process of its own: mypy finds site-packages from the interpreter's state, which
    # the tests run before this one in the same xdist worker may have changed.
    args = [*targets, "--config-file", str(CONFIG), "--cache-dir", str(cache), "--no-pretty"]
    done = subprocess.run(
        [sys.executable, "-m", "mypy", *args], capture_output=True, text=True, timeout=900
    )
    return done.stdout + done.stderr, done.returncode


def test_the_package_has_no_type_errors():
    report, status = _mypy(str(ROOT / "masking_lab"))
    assert status == 0, f"mypy masking_lab found errors:\n{report}"
    assert "Success: no issues found" in report


def test_the_configuration_catches_drift(tmp_path):
    bad = tmp_path / "drift.py"
    bad.write_text(
        "from typing import Literal\n"
        "\n"
        "def channel_limit(channel: Literal['EV', 'MV']) -> float:\n"
        "    return 1.0\n"
        "\n"
        "def untyped(name):\n"
        "    limit: int | None = None\n"
        "    return 3 < limit\n"  # reported only with check_untyped_defs
        "\n"
        "channel_limit(str('EV'))\n"
        "ok = 1  # type: ignore[assignment]\n",
        encoding="utf-8",
    )
    # a cache of its own: the two tests may run at once on two xdist workers, and mypy's cache
    # is not safe for concurrent writers
    report, status = _mypy(str(bad), cache=tmp_path / "mypy_cache")
    assert status == 1, report
    assert 'Unsupported operand types for < ("int" and "None")' in report
    assert "[arg-type]" in report and "Literal['EV', 'MV']" in report
    assert 'Unused "type: ignore" comment' in report
