"""STAND-IN ``nidaqmx.constants``: the enums the nidaq back-end uses, with NI's values."""

from enum import Enum


class AcquisitionType(Enum):
    FINITE = 10178
    CONTINUOUS = 10123
    HW_TIMED_SINGLE_POINT = 12522


class TaskMode(Enum):
    TASK_START = 0
    TASK_STOP = 1
    TASK_VERIFY = 2
    TASK_COMMIT = 3
    TASK_RESERVE = 4
    TASK_UNRESERVE = 5
    TASK_ABORT = 6


class WatchdogAOExpirState(Enum):
    VOLTAGE = 10322
    CURRENT = 10134
    NO_CHANGE = 10160


class WDTTaskAction(Enum):
    RESET_TIMER = 0
    CLEAR_EXPIRATION = 1


class AOIdleOutputBehavior(Enum):
    ZERO_VOLTS = 12526
    HIGH_IMPEDANCE = 12527
    MAINTAIN_EXISTING_VALUE = 12528


class Timescale(Enum):
    USE_HOST = 16126
    USE_IO_DEVICE = 16127
