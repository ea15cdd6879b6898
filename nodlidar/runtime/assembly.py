"""3D assembly: scans + actuator samples + the design's BeamModels -> a point cloud.

Every beam of many scans goes through one compiled per-point kernel
(:func:`nodlidar.runtime._assembly_kernel.assemble_points`, numba, loaded by the first
assembly and not by importing this module); this module validates the inputs, builds the
per-step and per-keyframe tables it reads and the :class:`PointCloud`. Per beam:

* each beam's time is its scan's time (SCIP step 0) + its step offset
  (:meth:`LidarModel.beam_time_s`, the one place that convention lives);
* its nod angle is interpolated from the nod servo's timestamped samples;
* the state of its mirror's side at that time (deployed / lifted / in between, from the
  lift servo samples against :class:`MirrorLiftProfile`) decides whether the beam was
  reflected: deployed -> the deployed :class:`BeamModel`, lifted -> the lifted one (the
  beam goes straight), in between -> the point is dropped and counted (the glass was
  moving; its geometry is unknown);
* error codes (NaN ranges) are filtered out;
* points are given in the sensor frame, or mapped to the robot frame with
  ``robot_from_sensor`` and the world frame with ``world_from_robot`` poses over time (per
  point by its own time). Transforms are named ``<to>_from_<from>``: ``robot_from_sensor``
  maps coordinates in the sensor frame into the robot frame (:mod:`nodlidar.frames`,
  docs/conventions.md); each is checked by :func:`nodlidar.frames.check_transform`.

Times are in whatever clock the scan times and the actuator samples share (the driver's
``Scan.stamp_s`` after :meth:`UrgDriver.sync_clock` with the actuators' time source).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from functools import cached_property
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
from numpy.typing import ArrayLike

from ..beams import DIRECT, BeamColumns, BeamModel  # noqa: F401  (BeamModel: type of fields)
from ..dynamixel import RAD_PER_TICK
from ..errors import ParameterError, require
from ..frames import RENAMED, check_transform, refuse_renamed, renamed_hint
from ..geometry import CLEAR, TOL, rotate_about_axis
from .servo_angles import MirrorLiftProfile, lift_profiles

if TYPE_CHECKING:
    from ..geometry import Perturbation
    from ..lidar import LidarModel
    from ..solver import Design

__all__ = ["FRAMES", "PointCloud", "ScanBatch", "AngleSamples", "PoseTrack", "AssemblyModel",
           "AssemblyStats", "assemble", "warm_up", "DEPLOYED", "LIFTED", "BETWEEN",
           "mirror_state"]

FRAMES = ("sensor", "robot", "world")
#: What :func:`~nodlidar.runtime.servo_angles.interpolate_angle` does outside the samples.
Outside = Literal["nan", "clamp", "extrapolate"]
DEPLOYED, LIFTED, BETWEEN = 0, 1, 2

# Default: within 3 servo ticks (4.6 mrad) of an end position counts as there, like
# MirrorLift's arrival tolerance; a lift fraction of 0.3 % tilts a reflected beam by a few
# mrad at most (2 x 0.003 x lift angle), below the URG's beam divergence.
LIFT_TOLERANCE_RAD = 3 * RAD_PER_TICK


def _plain(a: Any, dtype: Any = float) -> np.ndarray:
    """``a`` as a C-contiguous, writeable array of ``dtype``: the one array type per
    argument the compiled kernels are compiled (and cached) for. A strided or read-only
    array (a view, ``np.broadcast_to``, a buffer) would be a new numba signature: another
    compilation in the middle of a run. Copies only such arrays."""
    out = np.ascontiguousarray(a, dtype=dtype)
    return out if out.flags.writeable else out.copy()


@dataclass(frozen=True, eq=False)
class PointCloud:
    """Points with per-point provenance. All arrays have length ``n``.

    Attributes
    ----------
    xyz : (n, 3) float
        Points [m] in :attr:`frame`.
    t : (n,) float
        Time of each beam [s].
    step : (n,) int
        Lidar step.
    mirror : (n,) int
        Mirror index (into :attr:`mirror_names`) the beam reflected off, -1 direct.
    scan : (n,) int
        Index of the scan the point came from (in the assembled batch / recording).
    range_m : (n,) float
        Range (total path length) [m]; with a calibrated range model, the corrected one.
    frame : str
        ``"sensor"``, ``"robot"`` or ``"world"``.
    design_name, design_hash : str
        The design whose BeamModel made the points.
    calibration_id : str
        Calibration applied, ``"none"`` if none.
    mirror_names : tuple of str
    meta : dict
        Extra counters (e.g. beams dropped while a mirror moved).
    nod_rad : (n,) float or None
        Head pitch at each beam's time [rad], as the assembly interpolated it (None for a
        cloud read from a file).
    lifted : (n,) bool or None
        The beam's mirror side was lifted (it was projected as a direct beam although its
        step lies in a reflected window); None for a cloud read from a file.
    """

    xyz: np.ndarray
    t: np.ndarray
    step: np.ndarray
    mirror: np.ndarray
    scan: np.ndarray
    range_m: np.ndarray
    frame: str = "sensor"
    design_name: str = ""
    design_hash: str = ""
    calibration_id: str = "none"
    mirror_names: tuple[str, ...] = ()
    meta: Mapping[str, Any] = field(default_factory=dict)
    nod_rad: np.ndarray | None = None
    lifted: np.ndarray | None = None

    def __post_init__(self) -> None:
        n = len(self.t)
        require(np.shape(self.xyz) == (n, 3), "cloud.xyz.shape", np.shape(self.xyz), f"({n}, 3)")
        for name in ("step", "mirror", "scan", "range_m", "nod_rad", "lifted"):
            a = getattr(self, name)
            if a is not None:
                require(np.shape(a) == (n,), f"cloud.{name}.shape", np.shape(a), f"({n},)")
        require(self.frame in FRAMES, "cloud.frame", self.frame, ", ".join(FRAMES))

    def __len__(self) -> int:
        return len(self.t)

    def select(self, mask: np.ndarray) -> PointCloud:
        """The points where ``mask`` (n,) bool (or an index array) holds."""
        def opt(a):
            return None if a is None else a[mask]

        return PointCloud(self.xyz[mask], self.t[mask], self.step[mask], self.mirror[mask],
                          self.scan[mask], self.range_m[mask], self.frame, self.design_name,
                          self.design_hash, self.calibration_id, self.mirror_names, dict(self.meta),
                          opt(self.nod_rad), opt(self.lifted))

    def with_xyz(self, xyz: np.ndarray, frame: str) -> PointCloud:
        """Same points expressed in another frame."""
        return PointCloud(np.asarray(xyz, dtype=float), self.t, self.step, self.mirror, self.scan,
                          self.range_m, frame, self.design_name, self.design_hash,
                          self.calibration_id, self.mirror_names, dict(self.meta), self.nod_rad,
                          self.lifted)


@dataclass(frozen=True, eq=False)
class ScanBatch:
    """Many scans flattened into one set of beams.

    Attributes
    ----------
    steps : (N,) int
        Step of each value.
    ranges_m : (N,) float
        Range [m]; NaN = error code / no return.
    scan : (N,) int
        Index into :attr:`scan_time_s` of each value.
    scan_time_s : (m,) float
        Time of each scan's step 0 [s] (the SCIP timestamp convention).
    """

    steps: np.ndarray
    ranges_m: np.ndarray
    scan: np.ndarray
    scan_time_s: np.ndarray

    @classmethod
    def from_arrays(cls, steps: ArrayLike, ranges_m: ArrayLike,
                    scan_time_s: ArrayLike) -> ScanBatch:
        """From ``(m, n)`` ranges of ``m`` scans sharing the ``(n,)`` steps."""
        r = np.atleast_2d(np.asarray(ranges_m, dtype=float))
        st = np.asarray(steps)
        ts = np.atleast_1d(np.asarray(scan_time_s, dtype=float))
        require(r.shape[1:] == st.shape, "ranges_m.shape", r.shape, f"(m, {st.shape[0]})")
        require(ts.shape == (r.shape[0],), "scan_time_s.shape", ts.shape, f"({r.shape[0]},)")
        m, n = r.shape
        return cls(np.tile(st, m), r.ravel(), np.repeat(np.arange(m), n), ts)

    @classmethod
    def from_scans(cls, scans: Sequence, times: Sequence[float] | None = None) -> ScanBatch:
        """From driver :class:`~nodlidar.runtime.urg.Scan` objects (or anything with
        ``steps``, ``ranges_m`` and ``stamp_s``); ``times`` [s] overrides the stamps."""
        require(len(scans) > 0, "scans", "[]", "at least one scan")
        ts = (np.array([s.stamp_s for s in scans], dtype=float) if times is None
              else np.asarray(times, dtype=float))
        require(ts.shape == (len(scans),), "times.shape", ts.shape, f"({len(scans)},)")
        counts = [len(s.steps) for s in scans]
        return cls(np.concatenate([np.asarray(s.steps) for s in scans]),
                   np.concatenate([np.asarray(s.ranges_m, dtype=float) for s in scans]),
                   np.repeat(np.arange(len(scans)), counts), ts)


@dataclass(frozen=True, eq=False)
class AngleSamples:
    """Timestamped angle samples of one servo: ``t_s`` (k,) [s] increasing, ``angle_rad``
    (k,) [rad]."""

    t_s: np.ndarray
    angle_rad: np.ndarray

    @classmethod
    def of(cls, samples: Any) -> AngleSamples:
        """From a :class:`~nodlidar.runtime.actuators.Samples` (host_time_s, angle_rad), a
        ``(t, angle)`` pair, or an AngleSamples. Duplicate times (two READs in the same
        clock tick) keep the first sample, so the times are strictly increasing."""
        if isinstance(samples, AngleSamples):
            return samples
        if hasattr(samples, "host_time_s"):
            t, a = samples.host_time_s, samples.angle_rad
        else:
            t, a = samples
        t = np.asarray(t, dtype=float)
        a = np.asarray(a, dtype=float)
        require(t.shape == a.shape and t.ndim == 1, "samples.shape", (t.shape, a.shape),
                "two (k,) arrays")
        if t.size < 2 or bool(np.all(t[1:] > t[:-1])):  # already strictly increasing:
            return cls(t.copy(), a.copy())  # no sort (its own arrays, as after one)
        order = np.argsort(t, kind="stable")
        t, a = t[order], a[order]
        keep = np.concatenate([[True], np.diff(t) > 0]) if t.size else np.zeros(0, bool)
        return cls(t[keep], a[keep])

    def at(self, t: ArrayLike, outside: Outside = "nan") -> np.ndarray:
        """Linearly interpolated angle [rad] at times ``t`` [s] (any shape); NaN outside
        the samples (or the end sample's angle, or extrapolated: ``outside``, as
        :func:`~nodlidar.runtime.servo_angles.interpolate_angle`). The interpolation
        :func:`assemble` applies per beam (the compiled kernel's ``interp_angles``)."""
        from ._assembly_kernel import CLAMP, EXTRAPOLATE, NAN, interp_angles

        modes = {"nan": NAN, "clamp": CLAMP, "extrapolate": EXTRAPOLATE}
        require(outside in modes, "outside", outside, "'nan', 'clamp' or 'extrapolate'")
        n_min = 2 if outside == "extrapolate" else 1
        require(self.t_s.size >= n_min, "samples", self.t_s.size, f">= {n_min} samples")
        q = np.asarray(t, dtype=float)
        out = np.empty(q.shape)
        interp_angles(_plain(self.t_s), _plain(self.angle_rad), _plain(q).reshape(-1),
                      modes[outside], out.reshape(-1))
        return out


@dataclass(frozen=True, eq=False, init=False)
class PoseTrack:
    """Robot poses over time: ``world_from_robot`` (k, 4, 4) at increasing ``t_s`` (k,) [s]
    (each maps robot coordinates into the world frame; checked by
    :func:`~nodlidar.frames.check_transform`).

    Interpolated per query time: translation linearly, rotation by slerp; clamped outside.
    The old keyword ``world2robot`` is refused with a hint (``TypeError``), the old
    attribute with one (``AttributeError``).
    """

    t_s: np.ndarray
    world_from_robot: np.ndarray

    def __init__(self, t_s: Any, world_from_robot: Any = None, **renamed: Any) -> None:
        refuse_renamed(renamed, "PoseTrack")
        if world_from_robot is None:
            raise TypeError("PoseTrack() missing 1 required argument: 'world_from_robot'")
        object.__setattr__(self, "t_s", t_s)
        object.__setattr__(self, "world_from_robot", world_from_robot)
        self.__post_init__()

    def __getattr__(self, name: str) -> Any:
        # called only for attributes that do not exist: the old name gets the hint
        if name in RENAMED:
            raise AttributeError(f"PoseTrack has no attribute {name!r}: {renamed_hint(name)}")
        raise AttributeError(f"'PoseTrack' object has no attribute {name!r}")

    def __post_init__(self) -> None:
        t = np.asarray(self.t_s, float)
        T = check_transform(self.world_from_robot, "world_from_robot", stack=True)
        require(t.shape == (T.shape[0],), "poses.shape", (t.shape, T.shape),
                "(k,) times and (k, 4, 4) transforms")
        require(t.size >= 1 and bool(np.all(np.diff(t) > 0)), "poses.t_s", "not increasing",
                "strictly increasing times")

    def at(self, t: np.ndarray) -> np.ndarray:
        """``(n, 4, 4)`` world_from_robot at times ``t`` (n,) [s].

        Slerp written out (``R_i exp(f w_i)``, ``w_i`` the rotation vector from pose i to
        i+1, :func:`~nodlidar.geometry.rotate_about_axis` with one axis per point): scipy's
        per-point Rotation products cost more than the rest of assembly together.
        """
        from scipy.spatial.transform import Rotation

        t = np.asarray(t, dtype=float)
        T = np.asarray(self.world_from_robot, float)
        ts = np.asarray(self.t_s, float)
        out = np.zeros((t.size, 4, 4))
        out[:, 3, 3] = 1.0
        if ts.size == 1:
            out[:] = T[0]
            return out
        tq = np.clip(t, ts[0], ts[-1])
        R = T[:, :3, :3]
        w = Rotation.from_matrix(np.einsum("kji,kjl->kil", R[:-1], R[1:])).as_rotvec()  # (k-1, 3)
        i = np.clip(np.searchsorted(ts, tq, side="right") - 1, 0, ts.size - 2)
        f = (tq - ts[i]) / (ts[i + 1] - ts[i])
        k, th = self._axis_angle(f[:, None] * w[i])
        # R_i exp(th [k]) = exp(th [R_i k]) R_i: each column of R_i turned about the world
        # axis R_i k (no batched 3x3 products); rows of the (n, 3, 3) stack = the columns
        Ri = R[i]
        k_world = Ri[:, :, 0] * k[:, :1] + Ri[:, :, 1] * k[:, 1:2] + Ri[:, :, 2] * k[:, 2:]
        cols = rotate_about_axis(Ri.transpose(0, 2, 1), k_world[:, None, :], th[:, None])
        out[:, :3, :3] = cols.transpose(0, 2, 1)
        for j in range(3):  # three columns, not a per-point loop
            out[:, j, 3] = np.interp(tq, ts, T[:, j, 3])
        return out

    def apply(self, t: np.ndarray, p: np.ndarray) -> np.ndarray:
        """Points ``p`` (n, 3) [m] in the robot frame at times ``t`` (n,) [s] -> world
        frame (n, 3): the same interpolated poses as :meth:`at`, applied per point by the
        compiled kernel :func:`~nodlidar.runtime._assembly_kernel.apply_poses` (the slerp
        :func:`assemble` applies) without building the (n, 4, 4) matrices."""
        from ._assembly_kernel import apply_poses

        t = _plain(t).reshape(-1)
        out = np.array(p, dtype=float, order="C")  # a copy: the kernel works in place
        require(out.shape == (t.size, 3), "p.shape", out.shape, f"({t.size}, 3)")
        apply_poses(_plain(self.t_s), self._segment_table, t, out)
        return out

    @cached_property
    def _segment_table(self) -> np.ndarray:
        """Per keyframe pair i -> i+1, the row the kernel reads for a point in it
        (``(max(k-1, 1), 19)`` float64, columns
        :data:`~nodlidar.runtime._assembly_kernel.SEG`): angle [rad] and unit axis of
        ``R_i^T R_(i+1)`` (zero axis below ``TOL.angle_rad``), ``R_i`` row-major, the
        translation ``p_i`` [m] and its change to the next keyframe [m]. One keyframe: its
        pose with no rotation or change (the slerp is then that constant transform)."""
        T = np.asarray(self.world_from_robot, float)
        R = T[:, :3, :3]
        n = max(len(T) - 1, 1)
        seg = np.zeros((n, 19))
        if len(T) > 1:
            from scipy.spatial.transform import Rotation

            w = Rotation.from_matrix(np.einsum("kji,kjl->kil", R[:-1], R[1:])).as_rotvec()
            k, th = self._axis_angle(w)
            seg[:, 0], seg[:, 1:4] = th, k
            seg[:, 16:19] = np.diff(T[:, :3, 3], axis=0)
        seg[:, 4:13] = R[:n].reshape(n, 9)
        seg[:, 13:16] = T[:n, :3, 3]
        return seg

    @staticmethod
    def _axis_angle(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rotation vectors ``v`` (n, 3) -> unit axes (n, 3) and angles (n,) [rad]; a
        rotation below ``TOL.angle_rad`` gets a zero axis (the identity either way)."""
        th = np.linalg.norm(v, axis=1)
        safe = np.where(th > TOL.angle_rad, th, 1.0)
        return v / safe[:, None], th


@dataclass(frozen=True, eq=False)
class AssemblyModel:
    """What assembly needs from a design: the deployed and the lifted BeamModel (with the
    calibration's perturbations, if any), each mirror's side, and the provenance.

    Attributes
    ----------
    deployed, lifted : BeamModel
    mirror_side : (n_mirrors,) int
        0 for left ("L") mirrors, 1 for right ("R").
    clear : (n_steps,) bool
        Deployed: the step's path is clean (False: its reflected ray runs into another
        mirror or the housing, so one reflection does not describe it; such points are
        dropped and counted as ``blocked``).
    design_name, design_hash, calibration_id : str
    range_offset_m, range_scale : float
        The lidar's calibrated range model ``r_measured = (1 + range_scale) r +
        range_offset_m`` [m, -]; :func:`assemble` inverts it before projecting (0, 0: none).
    lift_left, lift_right : MirrorLiftProfile
        The design's lift-servo profiles (:func:`~nodlidar.runtime.servo_angles.lift_profiles`):
        what :func:`assemble` uses when it is given none.
    """

    deployed: BeamModel
    lifted: BeamModel
    mirror_side: np.ndarray
    clear: np.ndarray
    design_name: str
    design_hash: str
    calibration_id: str = "none"
    range_offset_m: float = 0.0
    range_scale: float = 0.0
    lift_left: MirrorLiftProfile | None = None
    lift_right: MirrorLiftProfile | None = None

    @classmethod
    def from_design(cls, design: Design,
                    perturbations: Mapping[str, Perturbation] | None = None,
                    calibration_id: str = "none",
                    ambiguous_steps: Sequence[int] | None = None) -> AssemblyModel:
        """Build both BeamModels of a solved design (perturbed by a calibration).

        With perturbations, which mirror each beam reaches is re-traced through the
        perturbed finite patches (:func:`nodlidar.verify.verify`, first hit): a mirror
        turned by a few degrees takes beams the design gave to its neighbour or to no
        mirror, and the design's nominal assignment would misplace those points.

        ``ambiguous_steps`` (default: the calibration's, ``perturbations.ambiguous_steps``
        of a loaded calibration file): steps whose mirror is uncertain within the
        calibration's errors; they are not ``clear``, so their points are dropped (counted
        as ``blocked``) rather than put on a ray they may not have taken. A loaded
        calibration's range model (``perturbations.range_offset_m``/``range_scale``) is
        kept too.
        """
        from ..beams import BeamModel
        from ..calibration.fit import design_hash
        from ..verify import verify

        if ambiguous_steps is None:
            ambiguous_steps = getattr(perturbations, "ambiguous_steps", ())
        perts = dict(perturbations) if perturbations else None
        side = np.array([0 if m.side == "L" else 1 for m in design.mirrors], dtype=int)
        v = verify(design, perts)
        deployed = BeamModel.build(design.lidar, design.patches(perts), v.hit,
                                   design.spec.nod.pivot_m)
        clear = np.asarray(v.blocker == CLEAR)
        if len(ambiguous_steps):
            amb = np.asarray(ambiguous_steps, dtype=int)
            design.lidar.check_step(amb, "ambiguous_steps")
            clear = clear.copy()
            clear[amb - design.lidar.step_min] = False
        offset = float(getattr(perturbations, "range_offset_m", 0.0))
        scale = float(getattr(perturbations, "range_scale", 0.0))
        require(np.isfinite(offset) and abs(offset) < 1.0, "range_offset_m", offset,
                "a finite offset within +-1 m")
        require(np.isfinite(scale) and abs(scale) < 0.5, "range_scale", scale,
                "a finite scale error within +-0.5")
        return cls(deployed, design.beam_model(perts, mirrors_deployed=False), side,
                   clear, design.spec.name, design_hash(design.spec),
                   calibration_id if (perts or offset or scale) else "none", offset, scale,
                   *lift_profiles(design))

    @property
    def lidar(self) -> LidarModel:
        return self.deployed.lidar

    @cached_property
    def columns(self) -> BeamColumns:
        """Projection tables of both models (:class:`~nodlidar.beams.BeamColumns`): row
        ``i`` = step ``step_min + i`` deployed, row ``n_steps + i`` the same step lifted
        (a direct beam, mirror ``DIRECT``)."""
        n = self.lidar.n_steps
        return BeamColumns.concat(BeamColumns.of(self.deployed),
                                  BeamColumns.of(self.lifted, np.full(n, DIRECT)))

    @cached_property
    def kernel_tables(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """What the compiled kernel reads per step (built once per model): the rows of
        :attr:`columns` as a ``(2 n_steps, 13)`` float64 table (columns
        :data:`~nodlidar.runtime._assembly_kernel.ROW`, the pivot per row), their mirror
        indices (2 n_steps,) int16, and each step's time after step 0 [s] (n_steps,)
        (:meth:`LidarModel.beam_time_s`, the one place of that convention)."""
        c = self.columns
        m = len(c.ax)
        pv = np.broadcast_to(c.pivot, (m, 3))
        rows = np.column_stack([c.ax, c.ay, c.az, c.bx, c.by, c.bz, c.t_mirror, c.d0x, c.d0y,
                                c.d0z, pv[:, 0], pv[:, 1], pv[:, 2]]).astype(float, order="C")
        step_dt = _plain(self.lidar.beam_time_s(0.0, self.lidar.steps))
        return _plain(rows), _plain(c.mirror, np.int16), step_dt

    @cached_property
    def step_side(self) -> np.ndarray:
        """(n_steps,) int8: the side (0 left, 1 right) of each step's deployed mirror,
        -1 for a direct step."""
        m = self.deployed.mirror_of_step
        side = np.asarray(self.mirror_side, dtype=np.int8)
        return np.where(m == DIRECT, -1, side[np.maximum(m, 0)]).astype(np.int8)


@dataclass(frozen=True)
class AssemblyStats:
    """What assembly dropped, by reason (counts of beams)."""

    beams: int = 0
    error_codes: int = 0
    no_nod: int = 0
    mirror_moving: int = 0
    blocked: int = 0
    points: int = 0


def warm_up(model: AssemblyModel) -> None:
    """Compile (or load from numba's cache) the assembly kernel now, not at the first scan.

    numba compiles :func:`~nodlidar.runtime._assembly_kernel.assemble_points` at its first
    call: ~3-6 s the first time on a machine, ~0.3 s to load from the cache in a new
    process. Inside a live capture that stalls the loop that reads the lidar (a first
    recording on a fresh install dropped 62 of its first scans), so
    :meth:`~nodlidar.runtime.session.Session.open` calls this before streaming. Every
    argument of the kernel goes through :func:`_plain`, so one call compiles the only
    version later calls use (one scan of one beam, a fixed nod; the result is discarded).
    """
    lidar = model.lidar
    assemble(model, ScanBatch.from_arrays([lidar.step_min], [[1.0]], [0.0]), 0.0)


def mirror_state(angle_rad: ArrayLike, profile: MirrorLiftProfile,
                 tolerance_rad: float = LIFT_TOLERANCE_RAD) -> np.ndarray:
    """DEPLOYED / LIFTED / BETWEEN (int8, shape of ``angle_rad``) of lift-servo angles
    [rad]: within ``tolerance_rad`` of an end (the lifted band wins where both hold), NaN
    -> BETWEEN (unknown). The classification :func:`assemble` applies per beam (the
    compiled kernel's ``mirror_states``)."""
    from ._assembly_kernel import mirror_states

    a = _plain(angle_rad)
    out = np.empty(a.shape, dtype=np.int8)
    mirror_states(a.reshape(-1), float(profile.deployed_rad), float(profile.lifted_rad),
                  float(tolerance_rad), out.reshape(-1))
    return out


def _side_constant(samples: Any, t_range: tuple[float, float],
                   profile: MirrorLiftProfile | None, tol: float) -> int | None:
    """The state of one side if it is the same at every beam time in ``t_range`` (first,
    last) [s] (a string, or samples all well inside one end's band and spanning the
    range), else None."""
    if samples is None or isinstance(samples, str):
        st = samples or "deployed"
        require(st in ("deployed", "lifted"), "mirror state", st,
                "'deployed', 'lifted' or samples")
        return DEPLOYED if st == "deployed" else LIFTED
    # a hand-built AssemblyModel may carry no lift profile: say so rather than AttributeError
    require(profile is not None, "lift_left/lift_right", None,
            "a MirrorLiftProfile (the model has none) when lift-servo samples are given")
    assert profile is not None  # for the type checker; require() raised otherwise
    smp = AngleSamples.of(samples)
    uniform = _uniform_state(smp.angle_rad, profile, tol)
    if uniform is None or t_range[0] > t_range[1]:  # (an empty range: no beams)
        return uniform
    return uniform if smp.t_s[0] <= t_range[0] and t_range[1] <= smp.t_s[-1] else None


def _uniform_state(a: np.ndarray, profile: MirrorLiftProfile, tol: float) -> int | None:
    """DEPLOYED or LIFTED if every lift angle ``a`` (k,) [rad] is that state with a margin
    (1e-9 rad, far above the rounding of a linear interpolation) and the two end bands
    do not overlap; else None (interpolate every beam)."""
    margin = 1e-9
    if a.size == 0 or abs(profile.deployed_rad - profile.lifted_rad) <= 2 * tol + margin:
        return None
    for state, end in ((DEPLOYED, profile.deployed_rad), (LIFTED, profile.lifted_rad)):
        if float(np.max(np.abs(a - end))) <= tol - margin:
            return state
    return None


def assemble(model: AssemblyModel, scans: ScanBatch, nod: Any, *,
             mirror_left: Any = None, mirror_right: Any = None,
             lift_left: MirrorLiftProfile | None = None,
             lift_right: MirrorLiftProfile | None = None,
             lift_tolerance_rad: float = LIFT_TOLERANCE_RAD,
             frame: str = "sensor", robot_from_sensor: np.ndarray | None = None,
             world_from_robot: PoseTrack | Callable[[np.ndarray], np.ndarray] | np.ndarray
             | None = None,
             nod_outside: Outside = "nan", **renamed: Any) -> PointCloud:
    """Assemble scans into a point cloud.

    Parameters
    ----------
    model : AssemblyModel
        BeamModels (deployed and lifted) of the design, calibration applied.
    scans : ScanBatch
        All beams of the scans, with each scan's step-0 time [s].
    nod : AngleSamples, Samples, (t, angle) pair or float
        Nod servo samples (head pitch [rad] at times [s]); a float is a fixed pitch.
    mirror_left, mirror_right : samples, "deployed", "lifted" or None
        Lift-servo samples of each side (None = deployed throughout).
    lift_left, lift_right : MirrorLiftProfile
        Deployed/lifted servo angles of each side (default: the design's,
        ``model.lift_left`` / ``model.lift_right``).
    lift_tolerance_rad : float
        How close to an end angle counts as at it [rad].
    frame : {"sensor", "robot", "world"}
    robot_from_sensor : (4, 4) array
        Maps sensor coordinates into the robot frame (needed for robot and world); the
        sensor's pose on the robot.
    world_from_robot : PoseTrack, callable t (n,) -> (n, 4, 4), or (4, 4) array
        Robot pose(s) (maps robot coordinates into the world), evaluated per point time.
        Every transform is checked by :func:`~nodlidar.frames.check_transform` (rigid,
        no reflection). The old keywords ``robot2sensor``/``world2robot`` are refused
        with a hint (``TypeError``).
    nod_outside : {"nan", "clamp", "extrapolate"}
        Beams outside the nod samples' time span: dropped (default), or given the end
        sample's / extrapolated angle.

    Returns
    -------
    PointCloud
        Only valid points; ``meta`` holds the :class:`AssemblyStats` counts. Its arrays
        are the first ``n`` rows of buffers sized for every beam (the kernel writes the
        kept points compressed; the dropped beams' share stays allocated with them, copied
        out instead when more than half the beams were dropped).
    """
    refuse_renamed(renamed, "assemble")
    require(frame in FRAMES, "frame", frame, ", ".join(FRAMES))
    robot_T = np.eye(4)  # robot_from_sensor, checked before any work
    if frame in ("robot", "world"):
        require(robot_from_sensor is not None, "robot_from_sensor", None,
                f"a 4x4 transform for frame {frame!r}")
        robot_T = check_transform(robot_from_sensor, "robot_from_sensor")
    if frame == "world":
        require(world_from_robot is not None, "world_from_robot", None,
                "poses for frame 'world'")
    # the compiled kernel (numba) is loaded by the first assembly, not by importing this
    from . import _assembly_kernel as _kernel

    lidar = model.lidar
    steps = _plain(scans.steps, np.int64)
    r_all = _plain(scans.ranges_m)
    scan_i = _plain(scans.scan, np.int64)
    scan_time = _plain(scans.scan_time_s)
    n_beams = r_all.size
    require(steps.shape == r_all.shape == scan_i.shape and r_all.ndim == 1, "scans.shape",
            (steps.shape, r_all.shape, scan_i.shape), "three (N,) arrays")
    lidar.check_step(steps, "steps")
    if n_beams:  # the kernel reads scan_time[scan] unchecked
        require(int(scan_i.min()) >= 0 and int(scan_i.max()) < scan_time.size, "scans.scan",
                f"{int(scan_i.min())}..{int(scan_i.max())}", f"0..{scan_time.size - 1}")
    rows, row_mirror, step_dt = model.kernel_tables

    # the nod: samples (sorted, duplicates dropped) interpolated per beam by the kernel
    require(nod_outside in ("nan", "clamp", "extrapolate"), "nod_outside", nod_outside,
            "'nan', 'clamp' or 'extrapolate'")
    if isinstance(nod, (int, float)):
        nod_t, nod_a, nod_mode = np.zeros(1), np.array([float(nod)]), _kernel.CONSTANT
    else:
        smp = AngleSamples.of(nod)
        n_min = 2 if nod_outside == "extrapolate" else 1
        require(smp.t_s.size >= n_min, "nod samples", smp.t_s.size, f">= {n_min} samples")
        nod_t, nod_a = _plain(smp.t_s), _plain(smp.angle_rad)
        nod_mode = {"nan": _kernel.NAN, "clamp": _kernel.CLAMP,
                    "extrapolate": _kernel.EXTRAPOLATE}[nod_outside]

    # mirror state per side: constant over every beam time (no per-beam work), or from the
    # side's lift samples per beam (in the kernel). Any range holding every beam time will
    # do for the constant test (the interpolated state is the same either way).
    if n_beams:
        t_range = (float(scan_time.min() + step_dt.min()), float(scan_time.max() + step_dt.max()))
    else:
        t_range = (np.inf, -np.inf)
    side_mode = np.zeros(2, dtype=np.int64)
    bands = np.zeros((2, 3))
    lift = [(np.zeros(1), np.zeros(1)), (np.zeros(1), np.zeros(1))]
    for k, samples, prof in ((0, mirror_left, lift_left or model.lift_left),
                             (1, mirror_right, lift_right or model.lift_right)):
        const = _side_constant(samples, t_range, prof, lift_tolerance_rad)
        if const is not None:
            side_mode[k] = const
            continue
        assert prof is not None  # _side_constant raised otherwise
        sm = AngleSamples.of(samples)
        require(sm.t_s.size >= 1, "lift samples", sm.t_s.size, ">= 1 sample")
        side_mode[k] = -1
        lift[k] = (_plain(sm.t_s), _plain(sm.angle_rad))
        bands[k] = (prof.deployed_rad, prof.lifted_rad, lift_tolerance_rad)

    track: PoseTrack | None = None
    callable_pose = None
    if frame == "world":
        if isinstance(world_from_robot, PoseTrack):
            if len(world_from_robot.t_s) == 1:  # one pose: a constant transform
                track_T = np.asarray(world_from_robot.world_from_robot, float)[0]
                robot_T = track_T @ robot_T
            else:
                track = world_from_robot
        elif callable(world_from_robot):
            callable_pose = world_from_robot
        else:
            W0 = check_transform(world_from_robot, "world_from_robot")
            robot_T = W0 @ robot_T  # one constant transform (4x4 @ 4x4: no BLAS threads)
    frame_mode = 0 if frame == "sensor" else 2 if track is not None else 1
    pose_t = np.zeros(1) if track is None else _plain(track.t_s)
    pose_seg = np.zeros((1, 19)) if track is None else track._segment_table

    # outputs for every beam; the kernel writes the kept ones first (the cloud's arrays
    # are views of their first n rows: at most the error codes' share unused)
    xyz = np.empty((n_beams, 3))
    t = np.empty(n_beams)
    r = np.empty(n_beams)
    nod_rad = np.empty(n_beams)
    step_out = np.empty(n_beams, dtype=np.int32)
    scan_out = np.empty(n_beams, dtype=np.int32)
    mirror = np.empty(n_beams, dtype=np.int16)
    lifted = np.empty(n_beams, dtype=bool)
    n, n_ok, n_no_nod, n_moving, n_blocked = _kernel.assemble_points(
        steps, r_all, scan_i, scan_time, lidar.step_min, step_dt, rows, row_mirror,
        lidar.n_steps, _plain(model.step_side, np.int8), _plain(model.clear, bool), nod_t,
        nod_a, nod_mode, side_mode,
        lift[0][0], lift[0][1], lift[1][0], lift[1][1], bands, float(model.range_offset_m),
        float(model.range_scale), frame_mode, _plain(robot_T[:3]), pose_t,
        pose_seg, xyz, t, r, nod_rad, step_out, scan_out, mirror, lifted)
    if 2 * n < n_beams:  # most beams dropped: do not keep the buffers alive for a few points
        xyz, t, r, nod_rad = xyz[:n].copy(), t[:n].copy(), r[:n].copy(), nod_rad[:n].copy()
        step_out, scan_out = step_out[:n].copy(), scan_out[:n].copy()
        mirror, lifted = mirror[:n].copy(), lifted[:n].copy()
    xyz, t, r, nod_rad = xyz[:n], t[:n], r[:n], nod_rad[:n]
    if callable_pose is not None:  # per-point poses of the kept points' times
        W = np.asarray(callable_pose(t), dtype=float)
        if W.shape not in ((4, 4), (n, 4, 4)):
            raise ParameterError("world_from_robot(t).shape", W.shape,
                                 f"(4, 4) or ({n}, 4, 4)")
        W = check_transform(W, "world_from_robot(t)", stack=W.ndim == 3)
        _kernel.apply_transforms(_plain(np.broadcast_to(W, (n, 4, 4))), xyz)
    stats = AssemblyStats(beams=n_beams, error_codes=n_beams - n_ok, no_nod=n_no_nod,
                          mirror_moving=n_moving, blocked=n_blocked, points=n)
    return PointCloud(xyz, t, step_out[:n], mirror[:n], scan_out[:n], r, frame,
                      model.design_name, model.design_hash, model.calibration_id,
                      model.deployed.mirror_names, asdict(stats), nod_rad, lifted[:n])
