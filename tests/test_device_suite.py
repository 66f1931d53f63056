"""The device suite (tests/device_suite.py) over every back-end, and its declarations checked.

One test per (target, check), like scikit-learn's ``parametrize_with_checks``. A target's
firmware process starts once per module; each check opens a fresh device on it. The recipe of
docs/architecture.md ("add a device back-end") is followed once below: a tiny back-end is
registered in the test and the same checks run over it.
"""

from __future__ import annotations

from typing import Any

import device_suite as suite
import pytest

from masking_lab.core.clock import VirtualClock
from masking_lab.core.errors import DeviceError, MaskingLabError
from masking_lab.device import registry
from masking_lab.device.sim import SimDevice
from masking_lab.session import opening


@pytest.fixture(scope="module", params=list(suite.TARGETS))
def target(request):
    made = suite.TARGETS[request.param]()
    yield made
    made.close()


@pytest.fixture
def device(target):
    dev = target.open()
    yield dev
    dev.close()


@pytest.mark.parametrize("check", suite.CHECKS, ids=lambda c: c.__name__)
def test_device_suite(target, device, check):
    check(target, device)


def test_every_registered_backend_runs_the_suite():
    assert set(suite.TARGET_BACKENDS.values()) == set(registry.BACKENDS)
    assert set(suite.TARGET_BACKENDS) == set(suite.TARGETS)


@pytest.mark.parametrize("name", sorted(registry.BACKENDS))
def test_virtual_time_is_as_declared(name):
    """Declared: some target runs it on a virtual clock. Declared absent: opening refuses one
    (before any driver is loaded)."""
    if registry.BACKENDS[name].capabilities.virtual_time:
        virtual = {"sim", "emulator", "host"}  # the targets opened on a VirtualClock
        assert any(suite.TARGET_BACKENDS[t] == name for t in virtual)
    else:
        with pytest.raises(DeviceError, match="real clock"):
            registry.open_device(name, None, VirtualClock())


# ------------------------------------------------------------------ the recipe, followed once


def open_tiny(arg: str, config: Any, clock: Any, options: Any) -> SimDevice:
    """The tiny back-end's opener: ``tiny:SEED``, a simulated device seeded by the spec."""
    return SimDevice(config, clock, seed=int(arg), onset_jitter_s=0.001)


class TinyTarget(suite.SimTarget):
    name = backend = "tiny"

    def open(self):
        return registry.open_device("tiny:7", suite.rig_config(), VirtualClock())


@pytest.fixture
def tiny(monkeypatch):
    """Register the tiny back-end (module + one registration), for this test only."""
    monkeypatch.setattr(registry, "BACKENDS", dict(registry.BACKENDS))
    caps = registry.Capabilities(streaming=True, watchdog=False, faults=False, virtual_time=True)
    registry.register(
        registry.Backend("tiny", "required", "tiny:SEED", f"{__name__}:open_tiny", caps)
    )
    return TinyTarget()


@pytest.mark.parametrize("check", suite.CHECKS, ids=lambda c: c.__name__)
def test_a_backend_added_by_the_recipe_runs_the_suite(tiny, check):
    # one grammar: the session's --device check knows the new back-end at once
    assert opening.check_device_spec("tiny:3") == "tiny:3"
    with pytest.raises(MaskingLabError, match=r"tiny:SEED"):
        opening.check_device_spec("tiny")
    device = tiny.open()
    try:
        check(tiny, device)
    finally:
        device.close()


@pytest.mark.parametrize(
    ("claim", "check"),
    [
        ({"watchdog": True}, suite.check_watchdog_as_declared),
        ({"streaming": False}, suite.check_streaming_as_declared),
        ({"faults": True}, suite.check_faults_zero_and_resume),
    ],
)
def test_a_backend_that_misdeclares_fails_the_suite(tiny, claim, check):
    caps = registry.BACKENDS["tiny"].capabilities
    lying = registry.Backend(
        "tiny",
        "required",
        "tiny:SEED",
        open_tiny,
        registry.Capabilities(**{**caps.__dict__, **claim}),
    )
    registry.BACKENDS["tiny"] = lying
    device = tiny.open()
    try:
        with pytest.raises((AssertionError, pytest.fail.Exception)):
            check(tiny, device)
    finally:
        device.close()


def test_registering_a_taken_name_is_refused(tiny):
    with pytest.raises(MaskingLabError, match="taken"):
        registry.register(registry.BACKENDS["sim"])
