"""The one geometry core: rotations, exact reflection, finite mirror patches, perturbations.

Everything that needs a mirror - the solver, the BeamModel, the simulator scene, the CAD
export, calibration - uses :class:`MirrorPatch` and the functions here. SI units: metres,
radians. Frames and signs are in docs/conventions.md.

A mirror is a flat rectangle in 3D (head frame)::

    p(s, z) = origin + s * along + z * up,   s in [s_min, s_max],  z in [z_min, z_max]

``origin`` is the mirror's anchor point (where its anchor beam hits it, in the scan plane
for an unperturbed mirror), ``normal`` the unit normal on the reflecting side (towards the
lidar), ``along`` the unit in-plane direction that stays horizontal for a vertical mirror,
``up`` = ``normal x along``. The mirror's own hinge line ``origin + hinge_z*up + s*along``
is the axis of the paper's tilt error Delta-beta only; the lift motor turns all of a
side's mirrors about the side's lift axis (:mod:`nodlidar.hinge`, docs/conventions.md).

The compiled kernels (the point assembly's and the simulator's) use the per-vector
counterparts of these formulas from :mod:`nodlidar._compiled_geometry`: its ``rodrigues``
is :func:`rotate_columns` for one vector and its ``reflect`` is :func:`reflect`, in the
same operation order; the assembly's nod is :func:`pitch_about_pivot`'s ``R_y``
(tests/test_assembly.py and tests/test_sim_kernel.py check them to 1e-12).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from .errors import ParameterError, require

__all__ = [
    "DIRECT",
    "CLEAR",
    "HOUSING",
    "BLOCKED",
    "Tol",
    "TOL",
    "unit",
    "reflect",
    "matrix_from_axis_angle",
    "rotate_about_axis",
    "rotate_columns",
    "rotate_about_line",
    "pitch_about_pivot",
    "directions_from_bearings",
    "incidence_angle",
    "perturb_frames",
    "EZ",
    "rot_x",
    "rot_y",
    "rot_z",
    "MirrorPatch",
    "Perturbation",
    "ray_plane_distance",
    "ray_circle_exit",
    "ray_cylinder_hit",
    "reflect_rays",
    "arc_point",
    "bearing_of",
    "wrap_angle",
]

#: Mirror index of a beam that meets no mirror (goes straight out of the lidar).
DIRECT = -1
#: Blocker code of a beam whose path is clear (verify.trace_beams). Same value as
#: ``DIRECT``, a different question: which obstacle, not which mirror.
CLEAR = -1
#: Blocker code of a beam stopped by the lidar's own housing (a reflection turned back).
HOUSING = -2
#: Blocker code of a beam stopped by anything else before its target (another mirror's
#: back, a carrier).
BLOCKED = -3


@dataclass(frozen=True)
class Tol:
    """The numerical tolerances of the geometry, in one place (SI units).

    Attributes
    ----------
    parallel : float
        ``|d . n|`` below which a ray counts as parallel to a plane [-].
    ahead_m : float
        Smallest distance along a ray that counts as a hit ahead of its origin [m] (a
        reflected ray must not hit the mirror it starts on again).
    unit_norm : float
        Allowed deviation of a unit vector's norm from 1, and of a dot product from 0 for
        vectors that must be perpendicular [-].
    rotation : float
        Allowed ``|R^T R - I|`` and ``|det R - 1|`` of a rotation matrix [-].
    angle_rad : float
        Angles closer than this are the same (e.g. a zero rotation) [rad].
    block_ahead_m : float
        Smallest distance along a ray leaving a mirror at which another surface (a mirror,
        the housing) counts as blocking it [m]. Coarser than ``ahead_m``: the ray starts
        on a hit point computed by a ray-plane intersection, and a neighbour sharing that
        edge (a chained mirror's joint) must not block it by round-off.
    angle_deg : float
        Angles typed in degrees (a design file's window edges) closer than this to a
        step's bearing are that bearing [deg]: covers the round-off of the conversion.
    degenerate_rad : float
        A construction angle this close to degenerate (a beam turned by 180 deg, a
        triangle angle of 0) is refused as ill-conditioned [rad]. A design margin, far
        coarser than round-off.
    collinear_m2 : float
        ``|(b - a) x (c - a)|`` (twice a triangle's area) below which three points count
        as collinear: no plane through them [m^2]. An area, not a length: a 30 um x 30 um
        triangle, far below a lidar's millimetre range noise.
    """

    parallel: float = 1e-12
    ahead_m: float = 1e-12
    block_ahead_m: float = 1e-9
    collinear_m2: float = 1e-9
    angle_deg: float = 1e-9
    degenerate_rad: float = 1e-6
    unit_norm: float = 1e-9
    rotation: float = 1e-6
    angle_rad: float = 1e-12


#: The tolerances every module uses (``geometry.TOL.parallel`` etc.).
TOL = Tol()

#: The head frame's vertical (yaw axis, mirror ``up`` when deployed).
EZ = np.array([0.0, 0.0, 1.0])
EZ.setflags(write=False)


def unit(v: np.ndarray) -> np.ndarray:
    """Normalise vectors along the last axis. ``(..., 3) -> (..., 3)``."""
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def reflect(d: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Exact specular reflection ``d' = d - 2 (d.n) n``.

    Parameters
    ----------
    d : (..., 3) float
        Incident directions.
    n : (..., 3) or (3,) float
        Unit mirror normals (either sign).
    """
    d = np.asarray(d, dtype=float)
    n = np.asarray(n, dtype=float)
    return d - 2.0 * np.sum(d * n, axis=-1, keepdims=True) * n


def matrix_from_axis_angle(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rotation matrix (3, 3) of ``angle`` [rad] about unit ``axis`` (right hand, active)."""
    a = unit(np.asarray(axis, dtype=float))
    x, y, z = a
    c, s = np.cos(angle), np.sin(angle)
    C = 1.0 - c
    return np.array(
        [
            [c + x * x * C, x * y * C - z * s, x * z * C + y * s],
            [y * x * C + z * s, c + y * y * C, y * z * C - x * s],
            [z * x * C - y * s, z * y * C + x * s, c + z * z * C],
        ]
    )


def rotate_about_axis(v: np.ndarray, axis: np.ndarray, angle: np.ndarray | float) -> np.ndarray:
    """Rotate vectors about axes through the origin (Rodrigues, right hand, active).

    The one rotation of the code base: every module that turns vectors about an axis
    calls this (or :func:`matrix_from_axis_angle` for one matrix).

    Parameters
    ----------
    v : (..., 3) float
        Vectors.
    axis : (3,) or (..., 3) float
        Unit axes (one for all rows, or one per row).
    angle : float or (...,) float
        Angles [rad] (one for all rows, or one per row).

    Returns
    -------
    (..., 3) float (the broadcast shape of the inputs).
    """
    v = np.asarray(v, dtype=float)
    k = np.asarray(axis, dtype=float)
    a = np.asarray(angle, dtype=float)
    q = rotate_columns(v[..., 0], v[..., 1], v[..., 2], k[..., 0], k[..., 1], k[..., 2],
                       np.cos(a), np.sin(a))
    return np.stack(np.broadcast_arrays(*q), -1)


def rotate_columns(x: np.ndarray, y: np.ndarray, z: np.ndarray,
                   kx: np.ndarray | float, ky: np.ndarray | float, kz: np.ndarray | float,
                   c: np.ndarray | float, s: np.ndarray | float
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rodrigues' rotation on columns: vectors ``(x, y, z)`` turned about unit axes
    ``(kx, ky, kz)`` by the angles whose cosine and sine are ``c, s``.

    ``q = v c + (k x v) s + k (k.v)(1 - c)``, every argument a scalar or an array of one
    broadcast shape (n,) or (...): the form hot paths use (no (n, 3) stacks, the cosine
    and sine computed once by the caller). :func:`rotate_about_axis` is this on rows.
    Returns ``(qx, qy, qz)``.
    """
    kv = kx * x + ky * y + kz * z
    kv = kv * (1.0 - c)
    qx = x * c + (ky * z - kz * y) * s + kx * kv
    qy = y * c + (kz * x - kx * z) * s + ky * kv
    qz = z * c + (kx * y - ky * x) * s + kz * kv
    return qx, qy, qz


def rotate_about_line(p: np.ndarray, point: np.ndarray, axis: np.ndarray,
                      angle: np.ndarray | float) -> np.ndarray:
    """Rotate points ``p (..., 3)`` about the line through ``point`` along unit ``axis``
    by ``angle`` [rad] (shapes as in :func:`rotate_about_axis`)."""
    q = np.asarray(point, dtype=float)
    return q + rotate_about_axis(np.asarray(p, dtype=float) - q, axis, angle)


def pitch_about_pivot(p: np.ndarray, pitch: np.ndarray | float,
                      pivot: np.ndarray | None = None) -> np.ndarray:
    """The nod: points ``p (..., 3)`` of the head frame turned by ``R_y(pitch)`` about
    ``pivot (3,)`` [m] (default the origin): ``pivot + R_y(pitch) (p - pivot)``.

    ``pitch`` [rad] is one angle or one per row (positive tips +x down,
    docs/conventions.md). Returns ``(..., 3)``.
    """
    p = np.asarray(p, dtype=float)
    a = np.asarray(pitch, dtype=float)
    c, s = np.cos(a), np.sin(a)
    q = p if pivot is None else p - np.asarray(pivot, dtype=float)
    x, y, z = q[..., 0], q[..., 1], q[..., 2]
    out = np.stack([c * x + s * z, np.broadcast_to(y, np.broadcast(x, c).shape), -s * x + c * z], -1)
    return out if pivot is None else out + np.asarray(pivot, dtype=float)


def directions_from_bearings(bearing: np.ndarray | float,
                             elevation: np.ndarray | float | None = None) -> np.ndarray:
    """Unit directions ``(..., 3)`` of bearings [rad] (from +x towards +y) in the scan
    plane, or lifted by ``elevation`` [rad] out of it (+z up)."""
    b = np.asarray(bearing, dtype=float)
    if elevation is None:
        return np.stack([np.cos(b), np.sin(b), np.zeros_like(b)], -1)
    e = np.asarray(elevation, dtype=float)
    ce = np.cos(e)
    return np.stack(np.broadcast_arrays(ce * np.cos(b), ce * np.sin(b), np.sin(e)), -1)


def incidence_angle(dirs: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Angle of incidence [rad] of unit directions ``dirs (..., 3)`` on a plane of unit
    ``normal`` ((3,) or (..., 3), either sign): ``arccos |d . n|`` in ``[0, pi/2]``, 0 at
    normal incidence (the paper's gamma). Returns ``(...,)``."""
    d = np.asarray(dirs, dtype=float)
    n = np.asarray(normal, dtype=float)
    return np.arccos(np.clip(np.abs(np.sum(d * n, axis=-1)), 0.0, 1.0))


def rot_z(angle: np.ndarray | float) -> np.ndarray:
    """Rotation(s) about +z (yaw). Scalar -> (3, 3); ``(n,)`` -> ``(n, 3, 3)``."""
    a = np.asarray(angle, dtype=float)
    c, s = np.cos(a), np.sin(a)
    o, i = np.zeros_like(a), np.ones_like(a)
    return np.stack([np.stack([c, -s, o], -1), np.stack([s, c, o], -1), np.stack([o, o, i], -1)], -2)


def rot_x(angle: np.ndarray | float) -> np.ndarray:
    """Rotation(s) about +x (roll; positive tips +y up). Scalar -> (3,3); (n,) -> (n,3,3)."""
    a = np.asarray(angle, dtype=float)
    c, s = np.cos(a), np.sin(a)
    o, i = np.zeros_like(a), np.ones_like(a)
    return np.stack([np.stack([i, o, o], -1), np.stack([o, c, -s], -1), np.stack([o, s, c], -1)], -2)


def rot_y(angle: np.ndarray | float) -> np.ndarray:
    """Rotation(s) about +y (pitch; positive tips +x down). Scalar -> (3,3); (n,) -> (n,3,3)."""
    a = np.asarray(angle, dtype=float)
    c, s = np.cos(a), np.sin(a)
    o, i = np.zeros_like(a), np.ones_like(a)
    return np.stack([np.stack([c, o, s], -1), np.stack([o, i, o], -1), np.stack([-s, o, c], -1)], -2)


def bearing_of(p: np.ndarray) -> np.ndarray:
    """Bearing ``atan2(y, x)`` [rad] of points ``(..., 3)`` or ``(..., 2)``."""
    p = np.asarray(p, dtype=float)
    return np.arctan2(p[..., 1], p[..., 0])


def ray_plane_distance(
    origins: np.ndarray, dirs: np.ndarray, point: np.ndarray, normal: np.ndarray
) -> np.ndarray:
    """Distance ``t`` along each ray to a plane; ``inf`` if parallel or behind.

    origins, dirs : (n, 3); point, normal : (3,). Returns (n,) float.
    """
    denom = dirs @ normal
    num = (point - origins) @ normal
    with np.errstate(divide="ignore", invalid="ignore"):
        t = num / denom
    return np.where((np.abs(denom) > TOL.parallel) & (t > TOL.ahead_m), t, np.inf)


def _circle_roots(origins: np.ndarray, dirs: np.ndarray, radius: float):
    """Entry/exit distances of rays (xy only) through the circle |p| = radius.

    Returns ``(t0, t1, disc, c)``: the two roots (nan where the ray misses), the
    discriminant, and ``|o|^2 - radius^2`` (negative when the ray starts inside).
    """
    o, d = origins[..., :2], dirs[..., :2]
    a = np.sum(d * d, -1)
    b = 2 * np.sum(o * d, -1)
    c = np.sum(o * o, -1) - radius**2
    disc = b * b - 4 * a * c
    with np.errstate(invalid="ignore", divide="ignore"):
        root = np.sqrt(disc)
        return (-b - root) / (2 * a), (-b + root) / (2 * a), disc, c


def ray_circle_exit(origins: np.ndarray, dirs: np.ndarray, radius: float) -> np.ndarray:
    """Distance along each ray (in the xy plane) to where it leaves the circle |p| = radius.

    Only x and y are used, so for 3D rays this is the exit from the vertical cylinder.
    origins, dirs : (n, 2|3). Returns (n,) float (nan if the ray never reaches it).
    """
    _, t1, disc, _ = _circle_roots(origins, dirs, radius)
    return np.where((disc >= 0) & (t1 > 0), t1, np.nan)


def ray_cylinder_hit(
    origins: np.ndarray, dirs: np.ndarray, radius: float, t_max: np.ndarray | float
) -> np.ndarray:
    """Whether each ray enters the vertical cylinder ``x^2+y^2 <= radius^2`` for ``0 < t < t_max``.

    Used to check reflected beams against the lidar housing. Returns (n,) bool.
    """
    t0, t1, disc, c = _circle_roots(origins, dirs, radius)
    enters = (disc > 0) & (t1 > TOL.block_ahead_m) & (t0 < t_max)
    return np.where(c < 0, True, enters)


@dataclass(frozen=True)
class Perturbation:
    """A mirror's mounting error, as in the paper's Table I.

    Attributes
    ----------
    dalpha : float
        Yaw error [rad]: rotation of the mirror about the vertical axis through the lidar
        origin (keeps its perpendicular distance, changes the normal's azimuth ``alpha``).
    dbeta : float
        Tilt error [rad]: rotation about the mirror's hinge axis (right hand about
        ``along``). Tilts reflected beams out of the scan plane by about ``2*dbeta``.
    dd : float
        Offset [m] along the outward normal (away from the lidar): ``d -> d + dd``.
    """

    dalpha: float = 0.0
    dbeta: float = 0.0
    dd: float = 0.0

    def as_array(self) -> np.ndarray:
        return np.array([self.dalpha, self.dbeta, self.dd])

    @classmethod
    def from_array(cls, a: np.ndarray) -> Perturbation:
        return cls(float(a[0]), float(a[1]), float(a[2]))


def perturb_frames(origin: np.ndarray, normal: np.ndarray, along: np.ndarray, up: np.ndarray,
                   hinge_z: float, dalpha: np.ndarray | float, dbeta: np.ndarray | float,
                   dd: np.ndarray | float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The mounting-error model (:class:`Perturbation`), vectorised over samples.

    The one implementation: :meth:`MirrorPatch.perturbed` calls it with one sample, the
    tolerance Monte Carlo with thousands. In order:

    1. tilt by ``dbeta`` about the hinge axis (the line ``origin + hinge_z*up`` along
       ``along``, right hand);
    2. offset by ``dd`` along the outward normal (away from the lidar);
    3. yaw by ``dalpha`` about the vertical (+z) through the lidar origin O.

    Parameters
    ----------
    origin, normal, along, up : (3,) float
        One patch's frame (head frame, ``up = normal x along``).
    hinge_z : float
        The hinge axis' offset along ``up`` [m].
    dalpha, dbeta : float or (n,) float
        Yaw and tilt errors [rad].
    dd : float or (n,) float
        Offset [m].

    Returns
    -------
    origin, normal, along, up : (n, 3) float each (``n`` the broadcast length, 1 for scalars).
    """
    da, db, dd = (np.atleast_1d(np.asarray(x, dtype=float)) for x in (dalpha, dbeta, dd))
    da, db, dd = np.broadcast_arrays(da, db, dd)
    o0, n0, a0, u0 = (np.asarray(v, dtype=float) for v in (origin, normal, along, up))
    pivot = o0 + hinge_z * u0
    o = rotate_about_line(o0, pivot, a0, db)
    nrm = rotate_about_axis(n0, a0, db)
    up_ = rotate_about_axis(u0, a0, db)
    outward = np.where((np.sum(o * nrm, -1) > 0)[:, None], nrm, -nrm)
    o = o + dd[:, None] * outward
    along_ = np.broadcast_to(a0, o.shape)
    return tuple(rotate_about_axis(v, EZ, da) for v in (o, nrm, along_, up_))  # type: ignore[return-value]


def _vec(v, name: str) -> tuple[float, float, float]:
    a = np.asarray(v, dtype=float).reshape(-1)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise ParameterError(name, v, "a finite 3-vector")
    return (float(a[0]), float(a[1]), float(a[2]))


@dataclass(frozen=True)
class MirrorPatch:
    """A finite flat rectangular mirror (see module docstring for the parametrisation).

    Vectors are stored as tuples so the dataclass is hashable and truly frozen; use the
    ``*_`` array properties in computations.
    """

    name: str
    origin: tuple[float, float, float]
    normal: tuple[float, float, float]
    along: tuple[float, float, float]
    s_min: float
    s_max: float
    z_min: float
    z_max: float
    hinge_z: float = 0.0
    perturbation: Perturbation = field(default_factory=Perturbation)

    def __post_init__(self) -> None:
        object.__setattr__(self, "origin", _vec(self.origin, f"{self.name}.origin"))
        n = np.asarray(_vec(self.normal, f"{self.name}.normal"))
        a = np.asarray(_vec(self.along, f"{self.name}.along"))
        tol = TOL.unit_norm
        require(abs(np.linalg.norm(n) - 1) < tol, f"{self.name}.normal", self.normal, "unit length")
        require(abs(np.linalg.norm(a) - 1) < tol, f"{self.name}.along", self.along, "unit length")
        require(abs(n @ a) < tol, f"{self.name}.along", self.along, "perpendicular to normal")
        object.__setattr__(self, "normal", tuple(map(float, n)))
        object.__setattr__(self, "along", tuple(map(float, a)))
        require(self.s_max > self.s_min, f"{self.name}.s_max", self.s_max, f"> s_min = {self.s_min}")
        require(self.z_max > self.z_min, f"{self.name}.z_max", self.z_max, f"> z_min = {self.z_min}")

    # -- arrays --------------------------------------------------------------------
    @property
    def origin_(self) -> np.ndarray:
        return np.asarray(self.origin)

    @property
    def normal_(self) -> np.ndarray:
        return np.asarray(self.normal)

    @property
    def along_(self) -> np.ndarray:
        return np.asarray(self.along)

    @property
    def up_(self) -> np.ndarray:
        # computed once per patch (the patch is frozen); read-only so no caller can alter it
        up = self.__dict__.get("_up_cache")
        if up is None:
            up = np.cross(self.normal_, self.along_)
            up.setflags(write=False)
            object.__setattr__(self, "_up_cache", up)
        return up

    @property
    def length(self) -> float:
        """Patch length along ``along`` [m]."""
        return self.s_max - self.s_min

    @property
    def height(self) -> float:
        """Patch height along ``up`` [m]."""
        return self.z_max - self.z_min

    @property
    def standoff(self) -> float:
        """Perpendicular distance from the lidar origin to the mirror plane, ``d`` [m]."""
        return float(abs(self.origin_ @ self.normal_))

    @property
    def normal_azimuth(self) -> float:
        """Azimuth ``alpha`` of the outward normal (away from the lidar) [rad]."""
        n_out = -self.normal_ if self.origin_ @ self.normal_ < 0 else self.normal_
        return float(np.arctan2(n_out[1], n_out[0]))

    def corners(self) -> np.ndarray:
        """The four corners (4, 3), order (s_min,z_min), (s_max,z_min), (s_max,z_max), (s_min,z_max)."""
        o, a, u = self.origin_, self.along_, self.up_
        return np.array(
            [o + s * a + z * u for s, z in
             ((self.s_min, self.z_min), (self.s_max, self.z_min),
              (self.s_max, self.z_max), (self.s_min, self.z_max))]
        )

    def point(self, s: np.ndarray | float, z: np.ndarray | float = 0.0) -> np.ndarray:
        """Points at patch coordinates ``(s, z)``, shape ``broadcast(s, z) + (3,)``."""
        s = np.asarray(s, dtype=float)[..., None]
        z = np.asarray(z, dtype=float)[..., None]
        return self.origin_ + s * self.along_ + z * self.up_

    def intersect(
        self, origins: np.ndarray, dirs: np.ndarray, *, finite: bool = True
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Intersect rays with the mirror.

        Parameters
        ----------
        origins, dirs : (n, 3) float
            Ray origins and unit directions.
        finite : bool
            If True, hits outside the rectangle count as misses.

        Returns
        -------
        t : (n,) float
            Distance along each ray to the plane (``inf`` where missed).
        s, z : (n,) float
            Patch coordinates of the hit point.
        """
        origins = np.atleast_2d(origins)
        dirs = np.atleast_2d(dirs)
        t = ray_plane_distance(origins, dirs, self.origin_, self.normal_)
        finite_t = np.where(np.isfinite(t), t, 0.0)
        rel = origins + finite_t[:, None] * dirs - self.origin_
        s = rel @ self.along_
        z = rel @ self.up_
        if finite:
            inside = (s >= self.s_min) & (s <= self.s_max) & (z >= self.z_min) & (z <= self.z_max)
            t = np.where(inside, t, np.inf)
        return t, s, z

    # -- rigid motions -----------------------------------------------------------------
    def transformed(self, R: np.ndarray, t: np.ndarray) -> MirrorPatch:
        """The patch moved by ``p -> R p + t`` (extents unchanged)."""
        R = np.asarray(R, dtype=float)
        return replace(
            self,
            origin=tuple(R @ self.origin_ + np.asarray(t, dtype=float)),
            normal=tuple(unit(R @ self.normal_)),
            along=tuple(unit(R @ self.along_)),
        )

    def rotated_about_hinge(self, angle: float) -> MirrorPatch:
        """The patch turned by ``angle`` [rad] about its hinge axis (right hand about ``along``).

        ``hinge_z`` is kept in the patch's own coordinates, so repeated calls compose.
        This is the mirror's own line (the axis of the mounting tilt ``dbeta``).
        """
        pivot = self.origin_ + self.hinge_z * self.up_
        return replace(
            self,
            origin=tuple(rotate_about_line(self.origin_, pivot, self.along_, angle)),
            normal=tuple(unit(rotate_about_axis(self.normal_, self.along_, angle))),
        )

    def perturbed(self, p: Perturbation) -> MirrorPatch:
        """Apply a mounting error: tilt about the hinge, then offset, then yaw about O
        (:func:`perturb_frames`, the only implementation of the model).

        The result remembers the perturbation (composed additively, which is exact for one
        application on a nominal mirror and first-order otherwise).
        """
        o, n, a, _ = perturb_frames(self.origin_, self.normal_, self.along_, self.up_,
                                    self.hinge_z, p.dalpha, p.dbeta, p.dd)
        total = Perturbation(*(self.perturbation.as_array() + p.as_array()))
        return replace(self, origin=tuple(o[0]), normal=tuple(unit(n[0])),
                       along=tuple(unit(a[0])), perturbation=total)


def reflect_rays(
    origins: np.ndarray, dirs: np.ndarray, point: np.ndarray, normal: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Reflect rays on the (infinite) plane through ``point`` with unit ``normal``.

    Returns
    -------
    t : (n,) float
        Distance from each origin to the plane (``inf`` if it never gets there).
    hit : (n, 3) float
        Hit points.
    out : (n, 3) float
        Reflected unit directions.
    """
    origins = np.atleast_2d(np.asarray(origins, dtype=float))
    dirs = np.atleast_2d(np.asarray(dirs, dtype=float))
    t = ray_plane_distance(origins, dirs, np.asarray(point, float), np.asarray(normal, float))
    hit = origins + np.where(np.isfinite(t), t, np.nan)[:, None] * dirs
    return t, hit, reflect(dirs, np.asarray(normal, float))


def arc_point(hit: np.ndarray, out: np.ndarray, radius: float) -> np.ndarray:
    """Where rays starting at ``hit`` along ``out`` cross the cylinder |xy| = radius. (n, 3)."""
    t = ray_circle_exit(hit, out, radius)
    return hit + t[:, None] * out


def wrap_angle(a: np.ndarray | float) -> np.ndarray:
    """Wrap angles to [-pi, pi)."""
    return np.mod(np.asarray(a, dtype=float) + np.pi, 2 * np.pi) - np.pi
