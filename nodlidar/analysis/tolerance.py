"""Tolerance analysis: mounting errors as distributions, Monte Carlo, sensitivities.

The ``[tolerance]`` table of a design file (all keys optional; defaults below)::

    [tolerance]
    distribution = "normal"     # "normal": values are 1-sigma; "uniform": values are half-widths
    dalpha_rad = 0.001          # every mirror: yaw about the lidar axis [rad]
    dbeta_rad = 0.001           # every mirror: tilt about its hinge [rad]
    dd_m = 0.0002               # every mirror: offset along its normal [m]
    ranges_m = [0.4, 1.0, 2.0, 6.0]   # where errors are evaluated [m]
    percentiles = [50.0, 95.0, 99.0]
    samples = 10000
    seed = 0
    chunk_size = 1000           # part of the reproducibility contract (seeds are per chunk)

    [tolerance.mirrors.L1]      # per-mirror overrides of the three values above
    dalpha_rad = 0.002

    [tolerance.lidar]           # the lidar's own mounting relative to the mirror assembly
    yaw_rad = 0.0               # about z
    pitch_rad = 0.0             # about y
    roll_rad = 0.0              # about x (tilts the scan plane sideways)
    offset_m = 0.0              # each of x, y, z

Mirror errors are applied as :class:`~nodlidar.geometry.Perturbation` (tilt about the
hinge, offset, yaw about O - :meth:`MirrorPatch.perturbed`); the lidar mounting error is a
rigid motion of every mirror into the actual lidar frame
(:meth:`MirrorPatch.transformed`). The Monte Carlo evaluates that in numpy arrays over
samples (:func:`trace_samples`; tests check it against ``MirrorPatch.perturbed`` and
:func:`~nodlidar.verify.verify`).

What is measured, per sample and mirror, on each arc of radius R (lidar frame):

* **bearing error**: the bearing the runtime reports (the nominal
  :class:`~nodlidar.beams.BeamModel` applied to the measured path length) minus the true
  bearing of the point the beam hit on the arc;
* **projected-range error**: the same point's horizontal range, reported minus true;
* **elevation**: the angle of the traced reflected direction out of the scan plane
  (``asin(dir_z)``; the paper's ``2 dbeta`` at normal incidence, ``asin(cos(theta_r)
  sin(2 dbeta))`` in general), and the height of the hit point on the arc;
* **edge misses**: beams that no longer fall on their own (finite) mirror patch (mirrors
  are evaluated one at a time, so a beam caught first by a displaced neighbour is not
  counted; :func:`~nodlidar.verify.verify` sees that).

Large runs go through Dask in fixed-size chunks, each seeded from
``np.random.SeedSequence(seed).spawn(n_chunks)[i]``, so a seed gives the same numbers on
any number of workers, or with no Dask at all.
"""

from __future__ import annotations

import contextlib
import math
import os
import signal
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from .._light import MAX_SAMPLES  # defined without numpy: the CLI parser shows it
from ..design import Design
from ..errors import ParameterError, require
from ..geometry import (
    EZ,
    MirrorPatch,
    Perturbation,
    arc_point,
    bearing_of,
    directions_from_bearings,
    incidence_angle,
    perturb_frames,
    reflect_rays,
    rot_x,
    rot_y,
    rot_z,
    rotate_about_axis,
    wrap_angle,
)
from ..spec import DesignSpec
from ..validation import check_keys

__all__ = [
    "DISTRIBUTIONS",
    "MirrorSigma",
    "LidarSigma",
    "ToleranceSpec",
    "tolerance_spec",
    "LidarMount",
    "mounted_patches",
    "SampleTrace",
    "trace_samples",
    "ToleranceResult",
    "monte_carlo",
    "dask_map",
    "check_scheduler",
    "DASK_MIN_SAMPLES",
    "runner_for",
    "SensitivityResult",
    "sensitivities",
    "PARAMETERS",
    "METRICS",
]

DISTRIBUTIONS = ("normal", "uniform")

#: Parameters of the sensitivity table and their SI units.
PARAMETERS = {"dalpha": "rad", "dbeta": "rad", "dd": "m", "lidar_yaw": "rad",
              "lidar_pitch": "rad", "lidar_roll": "rad", "lidar_x": "m", "lidar_y": "m"}

#: Columns of a lidar mounting error array: ``(..., 6)``; 5 columns mean no roll (the
#: roll column was added last so that a seed draws the same other errors as before).
LIDAR_COLUMNS = ("yaw", "pitch", "x", "y", "z", "roll")


# ---------------------------------------------------------------------------------------
# the [tolerance] table


#: Upper bounds of the [tolerance] table. A mounting error's spread beyond 0.2 rad (11 deg)
#: or 50 mm is not a tolerance of this build: the traced beams then miss the mirrors and
#: the tables fill with NaN. Samples and chunks are bounded by memory: a kept sample is
#: 4 x mirrors x (4 x ranges + 2) bytes (~290 B for the paper's build, 0.55 GiB at
#: MAX_SAMPLES; ``keep_samples=False`` keeps O(sqrt(samples)) values instead) and a chunk's
#: rows travel whole from a Dask worker (the kernel itself works in fixed-size blocks).
MAX_SIGMA_RAD = 0.2
MAX_SIGMA_M = 0.05
MAX_CHUNK_SIZE = 20_000
MAX_RANGE_M = 100.0


def _nonneg(table: dict, key: str, where: str, default: float) -> float:
    v = table.get(key, default)
    hi = MAX_SIGMA_M if key.endswith("_m") else MAX_SIGMA_RAD
    unit = "m" if key.endswith("_m") else "rad"
    require(isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)
            and 0 <= v <= hi, f"{where}.{key}", v, f"a finite number in 0 .. {hi:g} {unit}")
    return float(v)


def _unknown(table: Any, allowed: set[str], where: str) -> None:
    """Refuse a non-table or unknown keys, naming the nearest valid key."""
    check_keys(table, allowed, where)


@dataclass(frozen=True)
class MirrorSigma:
    """Spread of one mirror's mounting error (1-sigma, or half-width if uniform).

    Attributes
    ----------
    dalpha_rad : float
        Yaw about the lidar axis [rad].
    dbeta_rad : float
        Tilt about the hinge [rad].
    dd_m : float
        Offset along the mirror normal [m].
    """

    dalpha_rad: float = 0.001
    dbeta_rad: float = 0.001
    dd_m: float = 0.0002

    def as_array(self) -> np.ndarray:
        return np.array([self.dalpha_rad, self.dbeta_rad, self.dd_m])


@dataclass(frozen=True)
class LidarSigma:
    """Spread of the lidar's mounting error relative to the mirror assembly.

    Attributes
    ----------
    yaw_rad, pitch_rad, roll_rad : float
        Rotation about z, y and x [rad].
    offset_m : float
        Translation along each of x, y, z [m].
    """

    yaw_rad: float = 0.0
    pitch_rad: float = 0.0
    offset_m: float = 0.0
    roll_rad: float = 0.0

    def as_array(self) -> np.ndarray:
        """``(6,)`` in :data:`LIDAR_COLUMNS` order: yaw, pitch, x, y, z, roll."""
        return np.array([self.yaw_rad, self.pitch_rad, self.offset_m, self.offset_m, self.offset_m,
                         self.roll_rad])


