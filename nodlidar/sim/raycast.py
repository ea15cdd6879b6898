"""Ray caster of the simulated sensor: beams off finite mirrors into a trimesh/embree scene.

Independent of :class:`~nodlidar.beams.BeamModel` on purpose (the two check each other):

1. Every beam leaves the lidar origin along ``LidarModel.bearing_from_step`` (head frame)
   at its own time ``t_scan + step * step_period`` (``t_scan`` is the SCIP timestamp of the
   scan, which refers to step 0: conventions.md).
2. In the head frame it is cast with embree against every mirror as finite geometry: a
   two-triangle mesh of each patch of ``design.patches(perturbations)`` (the "as built"
   ground truth), turned about its side's lift axis (:mod:`nodlidar.hinge`, the one hinge
   model) by the lift state at the beam's time (the ray is turned back into the unturned
   patch's frame, so each beam may see its own lift state).
   The nearest mirror hit reflects it (:func:`~nodlidar.geometry.reflect`); up to
   ``max_bounces`` times. A beam meeting a mirror's back is absorbed (no return).
3. The outgoing ray is taken to the world at the beam's time: the nod pitch about
   ``nod.pivot_m`` (conventions.md), then the sensor pose of the :class:`~.scene.Scene`.
4. All rays of a scan are cast in one embree call against the static world
   (``trimesh.ray.ray_pyembree.RayMeshIntersector.intersects_first``) and, per mover, in one
   call against the mover's mesh with each ray moved into the mover's frame at its own time
   (rigid translation: origin - position(t_i)). The distance to the triangle found is
   recomputed in float64 from its plane (embree works in float32).
   The per-beam work around the embree calls (ray generation and turning, nod and pose,
   culls, distances, truth, noise) runs in compiled loops (:mod:`._kernel`, numba): the
   formulas of :mod:`nodlidar.geometry` and :mod:`.scene`, operation for operation.
5. Range = total path length (lidar -> mirror -> object), as the device measures it.

Assumptions: nothing in the scene lies between the lidar and its mirrors (within the
sensor head, ~0.2 m); the lidar housing does not block reflected beams (the solver keeps
them clear); mirror glass has no thickness.

The URG measurement model (:func:`measure`) adds Gaussian range noise with
``LidarModel.range_sigma_m`` (the data sheet's +-30 mm to 1 m / +-3 % beyond read as
3 sigma, i.e. 10 mm / 1 %; see lidar.py), rounds to mm, and reports no return as NaN.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..errors import ParameterError
from ..geometry import (
    MirrorPatch,
    Perturbation,
    directions_from_bearings,
    ray_cylinder_hit,
    rotate_about_axis,
)
from ..hinge import LiftAxis, lift_fraction, lifted_patch, side_lift_axes
from ..lidar import LidarModel
from . import _kernel as K
from .scene import HIT_NONE, HIT_STATIC, BackAndForth, ConstantVelocity, Fixed, Scene, builtin_scene

if TYPE_CHECKING:
    from ..design import Design

# lift_fraction (nodlidar.hinge) and rotate_about_axis (nodlidar.geometry) are re-exported
# under their old home for callers that import them from here
__all__ = ["ScanTruth", "SceneSimulator", "measure", "lift_fraction", "rotate_about_axis"]


def measure(true_ranges_m: np.ndarray, model: LidarModel, rng: np.random.Generator | None,
            *, noise: bool = True) -> np.ndarray:
    """The URG's range measurement: true path length [m] -> reported range [m].

    Adds ``N(0, range_sigma_m(r))`` noise (if ``noise``), rounds to the millimetre; no
    return (NaN or inf) stays NaN. Range limits are not applied here: the SCIP emulator
    turns values outside DMIN..DMAX into the device's error codes, and
    :meth:`ScanTruth.measured_m` gives NaN for them. The noise is one
    ``rng.standard_normal(shape)`` draw (every element, returns or not).
    """
    r = np.asarray(true_ranges_m, dtype=float)
    if noise and rng is None:
        raise ParameterError("rng", rng, "a numpy Generator when noise=True")
    z = rng.standard_normal(r.shape) if noise and rng is not None else np.zeros(0)
    near, knee, rel = model.range_noise
    out = K.measure(np.ascontiguousarray(r.ravel()), np.ascontiguousarray(z.ravel()), noise,
                    float(near), float(knee), float(rel))
    return out.reshape(r.shape)[()]


@dataclass(frozen=True, eq=False)
class ScanTruth:
    """One simulated scan with its per-beam ground truth. Arrays are ``(n,)`` / ``(n, 3)``
    over the simulated steps.

    Attributes
    ----------
    steps : int
    t_s : float
        Time of each beam [s].
    nod_rad : float
        Head pitch at each beam's time [rad].
    true_range_m : float
        Exact total path length [m] (NaN: no return).
    range_m : float
        What the device reports [m], noise and mm rounding applied, limits not (NaN: no
        return).
    mirror : int
        Index (into ``design.mirrors``) of the first mirror the beam reflected off, -1 direct.
    bounces : int
        Number of mirror reflections.
    object_id : int
        ``HIT_NONE`` (-1), ``HIT_STATIC`` (0) or ``1 + k`` for mover ``k``.
    part : int
        Index into ``SceneSimulator.part_names`` for static hits, else -1.
    point_world : float (n, 3)
        True hit point in the world frame [m] (NaN: no return).
    """

    steps: np.ndarray
    t_s: np.ndarray
    nod_rad: np.ndarray
    true_range_m: np.ndarray
    range_m: np.ndarray
    mirror: np.ndarray
    bounces: np.ndarray
    object_id: np.ndarray
    part: np.ndarray
    point_world: np.ndarray
    range_min_m: float
    range_max_m: float

    def measured_m(self) -> np.ndarray:
        """Ranges [m] a driver gets: NaN where the device sends an error code."""
        r = self.range_m
        ok = (r >= self.range_min_m) & (r <= self.range_max_m)
        return np.where(ok, r, np.nan)


def _trajectory_kernel_args(traj) -> tuple[int, np.ndarray, np.ndarray, float, float, float] | None:
    """``(kind, p0, p1, leg_s, t0, speed)`` of a scene trajectory for the mover kernels
    (``_kernel._position``; speed: its largest speed [m/s]); None: another kind, whose
    ``position(t)`` is called."""
    z3 = np.zeros(3)
    if isinstance(traj, Fixed):
        return K.TRAJ_FIXED, np.asarray(traj.position_m, dtype=float), z3, 1.0, 0.0, 0.0
    if isinstance(traj, ConstantVelocity):
        v = np.asarray(traj.velocity_m_s, dtype=float)
        return (K.TRAJ_CONSTANT_VELOCITY, np.asarray(traj.start_m, dtype=float), v, 1.0,
                float(traj.t0_s), float(np.linalg.norm(v)) * (1 + 1e-12))
    if isinstance(traj, BackAndForth):
        return (K.TRAJ_BACK_AND_FORTH, np.asarray(traj.start_m, dtype=float),
                np.asarray(traj.end_m, dtype=float), float(traj.leg_s), float(traj.t0_s),
                float(traj.speed_m_s) * (1 + 1e-12))
    return None


def _rows(a: np.ndarray) -> np.ndarray:
    """``a`` as a C-ordered float64 ``(n, 3)`` array (what the kernels take)."""
    return np.ascontiguousarray(a, dtype=np.float64)


def _per_beam(x: np.ndarray | float, n: int) -> np.ndarray:
    """A scalar or ``(n,)`` array as a C-ordered float64 ``(n,)`` array (no copy if it is one)."""
    a = np.asarray(x, dtype=np.float64)
    if a.shape == (n,):
        return np.ascontiguousarray(a)
    return np.ascontiguousarray(np.broadcast_to(a, (n,)))


class _MeshCaster:
    """One mesh with an embree intersector and what the kernels need of it.

    The kernels prepare the rays for embree exactly as trimesh's ``intersects_first``
    prepares them (``_kernel.embree_rays``: the same float32 rays, so the same triangles),
    :meth:`first` calls the embree scene directly (skipping trimesh's per-call mesh-hash
    lookup), and the kernels recompute each distance in float64 from the triangle's plane
    (``normals``, ``_offset``). Movers and mirrors are cast only with the rays that meet
    the mesh's bounding sphere (``_centre``, ``_radius2``: about the bounding box's centre
    through its corners, in float64, 1 mm larger: far above embree's float32 error, so no
    ray that embree would report is dropped); embree casts each ray on its own, so a subset
    gets the same triangle per ray.
    """

    _MARGIN_M = 1e-3

    def __init__(self, mesh):
        from trimesh.ray.ray_pyembree import RayMeshIntersector

        self.mesh = mesh
        self.intersector = RayMeshIntersector(mesh)
        wrap = self.intersector._scene  # trimesh's _EmbreeWrap: shift, scale, embree scene
        self._run = wrap.scene.run
        self._origin = np.asarray(wrap.origin, dtype=np.float64)
        self._scale = float(wrap.scale)
        tri = np.asarray(mesh.triangles, dtype=float)
        self.v0 = tri[:, 0]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        self.normals = np.ascontiguousarray(n / np.linalg.norm(n, axis=1, keepdims=True))
        self._offset = np.einsum("ij,ij->i", self.v0, self.normals)  # plane: x . n = offset
        lo, hi = np.asarray(mesh.bounds, dtype=float)
        self._centre = (lo + hi) / 2
        self._radius2 = (float(np.linalg.norm(hi - lo)) / 2 + self._MARGIN_M) ** 2

    def first(self, o32: np.ndarray, d32: np.ndarray) -> np.ndarray:
        """Triangle index (m,) int32 of each prepared embree ray's first hit (-1 none)."""
        if not len(o32):
            return np.zeros(0, dtype=np.int32)
        return self._run(o32, d32)


