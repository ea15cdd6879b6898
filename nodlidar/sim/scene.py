"""Scenes for the simulated sensor: static geometry, moving objects and the sensor's pose.

A :class:`Scene` is a frozen description (no meshes are built until asked): a room
(walls, floor, optional ceiling), static boxes, finite planes at a given pose (test and
calibration walls), moving objects on trajectories (a vertical cylinder or a box,
translating rigidly), and the pose of the sensor base over time (fixed, or driving at a
constant velocity). All coordinates are in the **world frame** [m], z up; the sensor base
frame is placed in it by :class:`SensorPose` (yaw only: the robot drives on a flat floor).

Scenes load from TOML (:meth:`Scene.from_toml`, :func:`scene_from_dict`) or by name
(:func:`builtin_scene`: ``"room"``, ``"paper-tracking"``, ``"wall"``); :func:`load_scene`
takes either. TOML format (angles in degrees at this edge, ``*_deg``)::

    name = "my-scene"
    [sensor]                      # optional; default at the origin, 0.4 m up, facing +x
    position_m = [0.0, 0.0, 0.4]
    yaw_deg = 0.0
    velocity_m_s = [0.0, 0.0, 0.0]
    [room]                        # optional
    size_m = [6.0, 5.0, 2.5]      # x, y extent and height
    center_m = [1.5, 0.0]         # floor centre (x, y)
    floor_z_m = 0.0
    ceiling = true
    [[box]]
    size_m = [0.5, 0.5, 1.0]
    center_m = [3.0, 1.0, 0.5]
    yaw_deg = 20.0
    [[plane]]                     # a finite rectangle, both sides visible
    center_m = [2.0, 0.0, 0.4]
    normal = [-1.0, 0.0, 0.0]
    size_m = [4.0, 3.0]           # width (horizontal), height
    [[wall]]                      # a vertical plane with openings (doorways, windows)
    center_m = [1.0, 0.0, 1.25]
    normal = [-1.0, 0.0, 0.0]     # horizontal; towards the side it is seen from
    size_m = [6.0, 2.5]           # width, height
    [[wall.opening]]              # a rectangular hole
    offset_m = 0.6                # its centre's offset from the wall centre along the width,
                                  # positive to the right as seen from the normal's side
    width_m = 0.9
    height_m = 2.0
    bottom_m = 0.0                # above the wall's bottom edge (0: a doorway)
    [[pole]]                      # a static vertical cylinder
    center_m = [0.8, 0.3]         # axis (x, y)
    radius_m = 0.05
    height_m = 2.0
    base_z_m = 0.0
    [[mover]]
    shape = "cylinder"            # or "box" (then size_m = [x, y, z])
    radius_m = 0.18
    height_m = 1.0
    base_z_m = 0.0                # bottom of the shape relative to the trajectory point
    trajectory = "back_and_forth" # or "constant_velocity", "fixed", "waypoints"
    start_m = [2.0, -0.8, 0.0]
    end_m = [2.0, 0.8, 0.0]
    speed_m_s = 0.13
    [[mover]]                     # stop and go: straight legs between waypoints
    trajectory = "waypoints"
    points_m = [[1.5, -1.0, 0.0], [2.5, -1.0, 0.0], [2.5, 0.5, 0.0]]
    speed_m_s = 0.6               # or one per leg: [0.6, 0.3]
    pause_s = 2.0                 # waits at each waypoint it reaches (default 0)
    loop = false                  # true: on to the first waypoint and round again

Object ids used in ground truth: :data:`HIT_NONE` (-1) no hit, :data:`HIT_STATIC` (0) the
static world, ``1 + k`` mover ``k``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from ..errors import DesignFileError, ParameterError, require
from ..paper import TRACKING_HEADING_DEG, TRACKING_SPEED_M_S

if TYPE_CHECKING:
    import trimesh

__all__ = [
    "HIT_NONE",
    "HIT_STATIC",
    "Box",
    "Plane",
    "Wall",
    "Opening",
    "Pole",
    "Room",
    "Cylinder",
    "Fixed",
    "ConstantVelocity",
    "BackAndForth",
    "Waypoints",
    "Mover",
    "SensorPose",
    "Scene",
    "scene_from_dict",
    "builtin_scene",
    "load_scene",
    "wall_scene",
    "paper_tracking_scene",
    "room_scene",
    "BUILTIN_SCENES",
]

HIT_NONE = -1
HIT_STATIC = 0

# facets of a cylinder mesh: the chord sag r (1 - cos(pi/n)) is 0.05 mm for r = 0.2 m,
# n = 128, well below the 1 mm quantisation of the range
_CYLINDER_SECTIONS = 128


def _v3(v, name: str) -> tuple[float, float, float]:
    a = np.asarray(v, dtype=float).reshape(-1)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise ParameterError(name, v, "3 finite numbers")
    return (float(a[0]), float(a[1]), float(a[2]))


def _v2(v, name: str) -> tuple[float, float]:
    a = np.asarray(v, dtype=float).reshape(-1)
    if a.shape != (2,) or not np.all(np.isfinite(a)):
        raise ParameterError(name, v, "2 finite numbers")
    return (float(a[0]), float(a[1]))


def _rect_mesh(center: np.ndarray, u: np.ndarray, v: np.ndarray, w: float, h: float):
    """Two triangles spanning ``center +- w/2 u +- h/2 v``."""
    import trimesh

    c = [center + a * w / 2 * u + b * h / 2 * v for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
    return trimesh.Trimesh(vertices=np.array(c), faces=[[0, 1, 2], [0, 2, 3]], process=False)


# -- static geometry ---------------------------------------------------------------------
@dataclass(frozen=True)
class Box:
    """An axis-upright box: ``size_m`` (x, y, z) [m] centred at ``center_m``, turned by ``yaw_rad``."""

    size_m: tuple[float, float, float]
    center_m: tuple[float, float, float]
    yaw_rad: float = 0.0
    name: str = "box"

    def __post_init__(self) -> None:
        object.__setattr__(self, "size_m", _v3(self.size_m, f"{self.name}.size_m"))
        object.__setattr__(self, "center_m", _v3(self.center_m, f"{self.name}.center_m"))
        require(min(self.size_m) > 0, f"{self.name}.size_m", self.size_m, "all > 0 m")

    def mesh(self) -> trimesh.Trimesh:
        """trimesh.Trimesh of the box in the frame it is given in."""
        import trimesh

        T = np.eye(4)
        c, s = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        T[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
        T[:3, 3] = self.center_m
        return trimesh.creation.box(extents=self.size_m, transform=T)

    def parts(self) -> list[tuple[str, Any]]:
        return [(self.name, self.mesh())]


@dataclass(frozen=True)
class Plane:
    """A finite flat rectangle (visible from both sides).

    Attributes
    ----------
    center_m : (3,) float
        Centre [m].
    normal : (3,) float
        Normal (normalised here; either sign).
    size_m : (2,) float
        Width along the horizontal in-plane direction and height along the other [m]
        (for a horizontal plane: along x and y).
    """

    center_m: tuple[float, float, float]
    normal: tuple[float, float, float]
    size_m: tuple[float, float] = (10.0, 10.0)
    name: str = "plane"

    def __post_init__(self) -> None:
        object.__setattr__(self, "center_m", _v3(self.center_m, f"{self.name}.center_m"))
        n = np.asarray(_v3(self.normal, f"{self.name}.normal"))
        require(np.linalg.norm(n) > 1e-9, f"{self.name}.normal", self.normal, "non-zero")
        object.__setattr__(self, "normal", tuple(map(float, n / np.linalg.norm(n))))
        object.__setattr__(self, "size_m", _v2(self.size_m, f"{self.name}.size_m"))
        require(min(self.size_m) > 0, f"{self.name}.size_m", self.size_m, "both > 0 m")

    def axes(self) -> tuple[np.ndarray, np.ndarray]:
        """In-plane unit axes (width, height): width horizontal unless the plane is."""
        n = np.asarray(self.normal)
        ref = np.array([0.0, 0.0, 1.0]) if abs(n[2]) < 0.9 else np.array([0.0, 1.0, 0.0])
        u = np.cross(ref, n)
        u /= np.linalg.norm(u)
        return u, np.cross(n, u)

    def mesh(self) -> trimesh.Trimesh:
        u, v = self.axes()
        return _rect_mesh(np.asarray(self.center_m), u, v, *self.size_m)

    def parts(self) -> list[tuple[str, Any]]:
        return [(self.name, self.mesh())]


@dataclass(frozen=True)
class Opening:
    """A rectangular hole in a :class:`Wall` (a doorway when ``bottom_m = 0``).

    ``offset_m``: its centre's horizontal offset from the wall centre [m], positive to the
    right as seen from the side the wall's normal points to; ``bottom_m``: its lower edge
    above the wall's bottom edge [m].
    """

    offset_m: float
    width_m: float
    height_m: float
    bottom_m: float = 0.0

    def __post_init__(self) -> None:
        for f in ("offset_m", "width_m", "height_m", "bottom_m"):
            v = getattr(self, f)
            require(isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v),
                    f"opening.{f}", v, "a finite number [m]")
            object.__setattr__(self, f, float(v))
        require(self.width_m > 0 and self.height_m > 0, "opening.width_m/height_m",
                (self.width_m, self.height_m), "both > 0 m")
        require(self.bottom_m >= 0, "opening.bottom_m", self.bottom_m, ">= 0 m")


@dataclass(frozen=True)
class Wall:
    """A vertical rectangle with rectangular openings (doorways, windows).

    ``normal`` must be horizontal; the width runs along ``u = z x normal`` (to the right as
    seen from the normal's side), the height along z. Openings must lie inside the wall.
    """

    center_m: tuple[float, float, float]
    normal: tuple[float, float, float]
    size_m: tuple[float, float]
    openings: tuple[Opening, ...] = ()
    name: str = "wall"

    def __post_init__(self) -> None:
        object.__setattr__(self, "center_m", _v3(self.center_m, f"{self.name}.center_m"))
        n = np.asarray(_v3(self.normal, f"{self.name}.normal"))
        require(np.hypot(n[0], n[1]) > 1e-9 and abs(n[2]) < 1e-9 * np.linalg.norm(n),
                f"{self.name}.normal", self.normal, "horizontal and non-zero (walls are vertical)")
        object.__setattr__(self, "normal", tuple(map(float, n / np.linalg.norm(n))))
        object.__setattr__(self, "size_m", _v2(self.size_m, f"{self.name}.size_m"))
        require(min(self.size_m) > 0, f"{self.name}.size_m", self.size_m, "both > 0 m")
        object.__setattr__(self, "openings", tuple(self.openings))
        w, h = self.size_m
        for i, o in enumerate(self.openings):
            require(isinstance(o, Opening), f"{self.name}.opening[{i}]", type(o).__name__, "Opening")
            require(abs(o.offset_m) + o.width_m / 2 <= w / 2 + 1e-9
                    and o.bottom_m + o.height_m <= h + 1e-9, f"{self.name}.opening[{i}]",
                    (o.offset_m, o.width_m, o.bottom_m, o.height_m),
                    f"inside the {w:g} x {h:g} m wall")

    def rects(self) -> list[tuple[float, float, float, float]]:
        """The solid parts as ``(u0, u1, z0, z1)`` rectangles in wall coordinates [m]
        (u from the centre along the width, z from the bottom edge)."""
        w, h = self.size_m
        cuts = sorted({-w / 2, w / 2} | {o.offset_m + s * o.width_m / 2 for o in self.openings
                                          for s in (-1, 1)})
        out = []
        for u0, u1 in zip(cuts[:-1], cuts[1:]):
            um = (u0 + u1) / 2
            holes = sorted((o.bottom_m, o.bottom_m + o.height_m) for o in self.openings
                           if abs(um - o.offset_m) < o.width_m / 2)
            z = 0.0
            for z0, z1 in holes:
                if z0 > z:
                    out.append((u0, u1, z, z0))
                z = max(z, z1)
            if z < h:
                out.append((u0, u1, z, h))
        return out

    def mesh(self) -> trimesh.Trimesh:
        import trimesh

        n = np.asarray(self.normal)
        u = np.cross([0.0, 0.0, 1.0], n)
        u /= np.linalg.norm(u)
        zc = np.array([0.0, 0.0, 1.0])
        bottom = np.asarray(self.center_m) - self.size_m[1] / 2 * zc
        parts = [_rect_mesh(bottom + (u0 + u1) / 2 * u + (z0 + z1) / 2 * zc, u, zc, u1 - u0, z1 - z0)
                 for u0, u1, z0, z1 in self.rects()]
        # Trimesh parts concatenate to one Trimesh (the annotation says only Geometry)
        return cast("trimesh.Trimesh", trimesh.util.concatenate(parts))

    def parts(self) -> list[tuple[str, Any]]:
        return [(self.name, self.mesh())]


@dataclass(frozen=True)
class Pole:
    """A static vertical cylinder: axis at ``center_m`` (x, y), from ``base_z_m`` up."""

    center_m: tuple[float, float]
    radius_m: float
    height_m: float
    base_z_m: float = 0.0
    name: str = "pole"

    def __post_init__(self) -> None:
        object.__setattr__(self, "center_m", _v2(self.center_m, f"{self.name}.center_m"))
        require(self.radius_m > 0, f"{self.name}.radius_m", self.radius_m, "> 0 m")
        require(self.height_m > 0, f"{self.name}.height_m", self.height_m, "> 0 m")

    def mesh(self) -> trimesh.Trimesh:
        import trimesh

        T = np.eye(4)
        T[:3, 3] = (*self.center_m, self.base_z_m + self.height_m / 2)
        return trimesh.creation.cylinder(radius=self.radius_m, height=self.height_m,
                                         sections=_CYLINDER_SECTIONS, transform=T)

    def parts(self) -> list[tuple[str, Any]]:
        return [(self.name, self.mesh())]


@dataclass(frozen=True)
class Room:
    """Four walls and a floor (and a ceiling if asked), as inward-facing planes.

    ``size_m`` = (x extent, y extent, height) [m]; ``center_m`` the floor centre (x, y).
    """

    size_m: tuple[float, float, float] = (6.0, 5.0, 2.5)
    center_m: tuple[float, float] = (1.5, 0.0)
    floor_z_m: float = 0.0
    ceiling: bool = True
    name: str = "room"

    def __post_init__(self) -> None:
        object.__setattr__(self, "size_m", _v3(self.size_m, f"{self.name}.size_m"))
        object.__setattr__(self, "center_m", _v2(self.center_m, f"{self.name}.center_m"))
        require(min(self.size_m) > 0, f"{self.name}.size_m", self.size_m, "all > 0 m")

    def planes(self) -> list[Plane]:
        lx, ly, h = self.size_m
        cx, cy = self.center_m
        z0, zc = self.floor_z_m, self.floor_z_m + h / 2
        out = [
            Plane((cx + lx / 2, cy, zc), (-1, 0, 0), (ly, h), f"{self.name}.wall+x"),
            Plane((cx - lx / 2, cy, zc), (1, 0, 0), (ly, h), f"{self.name}.wall-x"),
            Plane((cx, cy + ly / 2, zc), (0, -1, 0), (lx, h), f"{self.name}.wall+y"),
            Plane((cx, cy - ly / 2, zc), (0, 1, 0), (lx, h), f"{self.name}.wall-y"),
            Plane((cx, cy, z0), (0, 0, 1), (lx, ly), f"{self.name}.floor"),
        ]
        if self.ceiling:
            out.append(Plane((cx, cy, z0 + h), (0, 0, -1), (lx, ly), f"{self.name}.ceiling"))
        return out

    def parts(self) -> list[tuple[str, Any]]:
        return [(p.name, p.mesh()) for p in self.planes()]


# -- moving objects ----------------------------------------------------------------------
@dataclass(frozen=True)
class Cylinder:
    """A vertical cylinder, axis through the trajectory point, bottom at ``base_z_m`` above it."""

    radius_m: float
    height_m: float
    base_z_m: float = 0.0

    def __post_init__(self) -> None:
        require(self.radius_m > 0, "cylinder.radius_m", self.radius_m, "> 0 m")
        require(self.height_m > 0, "cylinder.height_m", self.height_m, "> 0 m")

    def mesh(self) -> trimesh.Trimesh:
        """Mesh in the object frame (trajectory point at the origin)."""
        import trimesh

        T = np.eye(4)
        T[2, 3] = self.base_z_m + self.height_m / 2
        return trimesh.creation.cylinder(radius=self.radius_m, height=self.height_m,
                                         sections=_CYLINDER_SECTIONS, transform=T)


@dataclass(frozen=True)
class Fixed:
    """A trajectory that stays at ``position_m`` [m]."""

    position_m: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        object.__setattr__(self, "position_m", _v3(self.position_m, "trajectory.position_m"))

    def position(self, t: np.ndarray | float) -> np.ndarray:
        """Position(s) [m] at times ``t`` [s]: ``shape(t) + (3,)``."""
        t = np.asarray(t, dtype=float)
        return np.broadcast_to(np.asarray(self.position_m), t.shape + (3,)).copy()


@dataclass(frozen=True)
class ConstantVelocity:
    """``position(t) = start_m + velocity_m_s * (t - t0_s)`` [m]."""

    start_m: tuple[float, float, float]
    velocity_m_s: tuple[float, float, float]
    t0_s: float = 0.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "start_m", _v3(self.start_m, "trajectory.start_m"))
        object.__setattr__(self, "velocity_m_s", _v3(self.velocity_m_s, "trajectory.velocity_m_s"))

    def position(self, t: np.ndarray | float) -> np.ndarray:
        t = np.asarray(t, dtype=float)
        return np.asarray(self.start_m) + (t - self.t0_s)[..., None] * np.asarray(self.velocity_m_s)


@dataclass(frozen=True)
class BackAndForth:
    """Constant speed from ``start_m`` to ``end_m`` and back, forever (triangle wave).

    At ``t0_s`` the object is at ``start_m`` heading for ``end_m``.
    """

    start_m: tuple[float, float, float]
    end_m: tuple[float, float, float]
    speed_m_s: float
    t0_s: float = 0.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "start_m", _v3(self.start_m, "trajectory.start_m"))
        object.__setattr__(self, "end_m", _v3(self.end_m, "trajectory.end_m"))
        require(self.speed_m_s > 0, "trajectory.speed_m_s", self.speed_m_s, "> 0 m/s")
        require(self.length_m > 0, "trajectory.end_m", self.end_m, "different from start_m")

    @classmethod
    def from_heading(cls, start_m: Sequence[float], heading_rad: float, speed_m_s: float, length_m: float,
                     t0_s: float = 0.0) -> BackAndForth:
        """Leg of ``length_m`` [m] from ``start_m`` along heading ``heading_rad`` (from +x)."""
        s = np.asarray(start_m, dtype=float)
        e = s + length_m * np.array([math.cos(heading_rad), math.sin(heading_rad), 0.0])
        return cls(tuple(s), tuple(e), speed_m_s, t0_s)

    @property
    def length_m(self) -> float:
        return float(np.linalg.norm(np.subtract(self.end_m, self.start_m)))

    @property
    def leg_s(self) -> float:
        """Time of one leg [s]."""
        return self.length_m / self.speed_m_s

    def velocity(self, t: np.ndarray | float) -> np.ndarray:
        """Velocity [m/s] at ``t`` [s], ``shape(t) + (3,)``."""
        t = np.asarray(t, dtype=float)
        u = np.subtract(self.end_m, self.start_m) / self.length_m
        sign = np.where(np.mod(t - self.t0_s, 2 * self.leg_s) < self.leg_s, 1.0, -1.0)
        return sign[..., None] * self.speed_m_s * u

    def position(self, t: np.ndarray | float) -> np.ndarray:
        t = np.asarray(t, dtype=float)
        T = self.leg_s
        ph = np.mod(t - self.t0_s, 2 * T)
        frac = np.where(ph < T, ph, 2 * T - ph) / T
        s = np.asarray(self.start_m)
        return s + frac[..., None] * (np.asarray(self.end_m) - s)


@dataclass(frozen=True)
class Waypoints:
    """Straight legs through ``points_m`` [m] at ``speed_m_s`` [m/s] (one value, or one
    per leg), waiting ``pause_s`` [s] at each waypoint it reaches: a person who stops and
    turns, a cart taken round a corner. After the last waypoint it stays there; with
    ``loop`` it goes on to the first and round again (then it also waits at the first on
    each return). Before ``t0_s`` [s] it waits at the first waypoint.
    """

    points_m: tuple[tuple[float, float, float], ...]
    speed_m_s: float | tuple[float, ...]
    pause_s: float = 0.0
    loop: bool = False
    t0_s: float = 0.0

    def __post_init__(self) -> None:
        raw = self.points_m
        require(isinstance(raw, Sequence) and len(raw) >= 2, "trajectory.points_m",
                raw, "a list of at least 2 waypoints [x, y, z]")
        pts = tuple(_v3(p, f"trajectory.points_m[{i}]") for i, p in enumerate(raw))
        object.__setattr__(self, "points_m", pts)
        legs = len(pts) - 1 + int(bool(self.loop))
        require(isinstance(self.loop, bool), "trajectory.loop", self.loop, "true or false")
        try:
            sp = np.atleast_1d(np.asarray(self.speed_m_s, dtype=float))
            pause, t0 = float(self.pause_s), float(self.t0_s)
        except (TypeError, ValueError):
            raise ParameterError("trajectory.speed_m_s/pause_s/t0_s",
                                 (self.speed_m_s, self.pause_s, self.t0_s),
                                 "numbers (a speed or one per leg [m/s]; a pause, a start "
                                 "time [s])") from None
        require(np.isfinite(t0), "trajectory.t0_s", t0, "a finite time [s]")
        object.__setattr__(self, "pause_s", pause)
        object.__setattr__(self, "t0_s", t0)
        require(sp.ndim == 1 and len(sp) in (1, legs) and bool(np.all(np.isfinite(sp) & (sp > 0))),
                "trajectory.speed_m_s", self.speed_m_s,
                f"a speed > 0 m/s, or one per leg ({legs})")
        object.__setattr__(self, "speed_m_s", float(sp[0]) if len(sp) == 1 and
                           np.ndim(self.speed_m_s) == 0 else tuple(float(s) for s in sp))
        require(np.isfinite(self.pause_s) and self.pause_s >= 0, "trajectory.pause_s",
                self.pause_s, ">= 0 s")
        ends = np.asarray(pts + pts[:1] if self.loop else pts)
        for k in range(legs):
            require(bool(np.any(ends[k + 1] != ends[k])), f"trajectory.points_m[{(k + 1) % len(pts)}]",
                    [float(x) for x in ends[k + 1]], "a point different from the waypoint before it")

    def _pieces(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Moving legs and pauses in order: start times ``(m,)`` [s] after ``t0_s``,
        durations ``(m,)`` [s], from and to points ``(m, 3)`` [m] (a pause: from == to)."""
        pts = np.asarray(self.points_m)
        ends = np.vstack([pts, pts[:1]]) if self.loop else pts
        legs = len(ends) - 1
        sp = np.broadcast_to(np.asarray(self.speed_m_s, dtype=float), (legs,))
        dur, a, b = [], [], []
        for k in range(legs):
            dur.append(float(np.linalg.norm(ends[k + 1] - ends[k])) / sp[k])
            a.append(ends[k])
            b.append(ends[k + 1])
            if self.pause_s > 0 and (self.loop or k < legs - 1):
                dur.append(self.pause_s)
                a.append(ends[k + 1])
                b.append(ends[k + 1])
        d = np.asarray(dur)
        return np.concatenate([[0.0], np.cumsum(d)[:-1]]), d, np.asarray(a), np.asarray(b)

    @property
    def duration_s(self) -> float:
        """Time from the first waypoint to the last (one round with ``loop``) [s]."""
        _, d, _, _ = self._pieces()
        return float(d.sum())

    def _locate(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, tuple]:
        start, dur, a, b = self._pieces()
        total = float(dur.sum())
        ph = np.maximum(np.asarray(t, dtype=float) - self.t0_s, 0.0)
        ph = np.mod(ph, total) if self.loop else np.minimum(ph, total)
        k = np.clip(np.searchsorted(start, ph, side="right") - 1, 0, len(start) - 1)
        frac = np.clip((ph - start[k]) / dur[k], 0.0, 1.0)
        return k, frac, (start, dur, a, b)

    def position(self, t: np.ndarray | float) -> np.ndarray:
        """Position(s) [m] at times ``t`` [s]: ``shape(t) + (3,)``."""
        k, frac, (_, _, a, b) = self._locate(np.asarray(t, dtype=float))
        return a[k] + frac[..., None] * (b[k] - a[k])

    def velocity(self, t: np.ndarray | float) -> np.ndarray:
        """Velocity [m/s] at ``t`` [s], ``shape(t) + (3,)``: the current leg's (0 while it
        waits, before ``t0_s`` and after the last waypoint)."""
        t = np.asarray(t, dtype=float)
        k, _, (_, dur, a, b) = self._locate(t)
        v = (b[k] - a[k]) / dur[k][..., None]
        ph = t - self.t0_s
        still = (ph < 0) if self.loop else (ph < 0) | (ph >= float(dur.sum()))
        return np.where(still[..., None], 0.0, v)


Trajectory = Fixed | ConstantVelocity | BackAndForth | Waypoints


@dataclass(frozen=True)
class Mover:
    """A rigidly translating object: ``shape`` (Cylinder, or a Box in the object frame)
    carried by ``trajectory`` (no rotation)."""

    shape: Cylinder | Box
    trajectory: Trajectory
    name: str = "mover"

    def mesh(self) -> trimesh.Trimesh:
        """Mesh in the object frame."""
        return self.shape.mesh()

    def position(self, t: np.ndarray | float) -> np.ndarray:
        return self.trajectory.position(t)


@dataclass(frozen=True)
class SensorPose:
    """Pose of the sensor base frame in the world over time.

    ``p_world = R_z(yaw_rad) p_sensor + position_m + velocity_m_s * (t - t0_s)``.
    Default: 0.4 m above the floor at the origin facing +x (a lidar on a Pioneer P3-DX).
    """

    position_m: tuple[float, float, float] = (0.0, 0.0, 0.4)
    yaw_rad: float = 0.0
    velocity_m_s: tuple[float, float, float] = (0.0, 0.0, 0.0)
    t0_s: float = 0.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "position_m", _v3(self.position_m, "sensor.position_m"))
        object.__setattr__(self, "velocity_m_s", _v3(self.velocity_m_s, "sensor.velocity_m_s"))

    @property
    def rotation(self) -> np.ndarray:
        """World-from-sensor rotation (3, 3)."""
        c, s = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])

    @property
    def is_static(self) -> bool:
        return not any(self.velocity_m_s)

    def translation(self, t: np.ndarray | float) -> np.ndarray:
        """World position [m] of the sensor base origin at ``t`` [s]: ``shape(t) + (3,)``."""
        t = np.asarray(t, dtype=float)
        return np.asarray(self.position_m) + (t - self.t0_s)[..., None] * np.asarray(self.velocity_m_s)

    def to_world(self, p_sensor: np.ndarray, t: np.ndarray | float) -> np.ndarray:
        """Sensor-frame points ``(n, 3)`` at times ``t`` ``(n,)`` -> world ``(n, 3)``."""
        return np.asarray(p_sensor) @ self.rotation.T + self.translation(t)

    def to_sensor(self, p_world: np.ndarray, t: np.ndarray | float) -> np.ndarray:
        """Inverse of :meth:`to_world`."""
        return (np.asarray(p_world) - self.translation(t)) @ self.rotation