@dataclass(frozen=True)
class ToleranceSpec:
    """The parsed ``[tolerance]`` table (see the module docstring)."""

    distribution: str = "normal"
    mirror: MirrorSigma = field(default_factory=MirrorSigma)
    mirrors: dict[str, MirrorSigma] = field(default_factory=dict)
    lidar: LidarSigma = field(default_factory=LidarSigma)
    ranges_m: tuple[float, ...] = (0.4, 1.0, 2.0, 6.0)
    percentiles: tuple[float, ...] = (50.0, 95.0, 99.0)
    samples: int = 10000
    seed: int = 0
    chunk_size: int = 1000

    def __post_init__(self) -> None:
        require(self.distribution in DISTRIBUTIONS, "tolerance.distribution", self.distribution,
                " or ".join(DISTRIBUTIONS))
        object.__setattr__(self, "ranges_m", tuple(float(x) for x in self.ranges_m))
        require(1 <= len(self.ranges_m) <= 64 and all(math.isfinite(x) and 0 < x <= MAX_RANGE_M
                                                      for x in self.ranges_m),
                "tolerance.ranges_m", list(self.ranges_m),
                f"1 to 64 ranges in 0 (excluded) .. {MAX_RANGE_M:g} m")
        object.__setattr__(self, "percentiles", tuple(float(x) for x in self.percentiles))
        require(1 <= len(self.percentiles) <= 64 and all(0 <= x <= 100 for x in self.percentiles),
                "tolerance.percentiles", list(self.percentiles), "1 to 64 values in 0..100")
        for key, hi in (("samples", MAX_SAMPLES), ("chunk_size", MAX_CHUNK_SIZE)):
            v = getattr(self, key)
            require(isinstance(v, int) and not isinstance(v, bool) and 1 <= v <= hi,
                    f"tolerance.{key}", v, f"an integer in 1 .. {hi}")
        require(isinstance(self.seed, int) and not isinstance(self.seed, bool) and self.seed >= 0,
                "tolerance.seed", self.seed, "an integer >= 0")

    def sigma_for(self, name: str) -> MirrorSigma:
        """The spread of mirror ``name`` (its override, else the all-mirror values)."""
        return self.mirrors.get(name, self.mirror)

    def sigma_array(self, names: tuple[str, ...] | list[str]) -> np.ndarray:
        """``(m, 3)`` spreads of ``names`` (dalpha, dbeta, dd)."""
        unknown = sorted(set(self.mirrors) - set(names))
        if unknown:
            raise ParameterError(f"tolerance.mirrors.{unknown[0]}", unknown[0],
                                 f"a mirror of this design: {', '.join(names)}")
        return np.stack([self.sigma_for(n).as_array() for n in names])

    def replace(self, **changes: Any) -> ToleranceSpec:
        return ToleranceSpec(**{**{f.name: getattr(self, f.name) for f in fields(self)},
                                **changes})

    def to_dict(self) -> dict[str, Any]:
        """The ``[tolerance]`` table as plain data (round-trips through :func:`tolerance_spec`)."""
        out: dict[str, Any] = {"distribution": self.distribution,
                               "dalpha_rad": self.mirror.dalpha_rad,
                               "dbeta_rad": self.mirror.dbeta_rad, "dd_m": self.mirror.dd_m,
                               "ranges_m": list(self.ranges_m),
                               "percentiles": list(self.percentiles), "samples": self.samples,
                               "seed": self.seed, "chunk_size": self.chunk_size,
                               "lidar": {f.name: getattr(self.lidar, f.name)
                                         for f in fields(self.lidar)}}
        if self.mirrors:
            out["mirrors"] = {n: {f.name: getattr(s, f.name) for f in fields(s)}
                              for n, s in self.mirrors.items()}
        return out


_MIRROR_KEYS = {"dalpha_rad", "dbeta_rad", "dd_m"}
_TOP_KEYS = _MIRROR_KEYS | {"distribution", "ranges_m", "percentiles", "samples", "seed",
                            "chunk_size", "mirrors", "lidar"}


def tolerance_spec(source: DesignSpec | dict[str, Any] | None = None) -> ToleranceSpec:
    """Parse and validate a ``[tolerance]`` table.

    Parameters
    ----------
    source : DesignSpec or dict or None
        A design spec (its ``sections["tolerance"]`` is used, defaults if absent), the
        table itself, or None for all defaults.

    Raises
    ------
    ParameterError
        Naming the offending ``tolerance.*`` field, its value and what is allowed.
    """
    if source is None:
        table: dict[str, Any] = {}
    elif isinstance(source, dict):
        table = source
    else:
        table = source.sections.get("tolerance", {})
    _unknown(table, _TOP_KEYS, "tolerance")
    default = MirrorSigma()
    base = MirrorSigma(**{k: _nonneg(table, k, "tolerance", getattr(default, k))
                          for k in _MIRROR_KEYS})
    mirrors: dict[str, MirrorSigma] = {}
    per = table.get("mirrors", {})
    _unknown(per, set(per) if isinstance(per, dict) else set(), "tolerance.mirrors")
    for name, sub in per.items():
        where = f"tolerance.mirrors.{name}"
        _unknown(sub, _MIRROR_KEYS, where)
        mirrors[name] = MirrorSigma(**{k: _nonneg(sub, k, where, getattr(base, k))
                                       for k in _MIRROR_KEYS})
    lt = table.get("lidar", {})
    lidar_keys = ("yaw_rad", "pitch_rad", "roll_rad", "offset_m")
    _unknown(lt, set(lidar_keys), "tolerance.lidar")
    lidar = LidarSigma(**{k: _nonneg(lt, k, "tolerance.lidar", 0.0) for k in lidar_keys})
    kw: dict[str, Any] = {}
    for key in ("distribution", "ranges_m", "percentiles", "samples", "seed", "chunk_size"):
        if key in table:
            kw[key] = table[key]
    for key in ("ranges_m", "percentiles"):
        if key in kw:
            v = kw[key]
            if not isinstance(v, list | tuple) or not all(
                    isinstance(x, int | float) and not isinstance(x, bool) for x in v):
                raise ParameterError(f"tolerance.{key}", v, "a list of numbers")
    return ToleranceSpec(mirror=base, mirrors=mirrors, lidar=lidar, **kw)


# ---------------------------------------------------------------------------------------
# the reference path: geometry objects


@dataclass(frozen=True)
class LidarMount:
    """The lidar's pose error in the mirror-assembly frame: yaw, pitch, roll [rad], offset [m].

    The lidar sits at ``R = rot_z(yaw) @ rot_y(pitch) @ rot_x(roll)``, ``offset``; a point
    ``p`` of the assembly is at ``R^T (p - offset)`` in the lidar frame.
    """

    yaw: float = 0.0
    pitch: float = 0.0
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    roll: float = 0.0

    @classmethod
    def from_array(cls, a: np.ndarray) -> LidarMount:
        """From ``(5,)`` or ``(6,)`` in :data:`LIDAR_COLUMNS` order (yaw, pitch, x, y, z[, roll])."""
        a = np.asarray(a, dtype=float)
        roll = float(a[5]) if len(a) > 5 else 0.0
        return cls(float(a[0]), float(a[1]), (float(a[2]), float(a[3]), float(a[4])), roll)

    def rotation(self) -> np.ndarray:
        return _mount_rotation(np.array([self.yaw]), np.array([self.pitch]),
                               np.array([self.roll]))[0]


