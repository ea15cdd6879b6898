"""Typed exceptions.

Every error raised for bad input names the parameter, the value it got and what is
allowed, so the CLI can print it as one line (``nodlidar: <message>``) and exit 2.
"""

from __future__ import annotations

from typing import Any


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


class DesignFileError(NodlidarError, ValueError):
    """A design/calibration file is missing, malformed or incomplete."""


class InfeasibleDesignError(NodlidarError):
    """The requested split/geometry cannot be built; the message says why."""


class ProtocolError(NodlidarError):
    """A device spoke something the protocol does not allow (bad frame, checksum...)."""


class DeviceError(NodlidarError):
    """A device reported an error status or went away."""


class CalibrationError(NodlidarError, ValueError):
    """Calibration data cannot determine the mirrors (too few walls or points, parallel
    walls, ill-conditioned fit) or a calibration file does not belong to the design."""


def require(cond: bool, field: str, value: Any, allowed: str) -> None:
    """Raise :class:`ParameterError` unless ``cond`` holds."""
    if not cond:
        raise ParameterError(field, value, allowed)
