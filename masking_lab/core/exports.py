"""Lazy package exports: a sub-package names its public API without importing it up front.

Each sub-package's ``__init__`` maps its public names to the modules that define them; a name
is imported on first use, so ``import masking_lab.analysis`` stays cheap (``masking-lab --help``
loads neither pandas nor SciPy) and importing a package never pulls in a layer it does not use.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping
from typing import Any

__all__ = ["lazy_exports"]


def lazy_exports(
    package: str, homes: Mapping[str, str]
) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """Module-level ``__getattr__`` and ``__dir__`` for a package's lazily loaded names.

    Parameters
    ----------
    package : str
        The package's ``__name__``.
    homes : mapping of str to str
        Public name → the sub-module (relative to ``package``) that defines it.

    Returns
    -------
    (__getattr__, __dir__)
        Functions to assign at the package's module level.

    Examples
    --------
    >>> get, names = lazy_exports("masking_lab.core", {"VirtualClock": "clock"})
    >>> get("VirtualClock").__name__
    'VirtualClock'
    >>> "VirtualClock" in names()
    True
    """

    def __getattr__(name: str) -> Any:
        if name in homes:
            return getattr(importlib.import_module(f"{package}.{homes[name]}"), name)
        raise AttributeError(f"module {package!r} has no attribute {name!r}")

    def __dir__() -> list[str]:
        return sorted(homes)

    return __getattr__, __dir__
