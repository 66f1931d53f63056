"""Seeded fuzzing of every input file kind through the real commands (issue 11, item 6).

Each example mutates a valid file of one kind (bytes flipped, hostile numbers, alias bombs,
deep nesting, duplicated or swapped lines, truncation, ...) and runs every command that reads
it, in-process; a traceback, a hang or a NaN/inf in any file written fails the test.
Derandomized and bounded: about 30 s. The longer campaign is ``tests/fuzz/campaign.py``.
"""

from __future__ import annotations

import subprocess
import sys

import pytest
from fuzz_corpus import FILE_NAMES, KINDS, Picker, mutate, prepare, seed, trial
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

SETTINGS = settings(
    derandomize=True,
    max_examples=10,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)


class DrawPicker:
    """A :class:`fuzz_corpus.Picker` drawing from hypothesis (so failures shrink)."""

    def __init__(self, data: st.DataObject) -> None:
        self.data = data

    def int(self, lo: int, hi: int) -> int:
        return self.data.draw(st.integers(lo, hi))


def check(kind: str, data: bytes, work) -> None:
    findings = [o for o in trial(kind, data, work, timeout_s=20.0) if o.kind != "clean"]
    assert not findings, "\n".join(f"{o.kind}: {' '.join(o.argv)}\n{o.detail}" for o in findings)


@pytest.mark.parametrize("kind", KINDS)
def test_the_seed_files_are_accepted(kind, tmp_path):
    # The control: unmutated, every command of every kind succeeds (exit 0, or 1 for a solve
    # whose answers exceed the reference rig's rating), so a refusal below is the mutation's.
    outcomes = trial(kind, seed(kind), tmp_path / "work")
    assert [o.kind for o in outcomes] == ["clean"] * len(outcomes)
    assert all(o.code in (0, 1) for o in outcomes), outcomes
    assert outcomes[0].code == 0  # validate


@pytest.mark.parametrize("kind", KINDS)
@SETTINGS
@given(data=st.data())
def test_mutated_files_end_cleanly(kind, tmp_path_factory, data):
    picker: Picker = DrawPicker(data)
    mutated = mutate(seed(kind), picker, data.draw(st.integers(1, 3)))
    check(kind, mutated, tmp_path_factory.mktemp("work") / kind)


@pytest.mark.parametrize("kind", ["protocol", "rig", "scene"])
def test_a_few_mutations_through_real_subprocesses(kind, tmp_path):
    # The console entry point, as a user runs it: exit 1/2 and a message, never a traceback.
    import random

    from fuzz_corpus import RandomPicker

    rng = random.Random(kind)
    data = mutate(seed(kind), RandomPicker(rng), 2)
    file = prepare(tmp_path / "work", kind, data)
    res = subprocess.run(
        [sys.executable, "-m", "masking_lab.commands.cli", "validate", str(file)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert res.returncode in (0, 1), res.stderr
    assert "Traceback" not in res.stderr
    assert FILE_NAMES[kind].split("/")[-1] in res.stdout + res.stderr