@dataclass(frozen=True)
class Scene:
    """Everything the simulated sensor sees, in the world frame.

    Attributes
    ----------
    name : str
    statics : tuple
        :class:`Room`, :class:`Box`, :class:`Plane`, :class:`Wall` and :class:`Pole` elements.
    movers : tuple of Mover
        Moving objects; ground-truth object id of mover ``k`` is ``1 + k``.
    sensor : SensorPose
    description : str
    """

    name: str = "scene"
    statics: tuple[Room | Box | Plane | Wall | Pole, ...] = ()
    movers: tuple[Mover, ...] = ()
    sensor: SensorPose = field(default_factory=SensorPose)
    description: str = ""

    def __post_init__(self) -> None:
        object.__setattr__(self, "statics", tuple(self.statics))
        object.__setattr__(self, "movers", tuple(self.movers))
        for s in self.statics:
            require(isinstance(s, Room | Box | Plane | Wall | Pole), "scene.statics",
                    type(s).__name__, "Room, Box, Plane, Wall or Pole")
        for m in self.movers:
            require(isinstance(m, Mover), "scene.movers", type(m).__name__, "Mover")

    def static_parts(self) -> list[tuple[str, Any]]:
        """``(name, trimesh)`` of every static part (a room gives one per wall/floor)."""
        return [p for s in self.statics for p in s.parts()]

    @classmethod
    def from_toml(cls, path: str | Path) -> Scene:
        """Load a scene file (format in the module docstring)."""
        from ..validation import read_toml  # a FIFO, directory or binary file: one line

        path = Path(path)
        if not (path.exists() or path.is_symlink()):
            raise ParameterError("scene", str(path), "an existing TOML file or a built-in name: "
                                 + ", ".join(BUILTIN_SCENES))
        data = read_toml(path, "scene", error=DesignFileError)
        data.setdefault("name", path.stem)
        return scene_from_dict(data, str(path))


