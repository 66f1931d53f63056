"""STAND-IN for NI's ``nidaqmx`` package (tests only; not NI's driver, no hardware).

See ``tests/nidaqmx_standin/__init__.py``.
"""

from nidaqmx import constants, errors, system
from nidaqmx.errors import DaqError
from nidaqmx.task import Task

__version__ = "0.0+standin"
__all__ = ["DaqError", "Task", "constants", "errors", "system"]
