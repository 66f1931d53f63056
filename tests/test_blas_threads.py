"""One BLAS thread inside a session and a plan, the process's own limit restored afterwards
(core/blas_threads.py; the session itself is checked in tests/test_quest_plus_session.py)."""

from __future__ import annotations

import argparse

import numpy  # noqa: F401  (loads the BLAS pool that threadpoolctl lists)
import pytest

threadpoolctl = pytest.importorskip("threadpoolctl")


def _blas_threads() -> set[int]:
    return {p["num_threads"] for p in threadpoolctl.threadpool_info() if p["user_api"] == "blas"}


@pytest.fixture(autouse=True)
def _needs_blas():
    if not _blas_threads():
        pytest.skip("this numpy has no BLAS thread pool")


def test_one_blas_thread_inside_the_block_and_the_limit_back_after_an_error():
    from masking_lab.core.blas_threads import one_blas_thread

    with threadpoolctl.threadpool_limits(limits=2, user_api="blas"):
        with pytest.raises(RuntimeError, match="inside"), one_blas_thread():
            assert _blas_threads() == {1}
            raise RuntimeError("inside")
        assert _blas_threads() == {2}


def test_plan_runs_on_one_blas_thread(monkeypatch):
    from masking_lab.commands import plan

    seen = []
    monkeypatch.setattr(plan, "_run", lambda args: seen.append(_blas_threads()) or 0)
    with threadpoolctl.threadpool_limits(limits=2, user_api="blas"):
        assert plan.run(argparse.Namespace()) == 0
        assert _blas_threads() == {2}
    assert seen == [{1}]
