"""The next trial's placement runs at real-time priority when the system permits it.

Real processes and the real kernel scheduler. The refusing case runs the check in a child
process whose CAP_SYS_NICE is dropped with util-linux's ``setpriv`` and whose rtprio limit is 0
(``prlimit``). The granting cases need CAP_SYS_NICE, which root has (CI runs as root); a process
without it skips them with that reason.
"""

from __future__ import annotations

import io
import json
import os
import shutil
import subprocess
import sys

import pytest
from runner_support import write_protocol

from masking_lab.procedures.staircase import Staircase
from masking_lab.session.priority import (
    placement_priority,
    placement_priority_note,
    realtime_permitted,
)
from masking_lab.session.runner import RunOptions, run_session

CAP_SYS_NICE = 23  # linux/capability.h


def _has_cap_sys_nice() -> bool:
    with open("/proc/self/status") as f:
        eff = next(line for line in f if line.startswith("CapEff:"))
    return bool(int(eff.split()[1], 16) >> CAP_SYS_NICE & 1)


root_only = pytest.mark.skipif(not _has_cap_sys_nice(), reason="needs CAP_SYS_NICE (root has it)")

PROBE = """
import json, os
from masking_lab.session import priority as p
with p.placement_priority():
    inside = os.sched_getscheduler(0)
print(json.dumps({"permitted": p.realtime_permitted(), "inside": inside,
                  "after": os.sched_getscheduler(0), "note": p.placement_priority_note()}))
"""
NO_CAP = ["setpriv", "--inh-caps=-sys_nice", "--bounding-set=-sys_nice"]


def _probe(prefix: list[str]) -> dict:
    for tool in {prefix[0], "setpriv"}:
        assert shutil.which(tool), f"{tool} (util-linux) is needed for this test"
    done = subprocess.run(
        [*prefix, sys.executable, "-c", PROBE], capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


@root_only
def test_the_block_runs_round_robin_and_the_policy_comes_back():
    before = (os.sched_getscheduler(0), os.sched_getparam(0))
    with placement_priority():
        assert os.sched_getscheduler(0) == os.SCHED_RR
        assert os.sched_getparam(0).sched_priority == os.sched_get_priority_min(os.SCHED_RR)
    assert (os.sched_getscheduler(0), os.sched_getparam(0)) == before
    with pytest.raises(ZeroDivisionError), placement_priority():
        1 / 0  # noqa: B018 - an update that fails must not leave the thread real-time
    assert os.sched_getscheduler(0) == before[0]
    assert realtime_permitted()
    assert "real-time priority (SCHED_RR)" in placement_priority_note()


def test_disabled_changes_nothing():
    with placement_priority(enabled=False):
        assert os.sched_getscheduler(0) == os.SCHED_OTHER


def test_without_the_permission_the_block_runs_at_normal_priority_and_says_how():
    got = _probe([*NO_CAP, "prlimit", "--rtprio=0"])
    assert got["permitted"] is False
    assert got["inside"] == got["after"] == os.SCHED_OTHER
    assert got["note"].startswith("placement: normal priority")
    assert "rtprio" in got["note"] and "docs/sessions.md" in got["note"]


def _run(tmp_path, real_time: bool):
    tiny = {"stimulus_s": 0.005, "gap_s": 0.002, "lead_in_s": 0.002}
    protocol = write_protocol(
        tmp_path, kind="baseline", sets=[{"id": "EV", "target": "EV270"}], timing=tiny
    )
    out = io.StringIO()
    options = RunOptions(
        protocol=protocol,
        participant="S01",
        device="sim",
        responder="sim",
        data_dir=tmp_path / f"data-{real_time}",
        seed=2,
        real_time=real_time,
    )
    return run_session(options, stream=out), out.getvalue()


@root_only
@pytest.mark.parametrize("real_time", [True, False])
def test_a_real_clock_session_places_each_trial_at_real_time_priority(
    tmp_path, monkeypatch, real_time
):
    policies: list[int] = []
    original = Staircase.update

    def spy(self, correct):
        policies.append(os.sched_getscheduler(0))
        return original(self, correct)

    monkeypatch.setattr(Staircase, "update", spy)
    result, printed = _run(tmp_path, real_time)
    assert result.exit_code == 0 and len(policies) > 10
    expected = os.SCHED_RR if real_time else os.SCHED_OTHER
    assert set(policies) == {expected}
    assert ("placement: real-time priority" in printed) is real_time
    assert os.sched_getscheduler(0) == os.SCHED_OTHER
