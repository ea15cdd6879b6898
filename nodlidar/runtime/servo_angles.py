"""Servo angle math without a servo: profiles, the design's lift angles, interpolation.

Pure numpy (no pyserial): the assembly, recordings and calibration import this module, the
servo driver (:mod:`nodlidar.runtime.actuators`) re-exports it.

* :class:`NodProfile` - the linear nod ramp between two pitch limits.
* :class:`MirrorLiftProfile` - a mirror-lift servo's deployed and lifted angles;
  :meth:`MirrorLiftProfile.for_design` / :func:`lift_profiles` take the lifted angle from
  the design (the one lift model, :func:`nodlidar.hinge.side_lift_axes`).
* :func:`interpolate_angle` - every lidar beam its own servo angle from timestamped samples.
* :func:`unwrap_tick_ms` - the servo's realtime tick to seconds.

Lift servo mounting
-------------------
The servo horn turns the side's carrier directly, about the side's lift axis (no gearing):
the servo body sits at the outer end of the carrier with its shaft on the axis and the horn
facing the inner end, i.e. the shaft points along ``LiftAxis.direction``. A Dynamixel's
position grows counter-clockwise seen from the horn, which is a right-handed turn about that
direction, so the lifted servo angle is ``deployed_rad + LiftAxis.lift_rad``: the design's
``mirror.lift_angle_rad`` with the side's sign (for the paper build the left servo turns
negative, the right one positive). The simulated sensor maps a servo angle ``a`` to the lift
fraction ``(a - deployed) / (lifted - deployed)`` of the same profile, so one servo radian
is one radian of the carrier about its axis on both sides.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

import numpy as np
from numpy.typing import ArrayLike

from ..dynamixel import RAD_PER_TICK, RAD_S_PER_VELOCITY_UNIT, REALTIME_TICK_MODULO
from ..errors import ParameterError, require
from ..hinge import side_lift_axes

if TYPE_CHECKING:  # pragma: no cover
    from ..solver import Design

__all__ = [
    "MIN_ANGLE_RAD",
    "MAX_ANGLE_RAD",
    "MAX_RATE_RAD_S",
    "SIDES",
    "NodProfile",
    "MirrorLiftProfile",
    "lift_profiles",
    "interpolate_angle",
    "unwrap_tick_ms",
]

#: Servo angle range [rad] (tick 0 .. 4095, 0 rad = tick 2048).
MIN_ANGLE_RAD = -math.pi
MAX_ANGLE_RAD = (4095 - 2048) * RAD_PER_TICK
#: Highest profile velocity [rad/s] (1023 velocity units).
MAX_RATE_RAD_S = 1023 * RAD_S_PER_VELOCITY_UNIT
#: Runtime side names -> the design's mirror sides.
SIDES = {"left": "L", "right": "R"}


# -- nod ramp ---------------------------------------------------------------------


@dataclass(frozen=True)
class NodProfile:
    """The nod: a linear ramp back and forth between two pitch limits.

    Attributes
    ----------
    lower_rad, upper_rad : float
        Pitch limits [rad] (servo angle, 0 = tick 2048), ``lower < upper``.
    rate_rad_s : float
        Nod rate [rad/s] (constant angular speed along each ramp).
    """

    lower_rad: float
    upper_rad: float
    rate_rad_s: float

    def __post_init__(self) -> None:
        require(
            math.isfinite(self.lower_rad)
            and math.isfinite(self.upper_rad)
            and MIN_ANGLE_RAD <= self.lower_rad < self.upper_rad <= MAX_ANGLE_RAD,
            "nod.limits_rad",
            (self.lower_rad, self.upper_rad),
            f"{MIN_ANGLE_RAD:.4f} <= lower < upper <= {MAX_ANGLE_RAD:.4f}",
        )
        require(
            math.isfinite(self.rate_rad_s) and 0 < self.rate_rad_s <= MAX_RATE_RAD_S,
            "nod.rate_rad_s",
            self.rate_rad_s,
            f"(0, {MAX_RATE_RAD_S:.3f}] rad/s",
        )

    @property
    def amplitude_rad(self) -> float:
        """Sweep ``upper - lower`` [rad]."""
        return self.upper_rad - self.lower_rad

    @property
    def sweep_time_s(self) -> float:
        """Duration of one ramp (lower -> upper) [s]."""
        return self.amplitude_rad / self.rate_rad_s

    @property
    def period_s(self) -> float:
        """Duration of a full nod (up and down) [s]."""
        return 2.0 * self.sweep_time_s

    def angle_at(self, t: ArrayLike, t_start: float = 0.0) -> float | np.ndarray:
        """Ideal nod angle [rad] at time(s) ``t`` [s]: at ``lower`` at ``t_start``, rising.

        Vectorised; a triangle wave with turnarounds every :attr:`sweep_time_s`.
        """
        tau = np.mod(np.asarray(t, dtype=float) - t_start, self.period_s)
        up = tau <= self.sweep_time_s
        s = np.where(up, tau, self.period_s - tau) * self.rate_rad_s
        out = self.lower_rad + s
        return float(out) if out.ndim == 0 else out


# -- mirror lift ------------------------------------------------------------------


@dataclass(frozen=True)
class MirrorLiftProfile:
    """Angles of one mirror-lift servo.

    Build it from the design with :meth:`for_design` (or :func:`lift_profiles`): the
    lifted angle depends on the design's lift angle and on the side, so there is no default.

    Attributes
    ----------
    deployed_rad : float
        Servo angle [rad] with the mirror in its working (deployed) position.
    lifted_rad : float
        Servo angle [rad] with the mirror lifted out of the beam.
    rate_rad_s : float
        Lift speed [rad/s].
    """

    deployed_rad: float
    lifted_rad: float
    rate_rad_s: float = 1.0

    def __post_init__(self) -> None:
        for name in ("deployed_rad", "lifted_rad"):
            v = getattr(self, name)
            require(
                math.isfinite(v) and MIN_ANGLE_RAD <= v <= MAX_ANGLE_RAD,
                f"mirror.{name}",
                v,
                f"[{MIN_ANGLE_RAD:.4f}, {MAX_ANGLE_RAD:.4f}]",
            )
        require(
            self.deployed_rad != self.lifted_rad,
            "mirror.lifted_rad",
            self.lifted_rad,
            "different from deployed_rad",
        )
        require(
            math.isfinite(self.rate_rad_s) and 0 < self.rate_rad_s <= MAX_RATE_RAD_S,
            "mirror.rate_rad_s",
            self.rate_rad_s,
            f"(0, {MAX_RATE_RAD_S:.3f}] rad/s",
        )

    @classmethod
    def for_design(cls, design: Design, side: str, *, deployed_rad: float = 0.0,
                   rate_rad_s: float = 1.0) -> MirrorLiftProfile:
        """The profile of one side's lift servo for a solved design.

        Parameters
        ----------
        design : Design
            Solved design: its side lift axis (:func:`nodlidar.hinge.side_lift_axes`) gives
            the signed lift ``LiftAxis.lift_rad`` (magnitude ``mirror.lift_angle_rad``).
        side : {"left", "right", "L", "R"}
        deployed_rad : float
            Servo angle [rad] of the deployed carrier (where the horn was fixed).
        rate_rad_s : float
            Lift speed [rad/s].

        Returns
        -------
        MirrorLiftProfile
            ``lifted_rad = deployed_rad + LiftAxis.lift_rad`` (see the module docstring).

        Raises
        ------
        ParameterError
            Unknown side, a side without mirrors, or a lifted angle outside the servo range.
        """
        key = SIDES.get(side, side)
        if key not in SIDES.values():
            raise ParameterError("mirror.side", side, "'left', 'right', 'L' or 'R'")
        axes = side_lift_axes(design)
        require(key in axes, "mirror.side", side, f"a side with mirrors ({', '.join(sorted(axes))})")
        return cls(deployed_rad=float(deployed_rad),
                   lifted_rad=float(deployed_rad) + float(axes[key].lift_rad),
                   rate_rad_s=float(rate_rad_s))


def lift_profiles(design: Design, *, deployed_rad: float = 0.0, rate_rad_s: float = 1.0
                  ) -> tuple[MirrorLiftProfile, MirrorLiftProfile]:
    """``(left, right)`` :meth:`MirrorLiftProfile.for_design` of a solved design; a side
    without mirrors gets the other side's angles mirrored (its servo never matters)."""
    axes = side_lift_axes(design)
    out = []
    for side, key in SIDES.items():
        other = "R" if key == "L" else "L"
        if key in axes:
            out.append(MirrorLiftProfile.for_design(design, side, deployed_rad=deployed_rad,
                                                    rate_rad_s=rate_rad_s))
        else:
            lift = -float(axes[other].lift_rad)
            out.append(MirrorLiftProfile(float(deployed_rad), float(deployed_rad) + lift,
                                         float(rate_rad_s)))
    return out[0], out[1]


