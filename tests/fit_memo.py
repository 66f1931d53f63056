"""A pure fit run once per distinct input, for tests that would repeat the very same fits.

The ML estimate of a set is a deterministic function of the levels and answers it is handed
and of its settings. Where a test (or several tests on one study) hands it the same arrays
again, the repeat costs seconds and shows nothing new; an input that differs in dtype, shape,
any value or any setting still gets its own fit.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np


def once_per_input(fit: Callable[..., Any], done: dict | None = None) -> Callable[..., Any]:
    """``fit`` memoised on its array arguments' bytes and its keyword settings.

    ``done`` may be shared (e.g. by a module-scoped fixture) between several wrapped fits:
    the function's name is part of the key.
    """
    memo: dict = {} if done is None else done

    def once(*arrays: Any, **settings: Any) -> Any:
        key: tuple = (fit.__module__, fit.__qualname__)
        key += tuple((a.dtype.str, a.shape, a.tobytes()) for a in map(np.asarray, arrays))
        key += tuple(sorted(settings.items()))
        if key not in memo:
            memo[key] = fit(*arrays, **settings)
        return memo[key]

    return once
