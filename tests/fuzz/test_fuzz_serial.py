"""Seeded fuzzing of the serial frames the host reads (issue 11, items 3 and 6): one mutated
HELLO, TIME, PLAY reply or DONE event from a scripted device on a real pty per example; the
host ends in a DeviceError or a played trial, never another exception, never a hang."""

from __future__ import annotations

from fuzz_serial import serial_trial
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st


class DrawPicker:
    def __init__(self, data: st.DataObject) -> None:
        self.data = data

    def int(self, lo: int, hi: int) -> int:
        return self.data.draw(st.integers(lo, hi))


@settings(
    derandomize=True, max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow]
)
@given(data=st.data())
def test_mutated_frames_end_in_a_device_error_or_a_trial(data):
    status, detail = serial_trial(DrawPicker(data), timeout_s=15.0)
    assert status == "clean", detail
