"""Typed exceptions.

Every error raised for bad input names the parameter, the value it got and what is
allowed, so the CLI can print it as one line (``nodlidar: <message>``) and exit 2.
"""

from __future__ import annotations

from typing import Any

__all__ = [
    "NodlidarError",
    "ParameterError",
    "InputFileError",
    "DesignFileError",
    "UnknownKeyError",
    "InfeasibleDesignError",
    "ProtocolError",
    "DeviceError",
    "CalibrationError",
    "require",
]


class NodlidarError(Exception):
    """Base class of every error nodlidar raises on purpose."""


class ParameterError(NodlidarError, ValueError):
    """A parameter has a value outside what is allowed.

    Parameters
    ----------
    field : str
        Dotted name of the parameter, e.g. ``"layout.design_distance_m"``.
    value : Any
        The offending value.
    allowed : str
        Human-readable description of what is allowed.
    """

    def __init__(self, field: str, value: Any, allowed: str):
        self.field = field
        self.value = value
        self.allowed = allowed
        super().__init__(f"{field} = {value!r} is invalid; allowed: {allowed}")

    def __reduce__(self):
        # the constructor's arguments, not the message: a worker process's error reaches
        # the parent whole (pickled by multiprocessing), not as a TypeError of the unpickler
        return type(self), (self.field, self.value, self.allowed)


class InputFileError(NodlidarError, ValueError):
    """An input file cannot be read as what it should be: missing, not a regular file (a
    FIFO, a directory), too large, not UTF-8 text, or malformed TOML. The message names
    the file."""


class DesignFileError(InputFileError):
    """A design/calibration file is missing, malformed or incomplete."""


class UnknownKeyError(DesignFileError, ParameterError):
    """A TOML file has a section or key nobody reads (usually a typo).

    The message names the file and suggests the nearest valid name, e.g. ``unknown
    section [tolerence] in x.toml; did you mean [tolerance]?``. It is a
    :class:`ParameterError` too (``field`` is the dotted name, ``allowed`` the valid names).
    """

    def __init__(self, message: str, field: str, value: Any, allowed: str):
        self.field = field
        self.value = value
        self.allowed = allowed
        Exception.__init__(self, message)

    def __reduce__(self):
        return type(self), (self.args[0], self.field, self.value, self.allowed)


class InfeasibleDesignError(NodlidarError):
    """The requested split/geometry cannot be built; the message says why."""


class ProtocolError(NodlidarError):
    """A device spoke something the protocol does not allow (bad frame, checksum...)."""


class DeviceError(NodlidarError):
    """A device reported an error status or went away."""


class CalibrationError(NodlidarError, ValueError):
    """Calibration data cannot determine the mirrors (too few walls or points, parallel
    walls, ill-conditioned fit) or a calibration file does not belong to the design."""


def require(cond: object, field: str, value: Any, allowed: str) -> None:
    """Raise :class:`ParameterError` unless ``cond`` holds (a ``bool`` or a numpy scalar bool:
    anything with a truth value; an array of several elements raises ``ValueError``)."""
    if not cond:
        raise ParameterError(field, value, allowed)
