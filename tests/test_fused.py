"""The compiled loops of procedures/fused.py give numpy's numbers bit for bit: the sums over the
nuisance grid, the wrong answer's table and the per-stimulus totals, on random tables with
zeros and subnormals, and the functional placement on the shipped grids; without numba's JIT
the numpy route runs and places the same stimuli."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from masking_lab.procedures import fused
from masking_lab.procedures.functional import FunctionalRampSettings, expected_entropy, ramp_tables

ROOT = Path(__file__).resolve().parents[1]


def _random_case(seed: int, r: int, n: int, a: int, s: int):
    rng = np.random.default_rng(seed)
    p = rng.random((n, a, s)).astype(np.float32)
    post = (rng.random((r, a, n)) ** 20).astype(np.float32)
    post[:, : a // 3] = 0.0  # cells that underflowed
    post[:, -1, 0] = np.float32(1e-42)  # a subnormal weight
    p[0, 0, 0] = np.float32(1e-40)
    return p, post


def test_numba_is_there_and_compiling():
    # numba is a dependency: the suite must test the compiled route, not silently the fallback
    assert fused.compiled()


@pytest.mark.parametrize(
    ("seed", "shape"), [(0, (1, 1, 1, 1)), (1, (3, 27, 40, 17)), (2, (2, 5, 9, 230))]
)
def test_nuisance_sums_equal_numpy_bit_for_bit(seed, shape):
    p, post = _random_case(seed, *shape)
    fast = fused.nuisance_sums(p, post)
    slow = fused.nuisance_sums(p, post, use_compiled=False)
    assert fast.dtype == slow.dtype == np.float32
    assert np.array_equal(fast, slow)
    # and numpy's plain expression, the functional placement's original arithmetic
    for k in range(post.shape[0]):
        ref = p[0] * post[k, :, 0, None]
        for n in range(1, post.shape[2]):
            ref += p[n] * post[k, :, n, None]
        assert np.array_equal(fast[k], ref)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_wrong_and_totals_equal_numpy_bit_for_bit(seed):
    p, post = _random_case(seed, 1, 7, 60, 31)
    m_c = fused.nuisance_sums(p, post)[0]
    rows = post[0].sum(axis=1)
    m_c[5, 3] = rows[5] + np.float32(1e-3)  # above the marginal: the wrong answer's floor 0
    fast = fused.wrong_and_totals(m_c, rows)
    slow = fused.wrong_and_totals(m_c, rows, use_compiled=False)
    assert fast[0][5, 3] == 0.0 and not np.signbit(fast[0][5, 3])
    for f, s in zip(fast, slow, strict=True):
        assert f.dtype == s.dtype
        assert np.array_equal(f, s)
        assert np.array_equal(np.signbit(f), np.signbit(s))


def test_the_shipped_functional_placement_is_the_numpy_one(monkeypatch):
    mapping = yaml.safe_load((ROOT / "protocols/experiment1_functional.yaml").read_text())
    t = ramp_tables(FunctionalRampSettings.from_mapping(mapping["procedure"]))
    rng = np.random.default_rng(5)
    post = rng.random(t.prior.shape) ** 30
    post /= post.sum()
    fast = expected_entropy(t, post)
    monkeypatch.setattr(fused, "_loops", lambda: None)
    assert not fused.compiled()
    assert np.array_equal(fast, expected_entropy(t, post))


def test_with_the_jit_disabled_the_numpy_route_places_the_same_stimulus():
    code = (
        "import numpy as np\n"
        "from masking_lab.procedures import fused\n"
        "from masking_lab.procedures.functional import FunctionalRampSettings, ramp_tables\n"
        "t = ramp_tables(FunctionalRampSettings(max_trials=5))\n"
        "print(fused.compiled(), t.first_stimulus)\n"
    )
    env = {**os.environ, "NUMBA_DISABLE_JIT": "1"}
    off = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    assert off.returncode == 0, off.stderr
    assert off.stdout.split() == [
        "False",
        str(ramp_tables(FunctionalRampSettings(max_trials=5)).first_stimulus),
    ]