# -- loading ---------------------------------------------------------------------------
def _trajectory_from_dict(d: Mapping[str, Any], where: str) -> Trajectory:
    kind = d.get("trajectory", "fixed")
    try:
        if kind == "fixed":
            return Fixed(d.get("position_m", d.get("start_m", (0.0, 0.0, 0.0))))
        if kind == "constant_velocity":
            return ConstantVelocity(d["start_m"], d["velocity_m_s"], d.get("t0_s", 0.0))
        if kind == "back_and_forth":
            if "end_m" in d:
                return BackAndForth(d["start_m"], d["end_m"], d["speed_m_s"], d.get("t0_s", 0.0))
            return BackAndForth.from_heading(d["start_m"], math.radians(d["heading_deg"]),
                                             d["speed_m_s"], d["length_m"], d.get("t0_s", 0.0))
        if kind == "waypoints":
            return Waypoints(d["points_m"], d["speed_m_s"], d.get("pause_s", 0.0),
                             d.get("loop", False), d.get("t0_s", 0.0))
    except KeyError as e:
        raise ParameterError(f"{where}.{e.args[0]}", None, f"required for trajectory {kind!r}") from None
    raise ParameterError(f"{where}.trajectory", kind,
                         "fixed, constant_velocity, back_and_forth or waypoints")


