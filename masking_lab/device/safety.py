"""Keeping volts off skin: amplitude checks before anything is sent, and zeroing on exit.

:func:`check_plan` / :func:`check_amplitude` are pure: every back-end calls them before a command
leaves the host, so an over-limit request raises :class:`~masking_lab.core.errors.SafetyLimitError`
and nothing is played. :func:`zero_on_exit` registers an open device so that its outputs are
zeroed when the program exits normally, on an uncaught exception, or on SIGTERM/SIGHUP. (SIGKILL
cannot be caught: the firmware watchdog covers it.)
"""

from __future__ import annotations

import atexit
import contextlib
import logging
import math
import os
import signal
import threading
import weakref
from collections.abc import Callable
from typing import Any, Protocol

from masking_lab.core.errors import SafetyLimitError
from masking_lab.device.base import DeviceLimits, TrialPlan

log = logging.getLogger("masking_lab.device")


def check_amplitude(channel: str, amplitude_v: float, limits: DeviceLimits, *, what: str) -> None:
    """Raise SafetyLimitError unless ``0 ≤ amplitude_v ≤`` the channel's limit (V).

    Parameters
    ----------
    channel : {"EV", "MV"}
        Output channel.
    amplitude_v : float
        Requested peak drive, V.
    limits : DeviceLimits
        Limits in force.
    what : str
        Names the request in the message (``"target EV270"``).

    Raises
    ------
    SafetyLimitError
        For an unknown channel, a non-finite or negative amplitude, or one above the limit.

    Examples
    --------
    >>> limits = DeviceLimits({"EV": 1.0, "MV": 0.5})
    >>> check_amplitude("EV", 0.8, limits, what="target EV270")  # within 1 V: no error
    >>> check_amplitude("MV", 0.6, limits, what="masker MV120")
    Traceback (most recent call last):
    ...
    masking_lab.core.errors.SafetyLimitError: masker MV120: 0.6 V exceeds the MV limit of 0.5 V; ...
    """
    if channel not in limits.max_drive_v:
        raise SafetyLimitError(f"{what}: no limit configured for channel {channel!r}; not played")
    limit = limits.max_drive_v[channel]
    if not (isinstance(amplitude_v, (int, float)) and math.isfinite(amplitude_v)):
        raise SafetyLimitError(f"{what}: amplitude {amplitude_v!r} is not a finite number of V")
    if amplitude_v < 0:
        raise SafetyLimitError(f"{what}: amplitude {amplitude_v} V is negative (peak must be ≥ 0)")
    if amplitude_v > limit:
        raise SafetyLimitError(
            f"{what}: {amplitude_v:.4g} V exceeds the {channel} limit of {limit:g} V; nothing was "
            "played. Lower the level, or check the participant's calibration and the device "
            "config's max_drive_v"
        )


def check_plan(plan: TrialPlan, limits: DeviceLimits) -> None:
    """Check every drive of a trial against ``limits`` (V); same-channel drives add.

    Also refuses a plan whose timing or target interval cannot be played.

    Parameters
    ----------
    plan : TrialPlan
        Stimuli, peak amplitudes (V) and timing (s) of the trial.
    limits : DeviceLimits
        Limits in force, V per channel.

    Raises
    ------
    SafetyLimitError
        If any drive (or the sum of two on one channel) exceeds its limit, or the plan's timing
        or target interval cannot be played; nothing is played.

    Examples
    --------
    Two 0.3 V drives on the MV channel add to 0.6 V, over its 0.5 V limit:

    >>> from masking_lab.core.stimulus import parse_stimulus
    >>> limits = DeviceLimits({"EV": 1.0, "MV": 0.5})
    >>> plan = TrialPlan(parse_stimulus("MV120am40"), 0.3, 1, parse_stimulus("MV120"), 0.3)
    >>> check_plan(plan, limits)
    Traceback (most recent call last):
    ...
    masking_lab.core.errors.SafetyLimitError: target MV120am40 + masker MV120 on one channel: ...
    >>> check_plan(TrialPlan(parse_stimulus("EV270"), 0.3, 1, parse_stimulus("MV120"), 0.3), limits)
    """
    if not 1 <= plan.target_interval <= plan.n_intervals:
        raise SafetyLimitError(
            f"trial plan: target_interval {plan.target_interval} is not in 1..{plan.n_intervals}"
        )
    for name in ("stimulus_s", "gap_s", "lead_in_s"):
        value = getattr(plan, name)
        if not (math.isfinite(value) and value >= 0) or (name == "stimulus_s" and value == 0):
            raise SafetyLimitError(f"trial plan: {name}={value!r} s cannot be played")
    check_amplitude(
        plan.target.channel, plan.target_amplitude_v, limits, what=f"target {plan.target}"
    )
    if plan.masker is None:
        if plan.masker_amplitude_v != 0:
            raise SafetyLimitError("trial plan: masker amplitude given without a masker stimulus")
        return
    check_amplitude(
        plan.masker.channel, plan.masker_amplitude_v, limits, what=f"masker {plan.masker}"
    )
    if plan.masker.channel == plan.target.channel:
        check_amplitude(
            plan.target.channel,
            plan.target_amplitude_v + plan.masker_amplitude_v,
            limits,
            what=f"target {plan.target} + masker {plan.masker} on one channel",
        )


