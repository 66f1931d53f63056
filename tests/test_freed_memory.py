"""analysis/freed_memory: where a large analysis's memory comes from (glibc's allocator).

Each case runs in a fresh interpreter: the allocator's thresholds are process-wide, so setting
them here would change every other test in this worker. Minor page faults, counted by the
kernel (``getrusage``), tell a block that comes back from the heap (no fault) from a fresh
mapping whose pages the kernel must supply and zero again (hundreds of faults per 8 MB array;
how many depends on the kernel's fault-around, so the cases compare counts, not pages).
"""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from masking_lab.analysis import freed_memory

# 100 rounds of allocating, filling and freeing an 8 MB array.
_CHURN = textwrap.dedent(
    """
    import json, resource, sys
    import numpy as np
    from masking_lab.analysis import freed_memory

    def faults():
        return resource.getrusage(resource.RUSAGE_SELF).ru_minflt

    def churn():
        np.ones(1 << 20).sum()  # warm: the first block may be new in any case
        before = faults()
        for _ in range(100):
            np.ones(1 << 20).sum()
        return faults() - before

    out = {}
    if "early" in sys.argv:
        freed_memory.return_early()
    out["plain"] = churn()
    with freed_memory.reused_blocks():
        out["reused"] = churn()
    out["after"] = churn()
    print(json.dumps(out))
    """
)


def _faults(*args: str) -> dict[str, int]:
    run = subprocess.run(
        [sys.executable, "-c", _CHURN, *args], capture_output=True, text=True, timeout=300
    )
    assert run.returncode == 0, run.stderr
    return json.loads(run.stdout)


@pytest.mark.skipif(freed_memory._libc() is None, reason="glibc's mallopt is Linux/glibc only")
def test_reused_blocks_keeps_large_blocks_in_the_heap_and_gives_them_back_after() -> None:
    f = _faults("early")
    # return_early: every 8 MB array is a new mapping, faulted in again (≥ 100 per array)
    assert f["plain"] > 100 * 100
    # within the block the same heap memory serves every round
    assert f["reused"] < f["plain"] / 20
    # and return_early's behaviour is back once the block ends
    assert f["after"] > f["plain"] / 2


@pytest.mark.skipif(freed_memory._libc() is None, reason="glibc's mallopt is Linux/glibc only")
def test_reused_blocks_leaves_glibcs_own_thresholds_alone() -> None:
    # Without return_early, glibc's adaptive threshold already keeps such blocks, and the
    # block must not fix a threshold (that would end the adaptation for the whole process).
    f = _faults()
    early = _faults("early")["plain"]
    assert f["plain"] < early / 20
    assert f["reused"] < early / 20
    assert f["after"] < early / 20


def test_reused_blocks_changes_no_value() -> None:
    rng = np.random.default_rng(3)
    a = rng.standard_normal((300, 400))
    plain = np.tanh(a) @ a.T
    with freed_memory.reused_blocks():
        inside = np.tanh(a) @ a.T
    assert np.array_equal(plain, inside)


def test_reused_blocks_restores_the_thresholds_when_the_block_raises() -> None:
    script = textwrap.dedent(
        """
        import json, resource
        import numpy as np
        from masking_lab.analysis import freed_memory

        freed_memory.return_early()
        try:
            with freed_memory.reused_blocks():
                raise KeyError("inside")
        except KeyError:
            pass
        np.ones(1 << 20).sum()
        before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        for _ in range(100):
            np.ones(1 << 20).sum()
        print(json.dumps(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before))
        """
    )
    if freed_memory._libc() is None:
        pytest.skip("glibc's mallopt is Linux/glibc only")
    run = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=300
    )
    assert run.returncode == 0, run.stderr
    # every array a new mapping again, as with return_early alone
    assert int(run.stdout) > _faults("early")["plain"] / 2