_KNOWN = {"name", "description", "sensor", "room", "box", "plane", "wall", "pole", "mover"}


def scene_from_dict(data: Mapping[str, Any], source: str = "<dict>") -> Scene:
    """Build a :class:`Scene` from a parsed TOML table (format in the module docstring)."""
    unknown = set(data) - _KNOWN
    require(not unknown, f"{source}: scene keys", sorted(unknown), ", ".join(sorted(_KNOWN)))
    s = dict(data.get("sensor", {}))
    sensor = SensorPose(s.get("position_m", (0.0, 0.0, 0.4)), math.radians(s.get("yaw_deg", 0.0)),
                        s.get("velocity_m_s", (0.0, 0.0, 0.0)), s.get("t0_s", 0.0))
    statics: list = []
    rooms = data.get("room", [])
    for r in [rooms] if isinstance(rooms, Mapping) else rooms:
        statics.append(Room(r.get("size_m", (6.0, 5.0, 2.5)), r.get("center_m", (1.5, 0.0)),
                            r.get("floor_z_m", 0.0), bool(r.get("ceiling", True)),
                            r.get("name", "room")))
    for i, b in enumerate(data.get("box", [])):
        try:
            statics.append(Box(b["size_m"], b["center_m"], math.radians(b.get("yaw_deg", 0.0)),
                               b.get("name", f"box{i}")))
        except KeyError as e:
            raise ParameterError(f"{source}: box[{i}].{e.args[0]}", None, "required") from None
    for i, p in enumerate(data.get("plane", [])):
        try:
            statics.append(Plane(p["center_m"], p["normal"], p.get("size_m", (10.0, 10.0)),
                                 p.get("name", f"plane{i}")))
        except KeyError as e:
            raise ParameterError(f"{source}: plane[{i}].{e.args[0]}", None, "required") from None
    for i, w in enumerate(data.get("wall", [])):
        where = f"{source}: wall[{i}]"
        try:
            ops = []
            for j, o in enumerate(w.get("opening", [])):
                try:
                    ops.append(Opening(o["offset_m"], o["width_m"], o["height_m"],
                                       o.get("bottom_m", 0.0)))
                except KeyError as e:
                    raise ParameterError(f"{where}.opening[{j}].{e.args[0]}", None,
                                         "required") from None
            statics.append(Wall(w["center_m"], w["normal"], w["size_m"], tuple(ops),
                                w.get("name", f"wall{i}")))
        except KeyError as e:
            raise ParameterError(f"{where}.{e.args[0]}", None, "required") from None
    for i, p in enumerate(data.get("pole", [])):
        try:
            statics.append(Pole(p["center_m"], p["radius_m"], p["height_m"],
                                p.get("base_z_m", 0.0), p.get("name", f"pole{i}")))
        except KeyError as e:
            raise ParameterError(f"{source}: pole[{i}].{e.args[0]}", None, "required") from None
    movers = []
    for i, m in enumerate(data.get("mover", [])):
        where = f"{source}: mover[{i}]"
        shape_kind = m.get("shape", "cylinder")
        shape: Cylinder | Box
        if shape_kind == "cylinder":
            shape = Cylinder(m.get("radius_m", 0.18), m.get("height_m", 1.0), m.get("base_z_m", 0.0))
        elif shape_kind == "box":
            size = _v3(m.get("size_m", (0.4, 0.4, 1.0)), f"{where}.size_m")
            shape = Box(size, (0.0, 0.0, m.get("base_z_m", 0.0) + size[2] / 2),
                        math.radians(m.get("yaw_deg", 0.0)), "shape")
        else:
            raise ParameterError(f"{where}.shape", shape_kind, "cylinder or box")
        movers.append(Mover(shape, _trajectory_from_dict(m, where), m.get("name", f"mover{i}")))
    return Scene(data.get("name", "scene"), tuple(statics), tuple(movers), sensor,
                 data.get("description", ""))


