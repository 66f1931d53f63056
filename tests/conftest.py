"""Test-suite settings shared by every file.

Property tests (hypothesis) draw their examples from a fixed seed, so a CI run is repeatable:
a failure found once is found again by the same command. ``HYPOTHESIS_PROFILE=explore`` draws
fresh random examples instead, for hunting locally.
"""

from __future__ import annotations

import os
import signal

import pytest
from hypothesis import settings
from xdisplay import virtual_display

settings.register_profile("repeatable", derandomize=True, print_blob=True)
settings.register_profile("explore", derandomize=False, print_blob=True)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "repeatable"))

# A suite started in the background (a shell's `&`, `nohup`) inherits SIGINT ignored, and every
# command it starts keeps it ignored across exec: the tests that press Ctrl-C on a command, or
# on this process, would fail for want of a Ctrl-C. They get the terminal's default.
if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)


# The files with the longest tests, longest first. pytest-xdist hands tests to its workers in
# collection order, so these start at once and the many short tests fill in around them;
# collected last, one of them would run alone on one core at the end while the others idle.
SLOW_FIRST = (  # from `--durations` of full runs, 2026-11-24
    "test_demo_rerun.py",
    "test_functional_study.py",
    "test_figure_legibility.py",
    "test_demo.py",
    "test_render.py",
    "test_output_kills.py",
    "test_adversarial_corpus.py",
    "test_log_reading_hardening.py",
    "test_firmware_build.py",
    "test_device_conformance.py",
    "test_virtual_time_waits.py",
    "test_html_report.py",
    "test_log_records.py",
    "test_window_metadata.py",
    "test_quest_plus_study.py",
    "test_study.py",
    "test_analysis.py",
)


def pytest_collection_modifyitems(config, items) -> None:
    """Move the tests of SLOW_FIRST's files to the front (stable: same order on every worker)."""
    rank = {name: i for i, name in enumerate(SLOW_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))


# Files whose tests are each long and share no costly module fixture: spread test by test over
# the workers. Every other file goes to one worker whole, so its module fixtures (a whole demo,
# a simulated study and its analysis) are computed once, not once per worker that got a test.
SPREAD = ("test_output_kills.py",)


@pytest.hookimpl(tryfirst=True)
def pytest_xdist_make_scheduler(config, log):
    """xdist's scope scheduling by file (SPREAD's files by test), in collection order.

    Units go to whichever worker is free, slowest files first (``--no-loadscope-reorder`` in
    pyproject keeps the order above). xdist's ``loadgroup`` would do this by marker, but it
    tags node ids through an attribute pytest 9 no longer reads, so the groups were lost.
    """
    from xdist.scheduler import LoadScopeScheduling

    class FileScheduling(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            path = nodeid.split("::", 1)[0]
            return nodeid if path.rsplit("/", 1)[-1] in SPREAD else path

    return FileScheduling(config, log)


def pytest_xdist_auto_num_workers(config) -> int:
    """``-n auto``: one worker more than the cores.

    Some tests spend much of their time waiting on real time (QEMU, the host build over a pty,
    windows under Xvfb, a watchdog's trip): with one worker per core, a core idles meanwhile.
    """
    return (os.cpu_count() or 1) + 1


@pytest.fixture(scope="session")
def x_display():
    """A virtual X display for this test process (see tests/xdisplay.py for why per process)."""
    yield from virtual_display()
