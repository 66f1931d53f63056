"""The README's commands do what it says: the first two run from a fresh shell (programs called
by their .venv path), the quick start activates the environment before calling `masking-lab`,
and its `fit` line reproduces the paper's pooled masking functions from Table 2."""

from __future__ import annotations

import json
import re
import shlex
from pathlib import Path

import pytest

from masking_lab.commands.cli import main

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text(encoding="utf-8")


def _blocks() -> list[str]:
    return re.findall(r"```bash\n(.*?)```", README, flags=re.S)


def _commands(block: str) -> list[list[str]]:
    """Shell lines of a block, continuations joined, comments dropped, split into words."""
    text = re.sub(r"\\\n\s*", " ", block)
    return [shlex.split(line, comments=True) for line in text.splitlines() if line.strip()]


def test_the_first_two_commands_need_no_activated_environment():
    first, second = _blocks()[:2]
    for block in (first, second):
        for cmd in _commands(block):
            for part in " ".join(cmd).split("&&"):
                prog = part.split()[0]
                assert prog == "python3" or prog.startswith(".venv/bin/"), part


def test_quick_start_activates_before_calling_masking_lab():
    quick = next(b for b in _blocks() if "masking-lab validate" in b)
    words = [cmd for cmd in _commands(quick) if cmd]
    assert words[0][:2] == ["source", ".venv/bin/activate"]


def test_the_fit_line_reproduces_the_papers_pooled_functions(tmp_path):
    fit = next(c for b in _blocks() for c in _commands(b) if c[:2] == ["masking-lab", "fit"])
    argv = fit[1:]
    out = argv.index("--out")
    argv[out + 1] = str(tmp_path / "t2")
    argv[1] = str(ROOT / argv[1])
    assert main(argv) == 0
    doc = json.loads((tmp_path / "t2" / "masking_params.json").read_text())
    f = {(e["target"], e["masker"]): e for e in doc["functions"]}
    # Ryu et al. 2020, section 3.2: EV ≈ max(0, −6.22 + 0.66x) for MV120/180, MV ≈ 1.39 + 1.09x
    # for MV180/270, each pooled over two pairs.
    for pair in (("EV270", "MV120"), ("EV270", "MV180")):
        assert f[pair]["pooled_pairs"] == ["EV270|MV120", "EV270|MV180"]
        assert f[pair]["intercept_db"] == pytest.approx(-6.22, abs=0.05)
        assert f[pair]["slope"] == pytest.approx(0.66, abs=0.01)
    for pair in (("MV180", "EV270"), ("MV270", "EV270")):
        assert f[pair]["pooled_pairs"] == ["MV180|EV270", "MV270|EV270"]
        assert f[pair]["intercept_db"] == pytest.approx(1.39, abs=0.01)
        assert f[pair]["slope"] == pytest.approx(1.09, abs=0.01)
