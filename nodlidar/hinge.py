"""The one hinge/lift model: each side's mirrors turn together about the side's lift axis.

Physically a side's mirrors sit on ONE printed carrier turned by ONE servo horn, so every
mirror of a side turns about the same line, the side's **lift axis** (docs/conventions.md,
"Mirror lift"). It is computed here, from the solved mirror faces alone (no CAD
parameters), and every layer uses it: the simulator (:mod:`nodlidar.sim.raycast`), the
CAD (:mod:`nodlidar.cad.mounts`, which builds the carrier's hinge on it) and the ROS
outputs (:mod:`nodlidar.runtime.ros`, the mirror joints' axes).

The rule (:func:`side_lift_axes`), per side, in the head frame:

* horizontal, at ``z = spec.mirror.hinge_z_m``;
* direction: the chord of the side's faces in plan, from the outer end of the outermost
  mirror's face to the inner end of the innermost one ("outer" = larger ``|bearing|``);
* through the most lidar-ward of the side's face end points (in plan), so every face lies
  on or behind the axis (away from the lidar);
* the lift turns the side by ``lift_rad`` about ``direction`` (right hand), signed so that
  the glass swings away from the lidar: for a hinge below the glass (every buildable
  design) the top of the glass goes away from the lidar; magnitude
  ``spec.mirror.lift_angle_rad``. At lift fraction ``f`` (0 deployed, 1 lifted) the
  side is turned by ``f * lift_rad``.

Not the lift: :meth:`~nodlidar.geometry.MirrorPatch.rotated_about_hinge` turns one mirror
about its own horizontal line ``origin + hinge_z*up + s*along``; that is the paper's
mounting error Delta-beta (:class:`~nodlidar.geometry.Perturbation`), a tilt of one glass
in its pocket, not a motion of the carrier.

numpy only. SI units.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from .errors import require
from .geometry import TOL, MirrorPatch, matrix_from_axis_angle, rotate_about_line, unit

if TYPE_CHECKING:
    from .design import Design

__all__ = ["SIDES", "LiftAxis", "side_lift_axes", "face_ends", "lift_fraction", "lifted_patch",
           "lifted_points"]

#: The two sides of the head, left (+y) and right.
SIDES = ("L", "R")
_EZ = np.array([0.0, 0.0, 1.0])


def _unit3(v: Any, name: str) -> tuple[float, float, float]:
    a = np.asarray(v, dtype=float).reshape(-1)
    require(a.shape == (3,) and bool(np.all(np.isfinite(a))), name, v, "a finite 3-vector")
    require(abs(float(np.linalg.norm(a)) - 1.0) < TOL.unit_norm, name, v, "unit length")
    return (float(a[0]), float(a[1]), float(a[2]))


@dataclass(frozen=True)
class LiftAxis:
    """One side's lift axis (head frame, metres).

    Attributes
    ----------
    side : str
        ``"L"`` or ``"R"``.
    point_m : (3,) float
        A point of the axis [m]: level with ``hinge_z``, abreast of the outer end of the
        side's outermost mirror face.
    direction : (3,) float
        Unit, horizontal: from the outer end towards the inner end of the side's mirrors.
    outward : (3,) float
        Unit, horizontal, perpendicular to ``direction``: away from the lidar (the side's
        faces lie on or behind the axis along it).
    lift_rad : float
        Signed rotation about ``direction`` (right hand) that lifts the side [rad]; the
        glass swings away from the lidar.
    """

    side: str
    point_m: tuple[float, float, float]
    direction: tuple[float, float, float]
    outward: tuple[float, float, float]
    lift_rad: float

    def __post_init__(self) -> None:
        require(self.side in SIDES, "side", self.side, "'L' or 'R'")
        p = np.asarray(self.point_m, dtype=float).reshape(-1)
        require(p.shape == (3,) and bool(np.all(np.isfinite(p))), "point_m", self.point_m,
                "a finite 3-vector [m]")
        object.__setattr__(self, "point_m", (float(p[0]), float(p[1]), float(p[2])))
        d = _unit3(self.direction, "direction")
        w = _unit3(self.outward, "outward")
        require(abs(d[2]) < TOL.unit_norm and abs(w[2]) < TOL.unit_norm, "direction",
                self.direction, "horizontal (the lift axis and its outward normal)")
        require(abs(float(np.dot(d, w))) < TOL.unit_norm, "outward", self.outward,
                "perpendicular to direction")
        object.__setattr__(self, "direction", d)
        object.__setattr__(self, "outward", w)
        require(math.isfinite(self.lift_rad) and 0 < abs(self.lift_rad) <= math.pi,
                "lift_rad", self.lift_rad, "0 < |lift_rad| <= pi [rad]")
        object.__setattr__(self, "lift_rad", float(self.lift_rad))

    @property
    def point_(self) -> np.ndarray:
        return np.asarray(self.point_m)

    @property
    def direction_(self) -> np.ndarray:
        return np.asarray(self.direction)

    @property
    def outward_(self) -> np.ndarray:
        return np.asarray(self.outward)

    @property
    def lift_direction(self) -> np.ndarray:
        """(3,) unit: the axis direction about which the lift is a positive (right-hand)
        rotation, ``sign(lift_rad) * direction`` (the ROS joints' x axis)."""
        return math.copysign(1.0, self.lift_rad) * self.direction_

    def angle(self, fraction: np.ndarray | float) -> np.ndarray:
        """Rotation [rad] about ``direction`` at lift fraction(s) ``fraction`` (0..1)."""
        return np.asarray(fraction, dtype=float) * self.lift_rad

    def transform(self, fraction: float) -> tuple[np.ndarray, np.ndarray]:
        """Rigid motion ``p -> R p + t`` [m] of the side at lift fraction ``fraction``:
        ``(R (3, 3), t (3,))``."""
        R = matrix_from_axis_angle(self.direction_, float(self.angle(fraction)))
        p = self.point_
        return R, p - R @ p

    def nearest_point(self, p: np.ndarray) -> np.ndarray:
        """The point(s) of the axis nearest ``p (..., 3)`` [m]."""
        q = np.asarray(p, dtype=float) - self.point_
        return self.point_ + (q @ self.direction_)[..., None] * self.direction_


def face_ends(patch: MirrorPatch) -> tuple[np.ndarray, np.ndarray]:
    """(outer, inner) ends [m] (3,) of a patch's face in the scan plane (``z = 0`` of the
    patch: its ``s_min`` and ``s_max`` points); outer = larger ``|bearing|``."""
    ends = patch.point(np.array([patch.s_min, patch.s_max]))
    b = np.abs(np.arctan2(ends[:, 1], ends[:, 0]))
    return (ends[0], ends[1]) if b[0] >= b[1] else (ends[1], ends[0])


def _axis_of_side(side: str, patches: list[MirrorPatch], hinge_z: float,
                  lift_angle: float) -> LiftAxis:
    """The lift axis of one side from its patches, outermost first (module docstring)."""
    ends = [face_ends(p) for p in patches]
    chord = ends[-1][1] - ends[0][0]
    c = unit(np.r_[chord[:2], 0.0])
    w = np.cross(c, _EZ)
    # outward = away from the lidar: opposite to the outermost face's normal (which points
    # towards the lidar)
    if w @ (-patches[0].normal_) < 0:
        w = -w
    ref = ends[0][0]
    pts = np.array([q for e in ends for q in e])
    e_min = float(np.min((pts - ref) @ w))
    a0 = ref + e_min * w
    a0[2] = hinge_z
    # the glass lies on the far side of the axis from the hinge: +z (above) for a hinge
    # below, -z for a hinge above. Turning by +angle about c takes a vector g*z to
    # g*(cos z + sin c x z); the glass goes away from the lidar when g (c x z) . w > 0
    g = 1.0 if hinge_z < 0 else -1.0
    sign = 1.0 if g * (np.cross(c, _EZ) @ w) > 0 else -1.0
    return LiftAxis(side=side, point_m=tuple(a0), direction=tuple(c), outward=tuple(w),
                    lift_rad=sign * float(lift_angle))


def side_lift_axes(design: Design) -> dict[str, LiftAxis]:
    """The lift axis of each side that has mirrors, keyed by side (``"L"``, ``"R"``).

    From the solved (nominal) mirror faces, ``spec.mirror.hinge_z_m`` and
    ``spec.mirror.lift_angle_rad`` only: the carrier is printed to the nominal design, so
    its axis does not move with a mirror's mounting error.

    Parameters
    ----------
    design : Design
        Solved design (its ``mirrors``: ``side``, ``index``, ``patch``; its ``spec``).
    """
    ms = design.spec.mirror
    out: dict[str, LiftAxis] = {}
    for side in SIDES:
        sols = sorted((m for m in design.mirrors if m.side == side), key=lambda m: m.index)
        if sols:
            out[side] = _axis_of_side(side, [m.patch for m in sols], float(ms.hinge_z_m),
                                      float(ms.lift_angle_rad))
    return out


def lift_fraction(servo_rad: np.ndarray | float, deployed_rad: float,
                  lifted_rad: float) -> np.ndarray:
    """How far a side is lifted (0 deployed .. 1 lifted, clipped) at lift-servo angle(s)
    [rad], linear between the servo's ``deployed_rad`` and ``lifted_rad``.

    Both ends are required: they come from the side's lift profile
    (``runtime.servo_angles.lift_profiles(design)``), never from a default, so the design
    file's lift angle is the only one."""
    require(math.isfinite(deployed_rad) and math.isfinite(lifted_rad)
            and lifted_rad != deployed_rad, "lifted_rad", lifted_rad,
            f"a finite servo angle [rad] other than deployed_rad = {deployed_rad!r}")
    a = np.asarray(servo_rad, dtype=float)
    return np.clip((a - deployed_rad) / (lifted_rad - deployed_rad), 0.0, 1.0)


def lifted_points(p: np.ndarray, axis: LiftAxis, fraction: np.ndarray | float) -> np.ndarray:
    """Points ``p (..., 3)`` [m] carried by the side, at lift fraction(s) ``fraction``
    (one, or one per row)."""
    return rotate_about_line(p, axis.point_, axis.direction_, axis.angle(fraction))


def lifted_patch(patch: MirrorPatch, axis: LiftAxis, fraction: float) -> MirrorPatch:
    """The glass ``patch`` at lift fraction ``fraction`` (0 deployed, 1 lifted): turned
    about its side's lift ``axis`` by ``fraction * axis.lift_rad``.

    ``hinge_z`` (the Delta-beta line, in the patch's own coordinates) travels with it."""
    R, t = axis.transform(fraction)
    return patch.transformed(R, t)