# -- interpolation ----------------------------------------------------------------


def interpolate_angle(
    sample_times: ArrayLike,
    sample_angles: ArrayLike,
    query_times: ArrayLike,
    *,
    outside: Literal["nan", "clamp", "extrapolate"] = "nan",
) -> np.ndarray:
    """Angle at each query time by linear interpolation between samples.

    Parameters
    ----------
    sample_times : array_like, shape (n,)
        Sample times [s], strictly increasing.
    sample_angles : array_like, shape (n,)
        Angles [rad] at ``sample_times``.
    query_times : array_like
        Times [s] to evaluate (any shape, e.g. one per lidar beam).
    outside : {"nan", "clamp", "extrapolate"}
        Queries before the first / after the last sample: NaN (default, so a beam
        newer than the newest sample is not silently given a stale angle), the
        end sample's angle, or linear extrapolation of the end segment.

    Returns
    -------
    ndarray of float
        Angles [rad], shape of ``query_times``.

    Raises
    ------
    ParameterError
        Mismatched lengths, too few samples, unsorted times, bad ``outside``.
    """
    t = np.asarray(sample_times, dtype=float)
    a = np.asarray(sample_angles, dtype=float)
    q = np.asarray(query_times, dtype=float)
    require(t.ndim == 1, "sample_times.ndim", t.ndim, "1")
    require(a.shape == t.shape, "sample_angles.shape", a.shape, f"{t.shape} (as sample_times)")
    require(
        outside in ("nan", "clamp", "extrapolate"),
        "outside",
        outside,
        "'nan', 'clamp' or 'extrapolate'",
    )
    n_min = 2 if outside == "extrapolate" else 1
    require(t.size >= n_min, "sample_times.size", t.size, f">= {n_min}")
    if t.size > 1:
        d = np.diff(t)
        if not np.all(d > 0):
            k = int(np.argmin(d > 0))
            raise ParameterError(
                f"sample_times[{k + 1}]",
                float(t[k + 1]),
                f"> sample_times[{k}] = {t[k]!r} (strictly increasing)",
            )
    out = np.interp(q, t, a)
    if outside == "clamp":
        return out
    lo, hi = q < t[0], q > t[-1]
    if outside == "nan":
        out = np.where(lo | hi, np.nan, out)
    else:
        s0 = (a[1] - a[0]) / (t[1] - t[0])
        s1 = (a[-1] - a[-2]) / (t[-1] - t[-2])
        out = np.where(lo, a[0] + s0 * (q - t[0]), out)
        out = np.where(hi, a[-1] + s1 * (q - t[-1]), out)
    return out


def unwrap_tick_ms(tick_ms: ArrayLike) -> np.ndarray:
    """Unwrap the servo realtime tick (ms modulo 32768) to seconds since the first sample.

    Assumes consecutive samples are less than 32.768 s apart.
    """
    k = np.asarray(tick_ms, dtype=np.int64)
    if k.size == 0:
        return np.zeros(0)
    d = np.diff(k) % REALTIME_TICK_MODULO
    return np.concatenate([[0], np.cumsum(d)]) * 1e-3