def _mount_rotation(yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """``rot_z(yaw) @ rot_y(pitch) @ rot_x(roll)`` for arrays ``(n,)`` -> ``(n, 3, 3)``."""
    return rot_z(yaw) @ rot_y(pitch) @ rot_x(roll)


def mounted_patches(design: Design, perturbations: dict[str, Perturbation] | None = None,
                    mount: LidarMount | None = None) -> list[MirrorPatch]:
    """The design's patches, perturbed, then seen from a mis-mounted lidar (lidar frame)."""
    patches = design.patches(perturbations)
    if mount is None:
        return patches
    R = mount.rotation()
    return [p.transformed(R.T, -R.T @ np.asarray(mount.offset, float)) for p in patches]


# ---------------------------------------------------------------------------------------
# the batched path


@dataclass(frozen=True, eq=False)
class _MirrorData:
    """Everything the batch needs about one mirror (plain arrays, cheap to pickle)."""

    name: str
    theta: np.ndarray        # (b,) beam bearings
    origin: np.ndarray       # (3,)
    normal: np.ndarray       # (3,) towards the lidar, as in the patch
    along: np.ndarray        # (3,)
    up: np.ndarray           # (3,)
    hinge_z: float
    extent: np.ndarray       # (4,) s_min, s_max, z_min, z_max
    t0: np.ndarray           # (b,) nominal path to the mirror (BeamModel)
    hit0: np.ndarray         # (b, 3)
    out0: np.ndarray         # (b, 3)


@dataclass(frozen=True, eq=False)
class _Problem:
    mirrors: tuple[_MirrorData, ...]
    sigma: np.ndarray        # (m, 3)
    lidar_sigma: np.ndarray  # (6,), LIDAR_COLUMNS
    distribution: str
    ranges: np.ndarray       # (r,)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(m.name for m in self.mirrors)


def _problem(design: Design, tol: ToleranceSpec, ranges_m=None) -> _Problem:
    bm = design.beam_model()
    lid = design.lidar
    data = []
    for m in design.mirrors:
        p = m.patch
        start, d, off = bm.rays(m.steps)
        data.append(_MirrorData(
            name=m.name, theta=lid.bearing_from_step(m.steps), origin=p.origin_,
            normal=p.normal_, along=p.along_, up=p.up_, hinge_z=float(p.hinge_z),
            extent=np.array([p.s_min, p.s_max, p.z_min, p.z_max]), t0=off, hit0=start, out0=d))
    names = tuple(m.name for m in design.mirrors)
    ranges = np.asarray(tol.ranges_m if ranges_m is None else ranges_m, dtype=float)
    return _Problem(mirrors=tuple(data), sigma=tol.sigma_array(names),
                    lidar_sigma=tol.lidar.as_array(), distribution=tol.distribution,
                    ranges=np.atleast_1d(ranges))


@dataclass(frozen=True, eq=False)
class SampleTrace:
    """One mirror's beams traced for ``n`` sampled builds (lidar frame).

    Attributes
    ----------
    name : str
    bearing : (n, b, r) float
        True bearing where each reflected beam crosses each arc [rad].
    points : (n, b, r, 3) float
        Those points [m].
    bearing_error : (n, b, r) float
        Bearing reported by the nominal BeamModel minus ``bearing`` [rad].
    range_error : (n, b, r) float
        Horizontal range reported minus true (true = the arc radius) [m].
    elevation : (n, b) float
        Angle of the reflected direction out of the scan plane, ``asin(dir_z)`` [rad].
    on_patch : (n, b) bool
        Whether the beam still hits its own finite mirror patch.
    """

    name: str
    bearing: np.ndarray
    points: np.ndarray
    bearing_error: np.ndarray
    range_error: np.ndarray
    elevation: np.ndarray
    on_patch: np.ndarray


#: Samples traced together inside a chunk: the kernel's (beams, block) working arrays
#: (~110 x 128 float64 = 110 kB each, ~20 of them) stay near a core's L2 cache. Only the
#: speed depends on it, never a result (chunks, not blocks, carry the seeds).
BLOCK_SAMPLES = 128

_EX, _EY, _EZ = np.eye(3)


def _lidar_frames(md: _MirrorData, dm: np.ndarray, dl: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Each sample's mirror frame in its mis-mounted lidar's frame: origin, normal, along,
    up, each ``(n, 3)``.

    1-3. the mounting-error model (:func:`~nodlidar.geometry.perturb_frames`, the same
    function as ``MirrorPatch.perturbed``); 4. a point ``p`` of the assembly is at
    ``R^T (p - offset)`` in the lidar frame, ``R = rot_z(yaw) rot_y(pitch) rot_x(roll)``
    (:class:`LidarMount`): turned about z by -yaw, then about y by -pitch, then about x by
    -roll (``rotate_about_axis`` by columns: no (n, 3, 3) matrices, no BLAS for 3 x 3).
    """
    o, nrm, along, up = perturb_frames(md.origin, md.normal, md.along, md.up, md.hinge_z,
                                       dm[:, 0], dm[:, 1], dm[:, 2])
    yaw, pitch, roll = -dl[:, 0], -dl[:, 1], -dl[:, 5]

    def to_lidar(v: np.ndarray) -> np.ndarray:
        v = rotate_about_axis(v, _EZ, yaw)
        v = rotate_about_axis(v, _EY, pitch)
        return rotate_about_axis(v, _EX, roll)

    return to_lidar(o - dl[:, 2:5]), to_lidar(nrm), to_lidar(along), to_lidar(up)


class _Sink:
    """Receives the kernel's columns of samples ``lo:hi``: ``(b, k)`` views of buffers the
    kernel reuses, so a sink reduces or copies them before it returns (it may overwrite
    them)."""

    def beams(self, lo: int, hi: int, out_z: np.ndarray, on: np.ndarray) -> None:
        """``out_z``: z of the reflected directions; ``on``: the hit is on the patch."""
        raise NotImplementedError

    def arc(self, lo: int, hi: int, j: int, px: np.ndarray, py: np.ndarray, pz: np.ndarray,
            berr: np.ndarray, rerr: np.ndarray) -> None:
        """Arc ``j``: the true point P [m], bearing error [rad], range error [m]."""
        raise NotImplementedError


def _trace_kernel(md: _MirrorData, dm: np.ndarray, dl: np.ndarray, ranges: np.ndarray,
                  sink: _Sink, block: int = BLOCK_SAMPLES) -> None:
    """Trace one mirror's beams on ``n`` sampled builds, block by block, into ``sink``.

    The one implementation behind :func:`trace_samples` and :func:`monte_carlo`.
    ``dm (n, 3)``, ``dl (n, 6)`` as in :func:`trace_samples`. Arrays are ``(b, k)`` (beams
    x samples of a block), x, y and z as separate columns in reused buffers written with
    ``out=``: no ``(n, b, r, 3)`` temporary exists. Per beam and sample: the distance ``t``
    along the beam from O (in the scan plane, z = 0) to the sampled plane, the hit point,
    the reflected direction ``out``, whether the hit is on the patch; per arc radius R: the
    exit ``t1`` of the reflected ray from the cylinder ``|xy| = R`` (the larger root, as
    :func:`~nodlidar.geometry.ray_circle_exit`; NaN if it never gets there), the true point
    ``P``, the point ``Q`` the nominal BeamModel reports for the measured path ``t + t1``,
    and the errors:

    * bearing ``atan2(P x Q, P . Q)`` (= ``wrap(bearing(Q) - bearing(P))``, one atan2);
    * range ``|Q_xy| - R`` (``|P_xy| = R`` by construction, to ~1e-16 m).
    """
    n, b = len(dm), len(md.theta)
    fo, fn, fa, fu = (np.ascontiguousarray(v.T) for v in _lidar_frames(md, dm, dl))  # (3, n)
    cth, sth = np.cos(md.theta)[:, None], np.sin(md.theta)[:, None]      # (b, 1)
    t0 = md.t0[:, None]
    h0x, h0y = md.hit0[:, 0:1], md.hit0[:, 1:2]
    o0x, o0y = md.out0[:, 0:1], md.out0[:, 1:2]
    s_lo, s_hi, z_lo, z_hi = (float(x) for x in md.extent)
    radii = [float(r) for r in ranges]
    k = max(1, min(block, n))
    fbuf = np.empty((20, b, k))
    bbuf = np.empty((2, b, k), bool)
    with np.errstate(divide="ignore", invalid="ignore"):
        for lo in range(0, n, k):
            hi = min(lo + k, n)
            (den, t, hx, hy, ox, oy, oz, w1, w2, a2, a4, bb, nb, c0, disc, t1, px, py, q,
             qx) = fbuf[:, :, :hi - lo]   # the last, shorter block: views of the same buffers
            qy = w2
            on, tmp = bbuf[:, :, :hi - lo]
            nx, ny, nz = fn[:, None, lo:hi]                                   # (1, k) each
            cx, cy, cz = fo[:, None, lo:hi]
            # distance to the plane along each beam: (o . n) / (d0 . n), d0 = (cos, sin, 0)
            np.multiply(cth, nx, out=den)
            np.multiply(sth, ny, out=w1)
            den += w1
            np.divide(cx * nx + cy * ny + cz * nz, den, out=t)
            np.multiply(t, cth, out=hx)
            np.multiply(t, sth, out=hy)
            # the reflection d0 - 2 (d0 . n) n
            np.multiply(den, 2.0, out=w2)
            np.multiply(w2, nx, out=w1)
            np.subtract(cth, w1, out=ox)
            np.multiply(w2, ny, out=w1)
            np.subtract(sth, w1, out=oy)
            np.multiply(w2, nz, out=oz)
            np.negative(oz, out=oz)
            # on the patch: (hit - o) . along in [s_min, s_max] and . up in [z_min, z_max]
            np.greater(t, 0.0, out=on)
            for e, lim_lo, lim_hi in ((fa, s_lo, s_hi), (fu, z_lo, z_hi)):
                ex, ey, ez = e[:, None, lo:hi]
                np.subtract(hx, cx, out=w1)
                w1 *= ex
                np.subtract(hy, cy, out=w2)
                w2 *= ey
                w1 += w2
                w1 -= cz * ez
                np.greater_equal(w1, lim_lo, out=tmp)
                on &= tmp
                np.less_equal(w1, lim_hi, out=tmp)
                on &= tmp
            sink.beams(lo, hi, oz, on)
            # the cylinder |xy| = R: a t1^2 + bq t1 + (|h|^2 - R^2) = 0
            np.multiply(ox, ox, out=a2)
            np.multiply(oy, oy, out=w1)
            a2 += w1                                     # a
            np.multiply(a2, 4.0, out=a4)
            a2 *= 2.0
            np.multiply(hx, ox, out=nb)
            np.multiply(hy, oy, out=w1)
            nb += w1
            nb *= 2.0                                    # bq
            np.multiply(nb, nb, out=bb)
            np.negative(nb, out=nb)
            np.multiply(hx, hx, out=c0)
            np.multiply(hy, hy, out=w1)
            c0 += w1
            for j, r in enumerate(radii):
                np.subtract(c0, r * r, out=w1)
                w1 *= a4
                np.subtract(bb, w1, out=disc)
                np.sqrt(disc, out=t1)
                t1 += nb
                t1 /= a2
                np.greater_equal(disc, 0.0, out=on)
                np.greater(t1, 0.0, out=tmp)
                on &= tmp
                np.logical_not(on, out=on)
                np.copyto(t1, np.nan, where=on)
                np.multiply(t1, ox, out=px)                # P = h + t1 out
                px += hx
                np.multiply(t1, oy, out=py)
                py += hy
                np.multiply(t1, oz, out=disc)                   # P_z (h_z = 0)
                # Q = hit0 + out0 (t + t1 - t0), the nominal model's point
                np.add(t, t1, out=q)
                q -= t0
                np.multiply(o0x, q, out=qx)
                qx += h0x
                np.multiply(o0y, q, out=qy)
                qy += h0y
                # bearing error atan2(P x Q, P . Q) into t1, range error |Q_xy| - R into q
                np.multiply(px, qy, out=t1)
                np.multiply(py, qx, out=w1)
                t1 -= w1
                np.multiply(px, qx, out=q)
                np.multiply(py, qy, out=w1)
                q += w1
                np.arctan2(t1, q, out=t1)
                np.multiply(qx, qx, out=q)
                np.multiply(qy, qy, out=w1)
                q += w1
                np.sqrt(q, out=q)
                q -= r
                sink.arc(lo, hi, j, px, py, disc, t1, q)


class _TraceSink(_Sink):
    """Keeps every column: the arrays of a :class:`SampleTrace`."""

    def __init__(self, n: int, b: int, r: int) -> None:
        self.bearing = np.empty((n, b, r))
        self.points = np.empty((n, b, r, 3))
        self.bearing_error = np.empty((n, b, r))
        self.range_error = np.empty((n, b, r))
        self.elevation = np.empty((n, b))
        self.on_patch = np.empty((n, b), bool)

    def beams(self, lo, hi, out_z, on):
        self.elevation[lo:hi] = np.arcsin(np.clip(out_z, -1.0, 1.0)).T
        self.on_patch[lo:hi] = on.T

    def arc(self, lo, hi, j, px, py, pz, berr, rerr):
        for i, c in enumerate((px, py, pz)):
            self.points[lo:hi, :, j, i] = c.T
        self.bearing[lo:hi, :, j] = np.arctan2(py, px).T
        self.bearing_error[lo:hi, :, j] = berr.T
        self.range_error[lo:hi, :, j] = rerr.T


class _SummarySink(_Sink):
    """Reduces over one mirror's beams into ``out``'s rows (the keys of :data:`METRICS`
    and ``edge_misses`` present in ``out``: ``(n, r)`` or ``(n,)`` views, any dtype)."""

    def __init__(self, out: dict[str, np.ndarray], b: int) -> None:
        self.out, self.b = out, b

    def beams(self, lo, hi, out_z, on):
        o = self.out
        if "elevation_max" in o:   # asin is odd and increasing: max |asin| = asin(max ||)
            np.abs(out_z, out=out_z)
            o["elevation_max"][lo:hi] = np.arcsin(np.clip(out_z.max(axis=0), -1.0, 1.0))
        if "edge_misses" in o:
            o["edge_misses"][lo:hi] = self.b - np.count_nonzero(on, axis=0)

    def arc(self, lo, hi, j, px, py, pz, berr, rerr):
        o = self.out
        if "bearing_error_mean" in o:
            o["bearing_error_mean"][lo:hi, j] = np.add.reduce(berr, axis=0) / self.b
        for key, v in (("bearing_error_max", berr), ("range_error_max", rerr),
                       ("height_max", pz)):
            if key in o:
                o[key][lo:hi, j] = np.abs(v, out=v).max(axis=0)


def _trace_mirror(md: _MirrorData, dm: np.ndarray, dl: np.ndarray,
                  ranges: np.ndarray) -> SampleTrace:
    """Batched equivalent of ``patch.perturbed(...)`` then ``.transformed(...)`` + trace,
    every array kept (:func:`_trace_kernel`)."""
    sink = _TraceSink(len(dm), len(md.theta), len(ranges))
    _trace_kernel(md, dm, dl, ranges, sink)
    return SampleTrace(name=md.name, bearing=sink.bearing, points=sink.points,
                       bearing_error=sink.bearing_error, range_error=sink.range_error,
                       elevation=sink.elevation, on_patch=sink.on_patch)


def trace_samples(design: Design, mirror_errors: np.ndarray, lidar_errors: np.ndarray | None = None,
                  ranges_m: ArrayLike = (2.0,)) -> list[SampleTrace]:
    """Trace every mirror's beams for ``n`` sampled builds at once.

    Parameters
    ----------
    design : Design
    mirror_errors : (n, m, 3) float
        Per sample and mirror (in ``design.mirrors`` order): dalpha [rad], dbeta [rad],
        dd [m], applied exactly like :meth:`MirrorPatch.perturbed`.
    lidar_errors : (n, 5) or (n, 6) float, optional
        Lidar yaw, pitch [rad], x, y, z offset [m] and roll [rad] (:data:`LIDAR_COLUMNS`,
        :class:`LidarMount`); 5 columns mean no roll.
    ranges_m : (r,) float
        Arc radii [m].

    Returns
    -------
    list of SampleTrace, one per mirror.
    """
    dm = np.asarray(mirror_errors, dtype=float)
    m = len(design.mirrors)
    if dm.ndim != 3 or dm.shape[1:] != (m, 3):
        raise ParameterError("mirror_errors", f"shape {dm.shape}", f"(n, {m}, 3)")
    dl = np.zeros((len(dm), 6)) if lidar_errors is None else np.asarray(lidar_errors, dtype=float)
    if dl.shape not in ((len(dm), 5), (len(dm), 6)):
        raise ParameterError("lidar_errors", f"shape {dl.shape}", f"({len(dm)}, 5) or ({len(dm)}, 6)")
    if dl.shape[1] == 5:
        dl = np.c_[dl, np.zeros(len(dl))]
    prob = _problem(design, ToleranceSpec(), ranges_m)
    return [_trace_mirror(md, dm[:, i], dl, prob.ranges) for i, md in enumerate(prob.mirrors)]


# ---------------------------------------------------------------------------------------
# Monte Carlo

#: Per-sample metrics kept by :func:`monte_carlo` (name -> unit).
METRICS = {"bearing_error_max": "rad", "bearing_error_mean": "rad", "range_error_max": "m",
           "height_max": "m", "elevation_max": "rad"}


def _draw(rng: np.random.Generator, shape: tuple[int, ...], distribution: str) -> np.ndarray:
    if distribution == "normal":
        return rng.standard_normal(shape)
    return rng.uniform(-1.0, 1.0, shape)


def _sample(prob: _Problem, n: int, seed: np.random.SeedSequence) -> tuple[np.ndarray, np.ndarray]:
    """``(n, m, 3)`` mirror errors and ``(n, 6)`` lidar errors (:data:`LIDAR_COLUMNS`) for
    one chunk. The roll column is drawn last, so the other errors of a seed are the same
    as before it existed."""
    rng = np.random.default_rng(seed)
    dm = _draw(rng, (n, len(prob.mirrors), 3), prob.distribution) * prob.sigma[None]
    dl = _draw(rng, (n, 5), prob.distribution) * prob.lidar_sigma[None, :5]
    roll = _draw(rng, (n, 1), prob.distribution) * prob.lidar_sigma[None, 5:]
    return dm, np.c_[dl, roll]


#: Per-sample arrays of a Monte Carlo result: name -> (dtype, per range?).
_ARRAYS = {"bearing_error_max": (np.float32, True), "bearing_error_mean": (np.float32, True),
           "range_error_max": (np.float32, True), "height_max": (np.float32, True),
           "elevation_max": (np.float32, False), "edge_misses": (np.int32, False)}


def _empty(keys: Sequence[str], n: int, m: int, r: int) -> dict[str, np.ndarray]:
    return {k: np.empty((n, m, r) if _ARRAYS[k][1] else (n, m), _ARRAYS[k][0]) for k in keys}


def _run_chunk(prob: _Problem, n: int, seed: np.random.SeedSequence,
               out: dict[str, np.ndarray] | None = None,
               keys: Sequence[str] = tuple(_ARRAYS)) -> dict[str, np.ndarray]:
    """Evaluate one chunk: per-sample, per-mirror summaries (float32 to keep big runs small).

    ``out``: ``(n, m[, r])`` arrays to write into (views of the preallocated result), else
    new arrays of ``keys`` are returned (what a Dask worker sends back).
    """
    dm, dl = _sample(prob, n, seed)
    if out is None:
        out = _empty(keys, n, len(prob.mirrors), len(prob.ranges))
    for i, md in enumerate(prob.mirrors):
        sink = _SummarySink({k: v[:, i] for k, v in out.items()}, len(md.theta))
        _trace_kernel(md, dm[:, i], dl, prob.ranges, sink)
    return out


@dataclass(frozen=True, eq=False)
class ToleranceResult:
    """Monte Carlo results: per sampled build, per mirror (and per range where it applies).

    Attributes
    ----------
    design_name : str
    tolerance : ToleranceSpec
    mirror_names : tuple of str
    ranges_m : (r,) float
    seed, chunk_size, n_samples : int
    bearing_error_max : (N, m, r) float32
        Largest |bearing error| over the mirror's beams [rad].
    bearing_error_mean : (N, m, r) float32
        Mean signed bearing error over the mirror's beams [rad].
    range_error_max : (N, m, r) float32
        Largest |projected-range error| [m].
    height_max : (N, m, r) float32
        Largest |height| of the hit point above the scan plane [m].
    elevation_max : (N, m) float32
        Largest |elevation| of the reflected beams [rad].
    edge_misses : (N, m) int32
        Beams that fall off their own mirror patch.
    samples_kept : bool
        False for ``monte_carlo(..., keep_samples=False)``: the six arrays above are then
        empty (0 rows) and only the spec's percentiles of :data:`SUMMARY_METRICS` and the
        edge-miss fraction are known (``summary``), exactly as from the samples.
    summary : dict
        Without samples: metric -> ``(len(q), m[, r])`` percentiles; ``"edge_miss_fraction"``
        -> ``(m,)``.
    runner : str
        ``"in-process"`` or ``"dask"`` (what ran the chunks).
    wall_s, startup_s : float
        Wall time of the whole run, and of starting the Dask cluster within it (0 in
        process) [s].
    """

    design_name: str
    tolerance: ToleranceSpec
    mirror_names: tuple[str, ...]
    ranges_m: np.ndarray
    seed: int
    chunk_size: int
    n_samples: int
    bearing_error_max: np.ndarray
    bearing_error_mean: np.ndarray
    range_error_max: np.ndarray
    height_max: np.ndarray
    elevation_max: np.ndarray
    edge_misses: np.ndarray
    samples_kept: bool = True
    summary: dict[str, np.ndarray] = field(default_factory=dict)
    runner: str = "in-process"
    wall_s: float = 0.0
    startup_s: float = 0.0

    def percentiles(self, metric: str, q: Sequence[float] | np.ndarray | None = None) -> np.ndarray:
        """Percentiles over samples: ``(len(q), m[, r])``; ``q`` defaults to the spec's."""
        if metric not in METRICS and metric != "edge_misses":
            raise ParameterError("metric", metric, ", ".join([*METRICS, "edge_misses"]))
        if not self.samples_kept:
            spec_q = list(self.tolerance.percentiles)
            if metric not in self.summary:
                raise ParameterError("metric", metric, f"one of {', '.join(SUMMARY_METRICS)} "
                                     "(the samples were not kept: keep_samples=False)")
            if q is not None and [float(x) for x in np.atleast_1d(q)] != spec_q:
                raise ParameterError("q", list(np.atleast_1d(q)), f"the spec's percentiles "
                                     f"{spec_q} (the samples were not kept: keep_samples=False)")
            return self.summary[metric].copy()
        q = self.tolerance.percentiles if q is None else q
        return np.percentile(np.asarray(getattr(self, metric), dtype=float), q, axis=0)

    def edge_miss_fraction(self) -> np.ndarray:
        """``(m,)`` fraction of sampled builds in which a mirror loses a beam off its patch."""
        if not self.samples_kept:
            return self.summary["edge_miss_fraction"].copy()
        return np.mean(self.edge_misses > 0, axis=0)

    def table(self) -> list[dict[str, Any]]:
        """Rows (mirror, range) with percentiles in display units (deg, mm)."""
        qs = self.tolerance.percentiles
        be = np.degrees(self.percentiles("bearing_error_max"))
        re = self.percentiles("range_error_max") * 1e3
        he = self.percentiles("height_max") * 1e3
        el = np.degrees(self.percentiles("elevation_max"))
        miss = self.edge_miss_fraction()
        rows = []
        for i, name in enumerate(self.mirror_names):
            for j, r in enumerate(self.ranges_m):
                rows.append({
                    "mirror": name, "range_m": float(r),
                    **{f"bearing_err_p{q:g}_deg": float(be[k, i, j]) for k, q in enumerate(qs)},
                    **{f"range_err_p{q:g}_mm": float(re[k, i, j]) for k, q in enumerate(qs)},
                    **{f"height_p{q:g}_mm": float(he[k, i, j]) for k, q in enumerate(qs)},
                    **{f"elevation_p{q:g}_deg": float(el[k, i]) for k, q in enumerate(qs)},
                    "edge_miss_fraction": float(miss[i]),
                })
        return rows


#: Metrics a summary-only run (``keep_samples=False``) keeps percentiles of: the table's.
SUMMARY_METRICS = ("bearing_error_max", "range_error_max", "height_max", "elevation_max")
#: A summary-only run keeps the first samples that arrive whole (at most this many) to place a
#: window around each percentile; after that only the values inside the windows are kept.
PILOT_SAMPLES = 20_000
#: Half-width of each window in standard errors of the pilot's estimate of the percentile
#: (binomial, ``sqrt(q (1 - q) / pilot)``). A percentile that still falls outside its window
#: is found exactly by a second pass over the (reproducible) chunks: only speed is at stake.
WINDOW_SIGMAS = 6.0


class _Summary:
    """Exact percentiles (as ``np.percentile``, linear) of :data:`SUMMARY_METRICS` and the
    edge-miss fraction, without keeping every sample.

    Each sample's row is ``(m[, r])`` cells. Per cell and percentile q a window
    ``[lo, hi]`` (from a pilot) keeps the values inside it and counts those below, so the
    order statistics the percentile interpolates between are known exactly when they fall
    in the window. Each time the samples seen grow fourfold the windows narrow to the
    (smaller) standard error of that many samples, from the kept values themselves (the
    values dropped below a window are counted): memory ~ pilot + ``O(sqrt(samples))``.
    """

    def __init__(self, q_percent: Sequence[float], n_total: int, m: int) -> None:
        self.q_percent = [float(x) for x in q_percent]
        self.q = np.true_divide(self.q_percent, 100)        # as np.percentile does
        self.n = n_total
        self.pilot: list[dict[str, np.ndarray]] = []
        self.n_pilot = self.n_seen = 0
        self.edge_any = np.zeros(m, np.int64)
        self.full: dict[str, np.ndarray] | None = None        # a run no longer than its pilot
        self.lo: dict[str, np.ndarray] = {}                   # (nq, cells) window bounds
        self.hi: dict[str, np.ndarray] = {}
        self.below: dict[str, np.ndarray] = {}                # (nq, cells) counts below lo
        self.nan: dict[str, np.ndarray] = {}                  # (cells,) a NaN was seen
        self.kept: dict[str, list[list[tuple[np.ndarray, np.ndarray]]]] = {}
        self.n_windowed = 0                                   # samples the windows are from

    def add(self, chunk: dict[str, np.ndarray]) -> None:
        """One chunk's rows (views of a reused buffer: what is kept is copied)."""
        n = len(chunk["edge_misses"])
        self.edge_any += np.count_nonzero(chunk["edge_misses"] > 0, axis=0)
        self.n_seen += n
        if not self.lo and self.full is None:
            self.pilot.append({k: chunk[k].copy() for k in SUMMARY_METRICS})
            self.n_pilot += n
            if self.n_pilot >= min(PILOT_SAMPLES, self.n):
                self._windows()
            return
        self._stream(chunk)
        if self.n_seen >= 4 * self.n_windowed:
            self._narrow()

    def _half(self, n: int) -> np.ndarray:
        """Half-width of the windows after ``n`` samples, in quantile (0..1)."""
        return WINDOW_SIGMAS * np.sqrt(self.q * (1 - self.q) / n) + 2.0 / n

    def _narrow(self) -> None:
        """Narrow every window to the standard error of the samples seen so far."""
        n = self.n_seen
        half = self._half(n)
        for k in SUMMARY_METRICS:
            n_cells = self.nan[k].size
            for j, q in enumerate(self.q):
                cells, vals, count, start = self._sorted(k, j, n_cells)
                lo, hi, below = self.lo[k][j], self.hi[k][j], self.below[k][j]
                # the order statistics at ranks (q -+ half) n, where the kept values hold them
                for rank, bound in ((math.floor((q - half[j]) * n), lo),
                                    (math.ceil((q + half[j]) * n), hi)):
                    if not 0 <= rank < n:
                        continue
                    idx = rank - below
                    ok = (idx >= 0) & (idx < count)
                    bound[ok] = vals[start[ok] + idx[ok]]
                drop_low = vals < lo[cells]
                below += np.bincount(cells[drop_low], minlength=n_cells)
                keep = ~drop_low & (vals <= hi[cells])
                self.kept[k][j] = [(cells[keep], vals[keep])]
        self.n_windowed = n

    def _sorted(self, k: str, j: int, n_cells: int
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The kept values of metric ``k``, window ``j``, sorted by cell then value: cells,
        values, count per cell, each cell's start."""
        parts = self.kept[k][j]
        cells = np.concatenate([c for c, _ in parts])
        vals = np.concatenate([v for _, v in parts])
        order = np.lexsort((vals, cells))
        cells, vals = cells[order], vals[order]
        count = np.bincount(cells, minlength=n_cells)
        return cells, vals, count, np.concatenate([[0], np.cumsum(count)[:-1]])

    def _windows(self) -> None:
        pilot = {k: np.concatenate([c[k] for c in self.pilot]) for k in SUMMARY_METRICS}
        self.pilot = []
        if self.n_pilot >= self.n:
            self.full = pilot
            return
        half = self._half(self.n_pilot)
        q_lo, q_hi = self.q - half, self.q + half
        for k, v in pilot.items():
            flat = v.reshape(len(v), -1).astype(float)
            with np.errstate(invalid="ignore"), _warnings_off():
                lo = np.nanpercentile(flat, np.clip(q_lo, 0, 1) * 100, axis=0)
                hi = np.nanpercentile(flat, np.clip(q_hi, 0, 1) * 100, axis=0)
            lo[q_lo <= 0] = -np.inf
            hi[q_hi >= 1] = np.inf
            # a cell whose pilot is all NaN: any window (its percentile is NaN anyway)
            self.lo[k] = np.nan_to_num(lo, nan=-np.inf)
            self.hi[k] = np.nan_to_num(hi, nan=np.inf)
            self.below[k] = np.zeros(lo.shape, np.int64)
            self.nan[k] = np.zeros(flat.shape[1], bool)
            self.kept[k] = [[] for _ in self.q]
        self.n_windowed = self.n_pilot
        self._stream(pilot)

    def _stream(self, chunk: dict[str, np.ndarray]) -> None:
        for k in SUMMARY_METRICS:
            v = chunk[k].reshape(len(chunk[k]), -1)
            self.nan[k] |= np.isnan(v).any(axis=0)
            for j in range(len(self.q)):
                self.below[k][j] += np.count_nonzero(v < self.lo[k][j], axis=0)
                rows, cells = np.nonzero((v >= self.lo[k][j]) & (v <= self.hi[k][j]))
                self.kept[k][j].append((cells.astype(np.int32), v[rows, cells]))

    def finish(self, rerun: Callable[[], Iterator[dict[str, np.ndarray]]],
               shapes: dict[str, tuple[int, ...]]) -> dict[str, np.ndarray]:
        """Percentiles ``(nq, *cell shape)`` per metric and ``edge_miss_fraction``;
        ``rerun()`` yields every chunk again (the second pass, if a window missed)."""
        out: dict[str, np.ndarray] = {"edge_miss_fraction": self.edge_any / self.n}
        if self.full is not None:
            for k, v in self.full.items():
                out[k] = np.percentile(np.asarray(v, dtype=float), self.q_percent, axis=0)
            return out
        missing: dict[str, set[int]] = {}
        n = self.n
        for k in SUMMARY_METRICS:
            n_cells = self.nan[k].size
            res = np.full((len(self.q), n_cells), np.nan)
            for j, q in enumerate(self.q):
                _, vals, count, start = self._sorted(k, j, n_cells)
                vals = vals.astype(float)
                h = (n - 1) * q                      # np.percentile's virtual index
                i0 = min(math.floor(h), n - 1)
                i1 = min(i0 + 1, n - 1)
                a0 = i0 - self.below[k][j]
                a1 = i1 - self.below[k][j]
                ok = (a0 >= 0) & (a1 < count) & ~self.nan[k]
                a = vals[start[ok] + a0[ok]]
                b = vals[start[ok] + a1[ok]]
                t = h - math.floor(h)
                diff = b - a                         # np.percentile's interpolation (_lerp)
                res[j, ok] = b - diff * (1 - t) if t >= 0.5 else a + diff * t
                missing.setdefault(k, set()).update(
                    int(x) for x in np.nonzero(~ok & ~self.nan[k])[0])
            out[k] = res
        todo = [(k, cell) for k, cs in missing.items() for cell in sorted(cs)]
        if todo:   # second pass: the whole column of each missed cell
            cols: dict[tuple[str, int], list[np.ndarray]] = {kc: [] for kc in todo}
            for chunk in rerun():
                for k, cell in todo:
                    cols[k, cell].append(chunk[k].reshape(len(chunk[k]), -1)[:, cell].copy())
            for (k, cell), col in cols.items():
                out[k][:, cell] = np.percentile(np.concatenate(col).astype(float),
                                                self.q_percent)
        return {k: (v if k == "edge_miss_fraction" else v.reshape((len(self.q), *shapes[k])))
                for k, v in out.items()}


@contextlib.contextmanager
def _warnings_off():
    """No RuntimeWarning from an all-NaN pilot column (its window does not matter)."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        yield


def _chunks(samples: int, chunk_size: int) -> list[int]:
    n_full, rest = divmod(samples, chunk_size)
    return [chunk_size] * n_full + ([rest] if rest else [])


def monte_carlo(
    design: Design,
    tolerance: ToleranceSpec | None = None,
    *,
    samples: int | None = None,
    seed: int | None = None,
    chunk_size: int | None = None,
    ranges_m: ArrayLike | None = None,
    workers: int | None = None,
    scheduler: str | None = None,
    client: Any = None,
    processes: bool = True,
    progress: Callable[[int, int], None] | None = None,
    keep_samples: bool = True,
) -> ToleranceResult:
    """Sample mounting errors and evaluate every mirror's beams, chunk by chunk.

    Parameters
    ----------
    design : Design
    tolerance : ToleranceSpec, optional
        Default: the design file's ``[tolerance]`` table (defaults if absent).
    samples, seed, chunk_size, ranges_m : optional
        Override the spec's values.
    workers : int, optional
        ``0``: run in this process (no Dask). ``n >= 1``: a
        ``distributed.LocalCluster(n_workers=n, processes=processes)`` started for this
        run. Default (:func:`runner_for`): in process up to :data:`DASK_MIN_SAMPLES`
        samples, else a local cluster with one worker per CPU - and in process on a
        single CPU, where a cluster cannot pay.
    scheduler : str, optional
        Address of an existing Dask scheduler to run on instead.
    client : distributed.Client, optional
        An existing client to run on instead.
    processes : bool
        Worker processes (True) or threads (False) for a local cluster.
    progress : callable, optional
        Called as ``progress(done_samples, total_samples)`` after each chunk.
    keep_samples : bool
        False: keep only the spec's percentiles of :data:`SUMMARY_METRICS` and the
        edge-miss fraction (what :meth:`ToleranceResult.table` shows), exact, without a
        row per sample (:class:`_Summary`); memory then hardly grows with ``samples``.

    Returns
    -------
    ToleranceResult
        Identical for a given (seed, chunk_size, samples) whatever runs it.
    """
    tol = tolerance if tolerance is not None else tolerance_spec(design.spec)
    changes = {k: v for k, v in (("samples", samples), ("seed", seed), ("chunk_size", chunk_size),
                                 ("ranges_m", ranges_m)) if v is not None}
    if changes:
        tol = tol.replace(**changes)
    if workers is not None:
        require(isinstance(workers, int) and workers >= 0, "workers", workers, "an integer >= 0")
    prob = _problem(design, tol)
    m, r = len(prob.mirrors), len(prob.ranges)
    sizes = _chunks(tol.samples, tol.chunk_size)
    starts = np.concatenate([[0], np.cumsum(sizes)]).astype(int)
    seeds = np.random.SeedSequence(tol.seed).spawn(len(sizes))
    t_start = time.perf_counter()
    timings: dict[str, float] = {}
    runner = runner_for(tol.samples, workers=workers, scheduler=scheduler, client=client)
    # preallocated: each chunk writes (or is copied) into its rows, nothing is concatenated;
    # without samples one chunk's rows are reused and folded into the summary
    keys = tuple(_ARRAYS) if keep_samples else (*SUMMARY_METRICS, "edge_misses")
    arrays = _empty(tuple(_ARRAYS), tol.samples if keep_samples else 0, m, r)
    summ = None if keep_samples else _Summary(tol.percentiles, tol.samples, m)
    buf = None if keep_samples else _empty(keys, tol.chunk_size, m, r)

    def rows(i: int) -> dict[str, np.ndarray]:
        if buf is None:
            return {k: v[starts[i]:starts[i + 1]] for k, v in arrays.items()}
        return {k: v[:sizes[i]] for k, v in buf.items()}

    done = 0
    if runner == "in-process":
        for i, (n, s) in enumerate(zip(sizes, seeds, strict=True)):
            out = _run_chunk(prob, n, s, out=rows(i))
            if summ is not None:
                summ.add(out)
            done += n
            if progress:
                progress(done, tol.samples)
    else:
        got = np.zeros(len(sizes), bool)
        for i, res in _dask_chunks(prob, sizes, seeds, workers=workers, scheduler=scheduler,
                                   client=client, processes=processes, keys=keys,
                                   timings=timings):
            if summ is not None:
                summ.add(res)
            else:
                for k, v in rows(i).items():
                    v[...] = res[k]
            got[i] = True
            done += sizes[i]
            if progress:
                progress(done, tol.samples)
        assert got.all()  # every chunk came back (a failed one raised above)
    summary: dict[str, np.ndarray] = {}
    if summ is not None:
        def rerun() -> Iterator[dict[str, np.ndarray]]:   # in process: rare, and exact
            for i, (n, s) in enumerate(zip(sizes, seeds, strict=True)):
                yield _run_chunk(prob, n, s, out=rows(i))

        summary = summ.finish(rerun, {k: (m, r) if _ARRAYS[k][1] else (m,)
                                      for k in SUMMARY_METRICS})
    return ToleranceResult(design_name=design.spec.name, tolerance=tol, mirror_names=prob.names,
                           ranges_m=prob.ranges, seed=tol.seed, chunk_size=tol.chunk_size,
                           n_samples=tol.samples, **arrays, samples_kept=keep_samples,
                           summary=summary, runner=runner,
                           wall_s=time.perf_counter() - t_start,
                           startup_s=timings.get("startup_s", 0.0))


#: Default of :func:`monte_carlo` (``workers=None``): runs of more samples than this go to
#: a local Dask cluster. Measured (benchmarks/bench_tolerance.py, docs/benchmarks.md; 2 CPUs
#: shared with other jobs): a local cluster of 2 worker processes starts in 1.8-4.4 s; this
#: process runs the fused kernel at ~13 500 samples/s of CPU (paper build, 4 arcs), 5 700-
#: 9 600 samples/s of wall time under that load, the 2 workers 4 200-13 500 samples/s.
#: Break-even ``N = S r0 / (1 - r0 / r2)``: 17 500, 94 000 and twice never (Dask slower) in
#: four runs; with both cores free (r2 ~ 1.8 r0, S ~ 2.3 s) ~70 000. Below 100 000 samples
#: (~7.5 s in process) a cluster rarely pays. Was 20 000 with the old, 8x slower kernel.
DASK_MIN_SAMPLES = 100_000


def runner_for(samples: int, *, workers: int | None = None, scheduler: str | None = None,
               client: Any = None) -> str:
    """What :func:`monte_carlo` runs ``samples`` on: ``"in-process"`` or ``"dask"``.

    Dask when asked for (a client, a scheduler, ``workers >= 1``); with ``workers=None``
    only above :data:`DASK_MIN_SAMPLES` and with more than one CPU (one worker process
    on one CPU is the in-process rate plus the cluster's start-up).
    """
    if client is not None or scheduler is not None or (workers is not None and workers > 0):
        return "dask"
    if workers is None and samples > DASK_MIN_SAMPLES and (os.cpu_count() or 1) > 1:
        return "dask"
    return "in-process"


#: Environment variables Dask's nanny sets in worker processes that we leave unset.
#: ``MALLOC_TRIM_THRESHOLD_=65536`` pins glibc's mmap threshold at 128 KiB, so every
#: temporary array of a chunk (a few MB each) is mmap'ed and page-faulted afresh: a
#: worker then ran a chunk 1.6x slower than this process did (0.52 s vs 0.31 s per 1000
#: samples, benchmarks/bench_tolerance.py). Chunks are small and short-lived, so the
#: memory the setting would hand back is not worth it.
_UNSET_WORKER_ENV = ("MALLOC_TRIM_THRESHOLD_",)


def _local_cluster(n_workers: int, processes: bool):
    """A quiet ``distributed.LocalCluster`` of single-threaded workers for :func:`monte_carlo`."""
    import logging

    import dask
    from distributed import LocalCluster

    env = {k: v for k, v in dask.config.get("distributed.nanny.pre-spawn-environ", {}).items()
           if k not in _UNSET_WORKER_ENV}
    with dask.config.set({"distributed.nanny.pre-spawn-environ": env}), _workers_ignore_sigint():
        # loopback only: dashboard_address=None still served HTTP on *:8787 (and warned
        # when another cluster had that port)
        # (threads, processes=False, talk in-process: no host to bind)
        net = {"host": "127.0.0.1", "worker_dashboard_address": "127.0.0.1:0"} if processes else {}
        # silence_logs=CRITICAL: a chunk's error reaches us through its future anyway, and on
        # Ctrl-C workers logged ERRORs about data released under them ("Could not find data")
        return LocalCluster(n_workers=n_workers, processes=processes, threads_per_worker=1,
                            dashboard_address="127.0.0.1:0", silence_logs=logging.CRITICAL, **net)


@contextlib.contextmanager
def _workers_ignore_sigint():
    """Worker processes started inside this block ignore SIGINT.

    Ctrl-C reaches the whole foreground process group: each worker then printed its own
    ``KeyboardInterrupt`` traceback while this process was already shutting the cluster
    down. An ignored signal stays ignored across fork/exec (Python installs its SIGINT
    handler only where SIGINT is not ignored), so the workers leave the interrupt to us
    and are stopped by ``cluster.close()``. A Ctrl-C during the few seconds of start-up
    is ignored too. Only the main thread may change handlers; from other threads nothing
    changes (and no Ctrl-C arrives there).
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old)


#: How long to wait for a Dask scheduler to accept a connection and greet [s].
SCHEDULER_TIMEOUT_S = 5.0


def check_scheduler(address: Any, timeout_s: float = SCHEDULER_TIMEOUT_S) -> None:
    """Refuse, within about ``timeout_s``, a scheduler address that is malformed, not
    reachable or not a Dask scheduler.

    A Dask scheduler speaks first: right after a TCP connect it sends its handshake, a
    frame with an 8-byte little-endian length. Anything else (an HTTP server waits for a
    request and Dask's own connect would then wait forever) is refused.
    """
    import socket
    import struct

    allowed = "the address of a running Dask scheduler, e.g. tcp://host:8786"
    if not isinstance(address, str) or not address.strip():
        raise ParameterError("scheduler", address, allowed)
    from distributed.comm.addressing import parse_address, parse_host_port

    try:
        scheme, loc = parse_address(address, strict=False)
        if scheme not in ("tcp", "tls", "inproc", "ucx", "ws", "wss"):
            raise ValueError(f"unknown scheme {scheme!r}")
        if scheme == "inproc":
            return
        host, port = parse_host_port(loc)
    except (ValueError, TypeError) as exc:
        raise ParameterError("scheduler", address, f"{allowed} ({exc})") from None
    if scheme != "tcp":
        return  # encrypted or other transports: leave the handshake to Dask (with its timeout)
    try:
        with socket.create_connection((host, port), timeout=timeout_s) as sock:
            sock.settimeout(timeout_s)
            head = b""
            while len(head) < 8:
                chunk = sock.recv(8 - len(head))
                if not chunk:
                    break
                head += chunk
    except TimeoutError:
        raise ParameterError("scheduler", address, f"{allowed} (no answer within "
                                                   f"{timeout_s:g} s)") from None
    except OSError as exc:
        raise ParameterError("scheduler", address,
                             f"{allowed} ({exc.strerror or exc})") from None
    if len(head) < 8 or struct.unpack("<Q", head)[0] > (1 << 20):
        raise ParameterError("scheduler", address, f"{allowed} (something else answers there)")


#: The old private name (commands imported it before it was public).
_check_scheduler = check_scheduler


def _dask_chunks(prob, sizes, seeds, *, workers, scheduler, client, processes,
                 keys=tuple(_ARRAYS), timings=None):
    """Yield ``(chunk index, result)`` as chunks finish on a Dask cluster (each result the
    arrays ``keys`` of :func:`_run_chunk`)."""
    yield from dask_map(_run_chunk, prob, [(n, s, None, keys) for n, s in
                                           zip(sizes, seeds, strict=True)], workers=workers,
                        scheduler=scheduler, client=client, processes=processes, timings=timings)


def dask_map(fn: Callable[..., Any], shared: Any, args: Sequence[tuple[Any, ...]], *,
             workers: int | None = None, scheduler: str | None = None, client: Any = None,
             processes: bool = True,
             timings: dict[str, float] | None = None) -> Iterator[tuple[int, Any]]:
    """Yield ``(i, fn(shared, *args[i]))`` as the tasks finish on a Dask cluster.

    The cluster is the caller's ``client``, or an existing ``scheduler`` (its address
    checked first, so a wrong one is one line, not a hang), or a local cluster of
    ``workers`` started here; what is started here is closed here, also when the caller
    stops early or Ctrl-C arrives (quietly: the one-line reason is the exception raised).
    ``shared`` is scattered once to every worker. Used by the Monte Carlo and by
    :mod:`nodlidar.analysis.explore`. ``timings``, if given, receives ``startup_s``: the
    wall time until the cluster holds ``shared`` and the tasks are submitted [s].
    """
    from distributed import Client, as_completed

    own_cluster = own_client = None
    futures: dict = {}
    interrupted = False
    t0 = time.perf_counter()
    try:
        if client is None:
            if scheduler is not None:
                check_scheduler(scheduler)
                try:
                    client = own_client = Client(scheduler, timeout=SCHEDULER_TIMEOUT_S)
                except (OSError, TimeoutError) as exc:  # CommClosedError is an OSError
                    raise ParameterError("scheduler", scheduler,
                                         f"a running Dask scheduler ({str(exc).splitlines()[0]})") from None
            else:
                n = workers or min(os.cpu_count() or 1, 8)
                own_cluster = _local_cluster(n, processes)
                client = own_client = Client(own_cluster)
        shared_f = client.scatter(shared, broadcast=True)
        futures = {client.submit(fn, shared_f, *a, pure=False): i for i, a in enumerate(args)}
        if timings is not None:
            timings["startup_s"] = time.perf_counter() - t0
        for fut in as_completed(futures):
            i = futures[fut]
            yield i, fut.result()
            fut.release()
    except BaseException:  # Ctrl-C, a failed task, the caller stopping early
        interrupted = True
        raise
    finally:
        # Torn down mid-run, the in-process scheduler logs a CRITICAL traceback for every
        # task it can no longer report to the closed client: cancel first and keep Dask
        # quiet while closing.
        with _logging_disabled() if interrupted else contextlib.nullcontext():
            if interrupted and client is not None and futures:
                with contextlib.suppress(Exception):
                    client.cancel(list(futures))
            if own_client is not None:
                own_client.close()
            if own_cluster is not None:
                own_cluster.close()


@contextlib.contextmanager
def _logging_disabled():
    """All logging off inside the block (restored after)."""
    import logging

    old = logging.root.manager.disable
    logging.disable(logging.CRITICAL)
    try:
        yield
    finally:
        logging.disable(old)


# ---------------------------------------------------------------------------------------
# sensitivities


def _bearing_at(patch: MirrorPatch, theta: np.ndarray, D: float) -> np.ndarray:
    _, hit, out = reflect_rays(np.zeros((len(theta), 3)), directions_from_bearings(theta),
                               patch.origin_, patch.normal_)
    return bearing_of(arc_point(hit, out, D))


@dataclass(frozen=True, eq=False)
class SensitivityResult:
    """d(bearing at D)/d(parameter), per mirror and beam.

    Attributes
    ----------
    design_name : str
    design_distance_m : float
    mirror_names : tuple of str
    steps : dict name -> (b,) int
    finite_difference : dict name -> dict parameter -> (b,) float
        Central differences through :meth:`MirrorPatch.perturbed` / ``transformed`` and
        the exact trace [rad per rad, rad per m].
    closed_form : dict name -> dict parameter -> (b,) float
        From eq. 1 differentiated analytically (NaN where there is none: lidar pitch and
        roll, which to first order only tilt beams out of the scan plane).
    """

    design_name: str
    design_distance_m: float
    mirror_names: tuple[str, ...]
    steps: dict[str, np.ndarray]
    finite_difference: dict[str, dict[str, np.ndarray]]
    closed_form: dict[str, dict[str, np.ndarray]]

    def table(self) -> list[dict[str, Any]]:
        """Rows (mirror, parameter): mean/min/max over beams in deg per deg or deg per mm."""
        rows = []
        for name in self.mirror_names:
            for p, unit in PARAMETERS.items():
                fd = self.finite_difference[name][p]
                cf = self.closed_form[name][p]
                scale = 1.0 if unit == "rad" else 1e-3   # per m -> per mm
                conv = np.degrees(fd * scale) if unit == "m" else fd
                rows.append({
                    "mirror": name, "parameter": p,
                    "unit": "deg/deg" if unit == "rad" else "deg/mm",
                    "mean": float(np.mean(conv)), "min": float(np.min(conv)),
                    "max": float(np.max(conv)),
                    "closed_form_max_diff": (float(np.max(np.abs(cf - fd)) * (
                        np.degrees(scale) if unit == "m" else 1.0))
                        if np.all(np.isfinite(cf)) else None),
                })
        return rows


def sensitivities(design: Design, D: float | None = None, h_rad: float = 1e-6,
                  h_m: float = 1e-6) -> SensitivityResult:
    """Sensitivity of every reflected beam's bearing at D to each mounting parameter.

    Finite differences are central, with steps ``h_rad`` / ``h_m`` (truncation error
    ``O(h^2)`` ~ 1e-12, round-off ~ 1e-16/h ~ 1e-10 relative). The closed forms come from
    eq. 1, ``b = theta_b + s (2 theta_r + asin(OZ sin 2theta_r / D) - pi)``:

    * ``dd``: theta_r fixed, ``OZ`` grows by ``dd / cos theta_r``, so
      ``db/dd = 2 s sin(theta_r) / AM`` (``AM = sqrt(D^2 - OA^2)``);
    * ``dalpha``: the mirror turns about O: ``d theta_r / dalpha`` from the normal,
      ``OZ = d / cos theta_r`` with ``d`` fixed;
    * ``dbeta``: to first order the tilt about a hinge at height ``h`` moves the mirror
      along its outward normal by ``h * dbeta`` (the out-of-plane turn is second order):
      ``db/dbeta = h * db/dd``;
    * lidar yaw = minus dalpha; lidar x/y offset = minus the normal's x/y times ``db/dd``.
    """
    D = float(design.design_distance_m if D is None else D)
    lid = design.lidar
    fd_all, cf_all, steps = {}, {}, {}
    for m in design.mirrors:
        th = lid.bearing_from_step(m.steps)
        steps[m.name] = m.steps.copy()
        patch = m.patch

        def b_pert(k: int, h: float, patch=patch, th=th) -> np.ndarray:
            a = np.zeros(3)
            a[k] = h
            return _bearing_at(patch.perturbed(Perturbation.from_array(a)), th, D)

        def b_mount(k: int, h: float, patch=patch, th=th) -> np.ndarray:
            a = np.zeros(6)
            a[k] = h
            mnt = LidarMount.from_array(a)
            R = mnt.rotation()
            return _bearing_at(patch.transformed(R.T, -R.T @ np.asarray(mnt.offset)), th, D)

        fd = {}
        for k, p in enumerate(("dalpha", "dbeta", "dd")):
            h = h_m if p == "dd" else h_rad
            fd[p] = wrap_angle(b_pert(k, h) - b_pert(k, -h)) / (2 * h)
        for k, p in ((0, "lidar_yaw"), (1, "lidar_pitch"), (5, "lidar_roll"), (2, "lidar_x"),
                     (3, "lidar_y")):
            h = h_m if p in ("lidar_x", "lidar_y") else h_rad
            fd[p] = wrap_angle(b_mount(k, h) - b_mount(k, -h)) / (2 * h)
        # closed forms from eq. 1
        n = patch.normal_
        n_out = n if patch.origin_ @ n > 0 else -n
        u = directions_from_bearings(th)
        un = u @ n
        theta_r = incidence_angle(u, n)
        oz = patch.standoff / np.cos(theta_r)
        oa = oz * np.sin(2 * theta_r)
        am = np.sqrt(D**2 - oa**2)
        s = m.sign
        db_doz = s * np.sin(2 * theta_r) / am
        db_dthr = s * (2 + 2 * oz * np.cos(2 * theta_r) / am)
        db_dd = db_doz / np.cos(theta_r)
        dthr_dalpha = -np.sign(un) * (u @ np.cross(EZ, n)) / np.sin(theta_r)
        db_dalpha = (db_dthr + db_doz * oz * np.tan(theta_r)) * dthr_dalpha
        cf = {"dalpha": db_dalpha, "dbeta": patch.hinge_z * db_dd, "dd": db_dd,
              "lidar_yaw": -db_dalpha, "lidar_pitch": np.full_like(th, np.nan),
              "lidar_roll": np.full_like(th, np.nan),
              "lidar_x": -n_out[0] * db_dd, "lidar_y": -n_out[1] * db_dd}
        fd_all[m.name], cf_all[m.name] = fd, cf
    return SensitivityResult(design_name=design.spec.name, design_distance_m=D,
                             mirror_names=tuple(m.name for m in design.mirrors), steps=steps,
                             finite_difference=fd_all, closed_form=cf_all)
