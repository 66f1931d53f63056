"""A recording STAND-IN for NI's ``nidaqmx`` package, for tests of the nidaq back-end.

This is not hardware and not NI's driver: it is a small pure-Python package, importable as
``nidaqmx``, with the parts of the real API surface that :mod:`masking_lab.device.nidaq` uses
(``Task``, ``constants``, ``errors``, ``system.Device``, ``system.System``,
``system.watchdog.WatchdogTask``). It records every call in order and keeps a crude model of the
output lines (what level each line holds), so tests can check the call sequence and the safe
state. It proves that our code calls the API in the right order with the right arguments; it
does not prove that a real chassis behaves as this model does.

Use :func:`install` in a test (it puts the stand-in first on ``sys.path`` and returns its
:class:`~nidaqmx._standin.State`); ``SITE`` is the folder to put on ``sys.path`` in a child
process.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

SITE = Path(__file__).resolve().parent / "site"


def install(monkeypatch: Any, **settings: Any) -> Any:
    """Make ``import nidaqmx`` load the stand-in for this test; return its fresh state.

    Parameters
    ----------
    monkeypatch : pytest.MonkeyPatch
        Undoes the ``sys.path`` change at the end of the test.
    **settings
        Attributes of :class:`nidaqmx._standin.State` to set (``driver_installed=False``, ...).
    """
    for name in [m for m in sys.modules if m == "nidaqmx" or m.startswith("nidaqmx.")]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.syspath_prepend(str(SITE))
    import nidaqmx._standin as standin

    assert standin.IS_STANDIN, "imported the real nidaqmx instead of the stand-in"
    return standin.reset(**settings)


def uninstall() -> None:
    """Forget the stand-in modules, so later tests import whatever is really installed."""
    for name in [m for m in sys.modules if m == "nidaqmx" or m.startswith("nidaqmx.")]:
        del sys.modules[name]