# -- built-ins -------------------------------------------------------------------------
def room_scene() -> Scene:
    """``"room"``: a 6 x 5 x 2.5 m room, the sensor 0.4 m up 1.5 m from the back wall facing
    +x, three boxes and one person-sized cylinder walking back and forth across the room."""
    return Scene(
        name="room",
        statics=(
            Room((6.0, 5.0, 2.5), (1.5, 0.0)),
            Box((0.6, 0.4, 0.8), (3.0, 1.2, 0.4), math.radians(15.0), "box0"),
            Box((0.5, 0.5, 1.2), (2.2, -1.3, 0.6), 0.0, "box1"),
            Box((1.0, 0.6, 0.5), (4.0, -0.2, 0.25), math.radians(-30.0), "box2"),
        ),
        movers=(Mover(Cylinder(0.2, 1.7), BackAndForth((2.5, -1.5, 0.0), (3.5, 1.5, 0.0), 0.5),
                      "walker"),),
        sensor=SensorPose((0.0, 0.0, 0.4), 0.0),
        description="6 x 5 m room with three boxes and a walker (r 0.2 m, 0.5 m/s)",
    )


#: Section VI geometry for "paper-tracking" (the paper gives only the speed and heading):
#: a cylinder of radius 0.18 m (a Pioneer-sized robot wrapped in a white cylinder) and 1 m
#: tall crosses in front of the sensor with its axis 2 m ahead (the design distance D, where
#: the reflected beams interleave best), along the paper's heading 89.4 deg for 1.6 m
#: (y from -0.8 to +0.8 m: inside the 80 deg middle window at 2 m) at 0.13 m/s, then back.
PAPER_TRACKING: dict[str, Any] = {
    "radius_m": 0.18,
    "height_m": 1.0,
    "start_m": (2.0, -0.8, 0.0),
    "length_m": 1.6,
    "sensor_height_m": 0.4,
}


