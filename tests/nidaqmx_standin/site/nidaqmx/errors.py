"""STAND-IN ``nidaqmx.errors``: the same class tree as NI's package."""


class Error(Exception):
    """Base error class of the package."""


class DaqNotFoundError(Error):
    """Raised when the NI-DAQmx driver is not installed."""


class DaqNotSupportedError(Error):
    """Raised when NI-DAQmx is not supported on this platform."""


class DaqFunctionNotSupportedError(Error):
    """Raised when the installed driver lacks a function."""


class DaqError(Error):
    """A driver call failed with an NI-DAQmx status code."""

    def __init__(self, message: str, error_code: int, task_name: str = "") -> None:
        self._error_code = int(error_code)
        if str(self._error_code) not in message:
            message = f"{message}\n\nStatus Code: {self._error_code}"
        super().__init__(message)

    @property
    def error_code(self) -> int:
        return self._error_code