def stricter_limits(host: DeviceLimits, device: DeviceLimits) -> DeviceLimits:
    """Per channel, the smaller of the host-config and the firmware-reported limit (V).

    Parameters
    ----------
    host : DeviceLimits
        Limits from the rig config, V; its channels are the result's channels.
    device : DeviceLimits
        Limits the firmware reported in its handshake, V.

    Returns
    -------
    DeviceLimits

    Examples
    --------
    >>> stricter_limits(DeviceLimits({"EV": 1.0, "MV": 0.5}), DeviceLimits({"EV": 0.8, "MV": 2.0}))
    DeviceLimits(max_drive_v={'EV': 0.8, 'MV': 0.5})
    """
    return DeviceLimits(
        {ch: min(v, device.max_drive_v.get(ch, v)) for ch, v in host.max_drive_v.items()}
    )


class _Stoppable(Protocol):
    def stop(self) -> None: ...


_registry: weakref.WeakSet[Any] = weakref.WeakSet()
_lock = threading.Lock()
_installed = False
_previous: dict[int, Any] = {}


def zero_on_exit(device: _Stoppable) -> None:
    """Zero ``device`` (call its ``stop()``) at interpreter exit and on SIGTERM/SIGHUP.

    Shell: installs an ``atexit`` hook and, from the main thread, signal handlers once per
    process; a handler chains to the one it replaced, or exits with 128 + the signal number.

    Parameters
    ----------
    device : object with ``stop()``
        An open device; held weakly, so a device that is garbage-collected is forgotten.
    """
    global _installed
    with _lock:
        _registry.add(device)
        if _installed:
            return
        _installed = True
    atexit.register(zero_all, "exit")
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGTERM, signal.SIGHUP):
            with contextlib.suppress(ValueError, OSError):
                _previous[sig] = signal.signal(sig, _on_signal)


def forget(device: _Stoppable) -> None:
    """Stop watching ``device`` (after it was closed).

    Parameters
    ----------
    device : object with ``stop()``
        A device passed to :func:`zero_on_exit` (unknown devices are ignored).
    """
    with _lock:
        _registry.discard(device)


def zero_all(reason: str) -> None:
    """Call ``stop()`` on every registered device, ignoring failures (best effort).

    Parameters
    ----------
    reason : str
        Why (``"exit"`` or a signal name), for the log.
    """
    with _lock:
        devices = list(_registry)
    for device in devices:
        try:
            device.stop()
            log.warning("zeroed outputs of %s on %s", getattr(device, "port", device), reason)
        except Exception as exc:  # a dead link cannot be zeroed from here; the watchdog will
            log.error("could not zero %s on %s: %s", device, reason, exc)


def _forget_in_child() -> None:
    """In a forked child: the watched devices are the parent's (its links, its file
    descriptors), so the child never stops them, and it dies of SIGTERM and SIGHUP as it
    would have before they were watched. (A worker process forked from a session or an
    analysis used to send STOP on its parent's link when terminated.) A device the child
    opens itself is watched afresh."""
    global _registry, _lock, _installed
    _lock = threading.Lock()  # another thread may have held the parent's at the fork
    _registry = weakref.WeakSet()
    if _installed and threading.current_thread() is threading.main_thread():
        for sig, previous in _previous.items():
            with contextlib.suppress(ValueError, OSError, TypeError):
                signal.signal(sig, signal.SIG_DFL if previous is None else previous)
    _previous.clear()
    _installed = False


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_in_child)


def _on_signal(signum: int, frame: Any) -> None:
    zero_all(signal.Signals(signum).name)
    previous: Callable[..., Any] | int | None = _previous.get(signum)
    if callable(previous):
        previous(signum, frame)
        return
    if previous == signal.SIG_IGN:
        return
    raise SystemExit(128 + signum)