def paper_tracking_scene() -> Scene:
    """``"paper-tracking"``: paper Section VI (see :data:`PAPER_TRACKING` for the choices)."""
    p = PAPER_TRACKING
    traj = BackAndForth.from_heading(p["start_m"], math.radians(TRACKING_HEADING_DEG),
                                     TRACKING_SPEED_M_S, p["length_m"])
    return Scene(
        name="paper-tracking",
        statics=(Room((8.0, 6.0, 2.5), (2.5, 0.0), ceiling=False),),
        movers=(Mover(Cylinder(p["radius_m"], p["height_m"]), traj, "cylinder"),),
        sensor=SensorPose((0.0, 0.0, p["sensor_height_m"]), 0.0),
        description="paper Section VI: cylinder r 0.18 m at ~2 m, 0.13 m/s, heading 89.4 deg, "
                    "back and forth",
    )


def wall_scene(distance_m: float = 1.5, yaw_rad: float = 0.0, size_m: tuple[float, float] = (8.0, 4.0),
               sensor_height_m: float = 0.0) -> Scene:
    """``"wall"``: one flat vertical wall, nothing else (calibration, paper Section IV).

    The wall's foot of perpendicular from the sensor origin is ``distance_m`` [m] away at
    azimuth ``yaw_rad`` (sensor frame, the sensor at ``(0, 0, sensor_height_m)`` facing +x):
    plane ``n . p = distance_m`` with ``n = (cos yaw, sin yaw, 0)`` in the sensor frame.
    """
    require(distance_m > 0, "wall.distance_m", distance_m, "> 0 m")
    n = np.array([math.cos(yaw_rad), math.sin(yaw_rad), 0.0])
    c = n * distance_m + np.array([0.0, 0.0, sensor_height_m])
    return Scene(
        name="wall",
        statics=(Plane(tuple(c), tuple(-n), size_m, "wall"),),
        sensor=SensorPose((0.0, 0.0, sensor_height_m), 0.0),
        description=f"flat wall {distance_m} m away at azimuth {math.degrees(yaw_rad):.1f} deg",
    )


BUILTIN_SCENES = {
    "room": room_scene,
    "paper-tracking": paper_tracking_scene,
    "wall": wall_scene,
}


def builtin_scene(name: str) -> Scene:
    """A built-in scene by name (``room``, ``paper-tracking``, ``wall``)."""
    try:
        return BUILTIN_SCENES[name]()
    except KeyError:
        raise ParameterError("scene", name, "one of " + ", ".join(BUILTIN_SCENES)
                             + " or a .toml file") from None


def load_scene(scene: Scene | str | Path | None) -> Scene:
    """A Scene as given, a built-in by name, or a TOML file; ``None`` -> ``"room"``."""
    if scene is None:
        return room_scene()
    if isinstance(scene, Scene):
        return scene
    s = str(scene)
    if s in BUILTIN_SCENES:
        return builtin_scene(s)
    if s.endswith(".toml") or Path(s).exists():
        return Scene.from_toml(s)
    if s and "/" not in s and "\\" not in s:
        # a scene shipped with the package by name (design/scenes/<name>.toml, package data:
        # found after a wheel install too)
        from ..paper import design_resource

        packaged = design_resource(f"scenes/{s}.toml")
        if packaged.is_file():
            return Scene.from_toml(packaged)
    return builtin_scene(s)