class SceneSimulator:
    """Casts the beams of a design's sensor head into a :class:`~.scene.Scene`.

    Parameters
    ----------
    design : Design
        Solved design: the lidar, the mirrors, the nod pivot, the lift geometry.
    scene : Scene, str or None
        Scene or built-in name (default ``"room"``). A TOML file is read by the caller
        (:func:`~.scene.load_scene`), not here: constructors do no I/O.
    perturbations : mapping name -> Perturbation, optional
        "As built" mirror errors (ground truth), e.g. ``nodlidar.paper.TABLE_I_PERTURBATIONS``.
    max_bounces : int
        Mirror reflections followed per beam.

    Building the embree scenes happens here (CPU work, no I/O).
    """

    def __init__(self, design: Design, scene: Scene | str | None = None,
                 perturbations: Mapping[str, Perturbation] | None = None, *,
                 max_bounces: int = 2) -> None:
        self.design = design
        self.lidar: LidarModel = design.lidar
        self.scene = scene if isinstance(scene, Scene) else builtin_scene(scene or "room")
        self.perturbations = dict(perturbations or {})
        self.patches: list[MirrorPatch] = design.patches(self.perturbations)
        self.mirror_sides = np.array([m.side for m in design.mirrors])
        self.lift_angle_rad = float(design.spec.mirror.lift_angle_rad)
        # the one hinge model (nodlidar.hinge): each side's mirrors turn about the side's
        # lift axis, from the nominal faces (the carrier is printed to the nominal design)
        self.lift_axes: dict[str, LiftAxis] = side_lift_axes(design)
        self._axis_of = [self.lift_axes[m.side] for m in design.mirrors]
        self.pivot = np.asarray(design.spec.nod.pivot_m, dtype=float)
        self.max_bounces = int(max_bounces)
        th = self.lidar.bearing_from_step(self.lidar.steps)
        self._dir0 = directions_from_bearings(th)
        import trimesh

        parts = self.scene.static_parts()
        self.part_names = [name for name, _ in parts]
        if parts:
            meshes = [m for _, m in parts]
            self._face_part = np.concatenate([np.full(len(m.faces), i) for i, m in enumerate(meshes)])
            self._static: _MeshCaster | None = _MeshCaster(trimesh.util.concatenate(meshes))
        else:
            self._face_part = np.zeros(0, dtype=int)
            self._static = None
        self._movers = [_MeshCaster(m.mesh()) for m in self.scene.movers]
        self._mover_args = [_trajectory_kernel_args(m.trajectory) for m in self.scene.movers]
        pose = self.scene.sensor
        # the sensor pose as the world_rays kernel takes it (scene.SensorPose.to_world)
        self._pose_args = (np.ascontiguousarray(pose.rotation), np.asarray(pose.position_m, dtype=float),
                           np.asarray(pose.velocity_m_s, dtype=float), float(pose.t0_s))
        # the static scene's embree shift and scale: world_rays prepares its rays too
        self._static_prep = ((self._static._origin, self._static._scale) if self._static is not None
                             else (np.zeros(3), 1.0))
        self._no_pos, self._no_rows = np.zeros(3), np.zeros((0, 3))
        self._steps_f = self.lidar.steps.astype(float)  # beam_times' float conversion, once
        # each mirror's glass as a mesh of its own (two triangles): beams are cast at it in
        # its unturned frame, one embree call per mirror and bounce
        # (culled to the rays that reach its beam window, then its bounding sphere)
        self._mirrors = [_MeshCaster(trimesh.Trimesh(p.corners(), [[0, 1, 2], [0, 2, 3]],
                                                     process=False))
                         for p in self.patches]
        self._head_cache: dict[tuple[float, float], tuple] = {}
        # each mirror's beam window: a sphere centred on its side's lift axis through its
        # corners (1 mm larger), so it holds the patch turned by any lift angle
        self._windows = []
        for p, ax in zip(self.patches, self._axis_of, strict=True):
            q = p.corners()
            c = ax.nearest_point(q.mean(axis=0))
            r = float(np.max(np.linalg.norm(q - c, axis=1))) + _MeshCaster._MARGIN_M
            self._windows.append((c, r * r))

    # -- pieces ------------------------------------------------------------------------
    def mirror_patches_at(self, lift_left: float = 0.0, lift_right: float = 0.0) -> list[MirrorPatch]:
        """The glass the beams meet at constant lift fractions (0 deployed, 1 lifted): each
        of :attr:`patches` turned about its side's lift axis (:func:`~nodlidar.hinge.lifted_patch`),
        the pose :meth:`head_rays` casts against."""
        frac = {"L": float(lift_left), "R": float(lift_right)}
        return [lifted_patch(p, ax, frac[ax.side])
                for p, ax in zip(self.patches, self._axis_of, strict=True)]

    def beam_times(self, t_scan_s: float, steps: np.ndarray | None = None) -> np.ndarray:
        """Time [s] of each step's measurement in the scan stamped ``t_scan_s`` (step 0)."""
        steps = self._steps_f if steps is None else np.asarray(steps)
        return self.lidar.beam_time_s(t_scan_s, steps)

    def head_rays(self, steps: np.ndarray, lift_left: np.ndarray | float = 0.0,
                  lift_right: np.ndarray | float = 0.0
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Trace beams off the mirrors in the head frame.

        Parameters
        ----------
        steps : (n,) int
        lift_left, lift_right : (n,) or float
            Lift fraction (0 deployed, 1 lifted) of each side's mirrors at each beam's time.

        Returns
        -------
        start (n, 3), direction (n, 3), path offset (n,) [m], first mirror (n,) int (-1
        direct), bounces (n,) int, alive (n,) bool (False: absorbed by a mirror's back or
        reflected into the lidar's housing).
        """
        steps = np.asarray(steps)
        self.lidar.check_step(steps, "steps")
        n = len(steps)
        o = np.zeros((n, 3))
        d = np.ascontiguousarray(self._dir0[steps - self.lidar.step_min])
        off = np.zeros(n)
        first = np.full(n, -1)
        bounces = np.zeros(n, dtype=np.int64)
        alive = np.ones(n, dtype=bool)
        last = np.full(n, -1)
        # the lift turns each side about its lift axis by f * lift_rad (nodlidar.hinge,
        # conventions.md): cosine and sine of each beam's angle per side, by numpy as
        # rotate_about_axis takes them (sin(-a) = -sin(a) exactly: the kernel turns back)
        trig = {}
        for side, f in (("L", lift_left), ("R", lift_right)):
            ax = self.lift_axes.get(side)
            if ax is not None:
                ang = _per_beam(ax.angle(f), n)
                trig[side] = (np.cos(ang), np.sin(ang))
        for _ in range(self.max_bounces):
            best_t = np.full(n, np.inf)
            best_m = np.full(n, -1)
            best_nrm = np.zeros((n, 3))
            for i, p in enumerate(self.patches):
                # the rays in the mirror's beam window, turned back into the unturned
                # patch's frame (one kernel), cast at the glass by embree
                ax, glass = self._axis_of[i], self._mirrors[i]
                centre, r2 = self._windows[i]
                c, s = trig[ax.side]
                idx, ol, dl, nrm, o32, d32 = K.mirror_rays(
                    o, d, alive, last, i, centre, r2, ax.point_, ax.direction_, c, s,
                    p.normal_, glass._centre, glass._radius2, glass._origin, glass._scale)
                if len(idx):
                    K.mirror_update(idx, ol, dl, nrm, glass.first(o32, d32), glass.normals,
                                    glass._offset, i, best_t, best_m, best_nrm)
            # a reflected beam that turns back into the lidar's own housing before it
            # meets another mirror is lost there (verify.trace's rule, which the runtime
            # uses to drop such steps); the reflecting side faces the lidar (normal towards
            # it): a hit on the back is absorbed
            housed = self._into_housing(o, d, bounces, alive, best_t)
            if not K.bounce(o, d, off, first, bounces, alive, last, best_t, best_m, best_nrm,
                            housed):
                break
        alive &= ~self._into_housing(o, d, bounces, alive, np.inf)
        return o, d, off, first, bounces, alive

    def _into_housing(self, o: np.ndarray, d: np.ndarray, bounces: np.ndarray,
                      alive: np.ndarray, t_max: np.ndarray | float) -> np.ndarray:
        """(n,) bool: reflected, live rays that enter the housing cylinder before ``t_max``."""
        out = np.zeros(len(o), dtype=bool)
        sel = np.flatnonzero(alive & (bounces > 0))
        if len(sel):
            tm = t_max if np.ndim(t_max) == 0 else np.asarray(t_max)[sel]
            out[sel] = ray_cylinder_hit(o[sel], d[sel], self.lidar.housing_radius_m, tm)
        return out

    def _head_rays_cached(self, steps, lift_left, lift_right, whole: bool | None = None):
        """:meth:`head_rays`, memoised for whole scans with a constant lift state (the usual
        case: the head-frame paths then do not change from scan to scan). ``whole``: the
        caller knows ``steps`` are all steps (None: compare)."""
        key: tuple[float, float] | None
        if isinstance(lift_left, int | float) and isinstance(lift_right, int | float):
            key = (float(lift_left), float(lift_right))
        else:
            fl, fr = np.asarray(lift_left, dtype=float), np.asarray(lift_right, dtype=float)
            constant = np.ptp(fl) == 0 and np.ptp(fr) == 0
            key = (float(fl.flat[0]), float(fr.flat[0])) if constant else None
        if whole is None:
            whole = bool(np.array_equal(steps, self.lidar.steps))
        if not whole or key is None:
            return self._frozen_head_rays(steps, lift_left, lift_right)
        hit = self._head_cache.get(key)
        if hit is None:
            hit = self._frozen_head_rays(steps, key[0], key[1])
            if len(self._head_cache) > 64:  # a lift in progress makes many keys
                self._head_cache.clear()
            self._head_cache[key] = hit
        return hit

    def _frozen_head_rays(self, steps, lift_left, lift_right):
        """:meth:`head_rays` read-only, with the head points relative to the nod pivot
        (for to_world). Cached or not, the kernels then see the same array types: numba
        compiles one version per argument type, read-only included, and a second version
        compiled mid-run (mirrors starting to move) would stall the emulator's thread."""
        hit = self.head_rays(steps, lift_left, lift_right)
        out = (*hit, hit[0] - self.pivot)
        for a in out:
            a.setflags(write=False)
        return out

    def to_world(self, p_head: np.ndarray, d_head: np.ndarray, nod_rad: np.ndarray,
                 t_s: np.ndarray, _rel: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Head-frame points/directions ``(n, 3)`` at per-row nod [rad] and time [s] -> world
        frame ``(n, 3), (n, 3)``: the nod ``R_y(nod)`` about the pivot (conventions.md,
        geometry.pitch_about_pivot), then the sensor pose (scene.SensorPose.to_world), in
        one kernel (``_kernel.world_rays``). ``_rel``: the cached ``p_head - pivot``."""
        return self._to_world(p_head, d_head, nod_rad, t_s, _rel)[:2]

    def _to_world(self, p_head, d_head, nod_rad, t_s, _rel=None):
        """:meth:`to_world` and the world rays as the static scene's embree rays:
        ``(o (n, 3), d (n, 3), o32 (n, 3), d32 (n, 3))``."""
        rel = _rows(p_head - self.pivot if _rel is None else _rel)
        nod = _per_beam(nod_rad, len(rel))
        return K.world_rays(rel, _rows(d_head), self.pivot, np.cos(nod), np.sin(nod),
                            _per_beam(t_s, len(rel)), *self._pose_args, *self._static_prep)

    def cast_world(self, origins: np.ndarray, dirs: np.ndarray, t_s: np.ndarray,
                   _prepared: tuple[np.ndarray, np.ndarray] | None = None
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Nearest hit of world rays ``(n, 3)`` among the static world and the movers at
        times ``t_s (n,)`` [s] (``_prepared``: the rays already as the static scene's embree
        rays, from :meth:`_world_rays`).

        Returns ``(distance (n,) [m] inf = none, object_id (n,), part (n,))``.
        """
        o, d = _rows(origins), _rows(dirs)
        n = len(o)
        if self._static is not None:
            st = self._static
            o32, d32 = (_prepared if _prepared is not None
                        else K.embree_rays(o, d, st._origin, st._scale))
            dist, obj, part = K.first_hits(o, d, st.first(o32, d32), st.normals, st._offset,
                                           self._face_part, HIT_STATIC)
        else:
            dist, obj, part = np.full(n, np.inf), np.full(n, HIT_NONE), np.full(n, -1)
        if not self._movers:
            return dist, obj, part
        t = _per_beam(t_s, n)
        for k, (mover, caster, args) in enumerate(zip(self.scene.movers, self._movers,
                                                      self._mover_args, strict=True)):
            # a rigidly translating object: cast each ray in the object's frame at its time
            if args is None:  # another kind of trajectory: its own position(t)
                kind, p0, p1, leg_s, t0, speed = -1, self._no_pos, self._no_pos, 1.0, 0.0, 0.0
                pos = _rows(mover.position(t))
            else:
                (kind, p0, p1, leg_s, t0, speed), pos = args, self._no_rows
            idx, om, o32, d32 = K.mover_rays(o, d, t, kind, p0, p1, leg_s, t0, speed, pos,
                                             caster._centre, caster._radius2, caster._origin,
                                             caster._scale)
            if len(idx):
                K.merge_closer(idx, om, d, caster.first(o32, d32), caster.normals,
                               caster._offset, 1 + k, dist, obj, part)
        return dist, obj, part

    # -- whole scan --------------------------------------------------------------------
    def scan(self, t_scan_s: float = 0.0, nod_rad: np.ndarray | float = 0.0,
             lift_left: np.ndarray | float = 0.0, lift_right: np.ndarray | float = 0.0, *,
             steps: np.ndarray | None = None, noise: bool = True,
             rng: np.random.Generator | None = None, seed: int | None = 0) -> ScanTruth:
        """Simulate one scan.

        Parameters
        ----------
        t_scan_s : float
            Scan timestamp (time of step 0) [s].
        nod_rad : float or (n,)
            Head pitch at each beam's time [rad].
        lift_left, lift_right : float or (n,)
            Lift fraction per side (0 deployed, 1 lifted; see :func:`lift_fraction`).
        steps : (n,) int, optional
            Steps to simulate (default all valid steps).
        noise : bool
            Add the URG range noise.
        rng, seed : optional
            Noise generator, or a seed for a fresh one.
        """
        rays = self._world_rays(t_scan_s, nod_rad, lift_left, lift_right, steps)
        dist, obj, part = self.cast_world(rays[5], rays[6], rays[1], rays[9])
        if noise and rng is None:
            rng = np.random.default_rng(seed)
        return self._truth(rays, dist, obj, part, rng, noise)

    def warm_up(self) -> None:
        """Compile (or load from numba's cache) every kernel a scan can use, now.

        numba compiles a kernel at its first call: ~5 s per machine the first time (the
        cache keeps it after), ~0.3 s to load from the cache in a new process. Paid inside
        a real-time loop - the emulator's first scan while the driver waits - it loses
        scans, so :meth:`SimulatedSensor.start` calls this before it serves. Simulates
        (and discards) a scan with the mirrors still, one with them moving and one noisy.
        """
        half = np.full(self._steps_f.shape, 0.5)
        self.scan(0.0, 0.0, 0.0, 0.0, noise=False)
        self.scan(0.0, 0.0, half, half, noise=True, rng=np.random.default_rng(0))

    def _world_rays(self, t_scan_s, nod_rad, lift_left, lift_right, steps):
        """World rays of one scan: (steps, t, nod, head-path offset, first mirror, origins,
        directions, bounces, alive, (o32, d32) the static scene's embree rays)."""
        whole = steps is None
        steps = self.lidar.steps if whole else np.asarray(steps)
        n = len(steps)
        t = self.beam_times(t_scan_s, steps)
        a = np.asarray(nod_rad, dtype=float)
        nod = (a.copy() if a.shape == (n,) else np.full(n, a) if a.ndim == 0
               else np.array(np.broadcast_to(a, (n,))))
        o_h, d_h, off, first, bounces, alive, *rel = self._head_rays_cached(
            steps, lift_left, lift_right, whole=True if whole else None)
        o_w, d_w, o32, d32 = self._to_world(o_h, d_h, nod, t, rel[0] if rel else None)
        return steps, t, nod, off, first, o_w, d_w, bounces, alive, (o32, d32)

    def _truth(self, rays, dist, obj, part, rng, noise) -> ScanTruth:
        """ScanTruth of one scan from its rays and their world hits (the noise: one
        ``rng.standard_normal(n)`` draw, as :func:`measure`)."""
        steps, t, nod, off, first, o_w, d_w, bounces, alive, _ = rays
        z = rng.standard_normal(len(dist)) if noise else np.zeros(0)
        near, knee, rel = self.lidar.range_noise
        true_r, r, obj_out, part_out, pts = K.scan_truth(
            np.ascontiguousarray(alive), dist, np.ascontiguousarray(off, dtype=float), o_w, d_w,
            obj, part, z, bool(noise), float(near), float(knee), float(rel))
        return ScanTruth(steps=steps, t_s=t, nod_rad=nod, true_range_m=true_r, range_m=r,
                         mirror=first, bounces=bounces, object_id=obj_out, part=part_out,
                         point_world=pts, range_min_m=self.lidar.range_min_m,
                         range_max_m=self.lidar.range_max_m)

    def scans(self, n_scans: int, *, t0_s: float = 0.0,
              nod: float | Callable[[np.ndarray], np.ndarray] | None = None,
              lift_left: float = 0.0, lift_right: float = 0.0, noise: bool = True,
              seed: int = 0) -> list[ScanTruth]:
        """Simulate ``n_scans`` consecutive scans (the direct API, no emulators).

        Parameters
        ----------
        n_scans : int
        t0_s : float
            Timestamp of the first scan [s]; scan ``k`` is stamped ``t0_s + k * period``.
        nod : None, float or callable
            Head pitch [rad]: ``None`` = the design's nod ramp (``NodSpec.pitch_at``, from
            the lower limit at t = 0), a constant, or ``f(t_s (n,)) -> (n,)``.
        lift_left, lift_right : float
            Constant lift fractions (0 deployed, 1 lifted).
        noise, seed : noise switch; scan ``k`` uses ``default_rng([seed, k])`` like
            :class:`~nodlidar.sim.sensor.SimulatedSensor`.
        """
        period = self.lidar.scan_period_s
        k0 = int(round(t0_s / period))
        rays = []
        for i in range(int(n_scans)):
            t_scan = t0_s + i * period
            t = self.beam_times(t_scan)
            pitch: np.ndarray | float
            if nod is None:
                pitch = self.design.spec.nod.pitch_at(t)
            elif callable(nod):
                pitch = np.asarray(nod(t), dtype=float)
            else:
                pitch = float(nod)
            rays.append(self._world_rays(t_scan, pitch, lift_left, lift_right, None))
        if not rays:
            return []
        # every scan's rays in one embree call per mesh (each ray is cast on its own, so
        # the hits are those of scan-by-scan casts)
        cut = np.cumsum([len(r[0]) for r in rays])[:-1]
        dist, obj, part = self.cast_world(np.concatenate([r[5] for r in rays]),
                                          np.concatenate([r[6] for r in rays]),
                                          np.concatenate([r[1] for r in rays]),
                                          (np.concatenate([r[9][0] for r in rays]),
                                           np.concatenate([r[9][1] for r in rays])))
        out = []
        for i, (r, d, o, p) in enumerate(zip(rays, np.split(dist, cut), np.split(obj, cut),
                                             np.split(part, cut))):
            rng = np.random.default_rng([int(seed), k0 + i]) if noise else None
            out.append(self._truth(r, d, o, p, rng, noise))
        return out
