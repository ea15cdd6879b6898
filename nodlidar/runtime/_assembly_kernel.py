"""Compiled per-point kernels of the point assembly (:mod:`nodlidar.runtime.assembly`).

One pass over the beams does what the assembly does per point: the beam's time, its
nod angle interpolated from the servo samples, its mirror side's state (interpolated lift
angle against the deployed/lifted bands), the drop decision, the range model, the
projection on its step's table row, the nod about the pivot, the sensor's mount on the
robot and the robot's slerped pose at the beam's own time; the kept points are written
compressed into preallocated outputs. The per-step and per-keyframe tables, the
validation and the PointCloud are built by :mod:`nodlidar.runtime.assembly`.

The scalar rotation math is the per-point counterpart of :mod:`nodlidar.geometry`, from
:mod:`nodlidar._compiled_geometry` (shared with the simulator's kernels):
:func:`rodrigues` is :func:`~nodlidar.geometry.rotate_columns` (the same formula, the
same operation order) and :func:`cos_sin` is :func:`nodlidar.beams.cos_sin`; the slerp is
:class:`~nodlidar.runtime.assembly.PoseTrack`'s ``R_i exp(f th_i [k_i])``
(tests/test_assembly.py checks both against those to 1e-12).

numba is imported here only: :mod:`nodlidar.runtime.assembly` imports this module inside
the functions that assemble, so ``import nodlidar``, the CLI's parser and ``nodlidar
design`` never load it. Compiled with ``cache=True`` (the first call in a fresh
environment compiles, later processes load the cache; ``benchmarks/bench_assembly.py``
reports both), ``nogil=True`` (driver threads keep running), no fastmath (the results
are those of the float64 formulas, tests/test_assembly_regression.py) and no parallel
loops (two cores shared with the driver threads).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from .._compiled_geometry import cos_sin, rodrigues

__all__ = ["ROW", "SEG", "NAN", "CLAMP", "EXTRAPOLATE", "CONSTANT", "cos_sin", "rodrigues",
           "assemble_points", "apply_poses", "apply_transforms", "interp_angles",
           "mirror_states"]

_jit = numba.njit(cache=True, nogil=True)
# the per-point helpers are inlined into the kernels at numba's IR level: as separate
# compiled functions each call costs ~13 ns (measured; LLVM does not inline them)
_inline = numba.njit(cache=True, nogil=True, inline="always")

#: Columns of the per-step row table ``rows`` (m, 13) of :func:`assemble_points`: offset
#: ``a`` [m] and direction ``b`` of ``a + b r`` (pivot subtracted), path length to the
#: mirror [m], direction leaving the lidar ``d0``, nod pivot [m]
#: (:class:`~nodlidar.beams.BeamColumns` as rows).
ROW = {n: i for i, n in enumerate(("ax", "ay", "az", "bx", "by", "bz", "t_mirror",
                                   "d0x", "d0y", "d0z", "px", "py", "pz"))}
#: Columns of the keyframe-pair table ``seg`` (max(k-1, 1), 19) of a pose track: angle
#: [rad] and unit axis of ``R_i^T R_(i+1)``, ``R_i`` row-major, translation ``p_i`` [m]
#: and its change to the next keyframe [m].
SEG = {n: i for i, n in enumerate(
    ("th", "kx", "ky", "kz", "r00", "r01", "r02", "r10", "r11", "r12", "r20", "r21", "r22",
     "p0", "p1", "p2", "dp0", "dp1", "dp2"))}

#: Interpolation outside the samples (servo_angles.interpolate_angle's modes) and a
#: constant angle: the ``mode`` argument of :func:`interp_angles` / :func:`assemble_points`.
NAN, CLAMP, EXTRAPOLATE, CONSTANT = 0, 1, 2, 3
DEPLOYED, LIFTED, BETWEEN = 0, 1, 2  # assembly's mirror states


@_inline
def _segment(ts: np.ndarray, q: float, j: int) -> int:
    """Index ``j`` in ``[0, k-2]`` of the sample interval of ``ts`` (k,) [s] (k >= 2,
    increasing) holding ``q`` (``ts[j] <= q < ts[j+1]``; the end intervals for ``q``
    outside); ``j`` on entry is a hint (the previous point's: beams come in time order
    within a scan, so it is mostly right or one off)."""
    n = ts.size
    if 0 <= j <= n - 2 and ts[j] <= q:
        if q < ts[j + 1]:
            return j
        if j + 2 <= n - 1 and q < ts[j + 2]:
            return j + 1
    if q < ts[1]:
        return 0
    if q >= ts[n - 2]:
        return n - 2
    lo, hi = 1, n - 2  # ts[lo] <= q < ts[hi]
    while hi - lo > 1:
        mid = (lo + hi) >> 1
        if ts[mid] <= q:
            lo = mid
        else:
            hi = mid
    return lo


@_inline
def _interp(ts: np.ndarray, a: np.ndarray, q: float, mode: int, j: int
            ) -> tuple[float, int]:
    """Angle [rad] at ``q`` [s] from samples ``ts``, ``a`` (k,): ``np.interp``'s formula
    inside, outside by ``mode`` (NAN, CLAMP, EXTRAPOLATE: the end segment's line, as
    :func:`~nodlidar.runtime.servo_angles.interpolate_angle`; CONSTANT: ``a[0]``
    everywhere). Returns the angle and the interval index (the next call's hint)."""
    if mode == CONSTANT:
        return a[0], j
    n = ts.size
    if not (q == q):
        return math.nan, j
    if q < ts[0] or q > ts[n - 1]:
        if mode == NAN:
            return math.nan, j
        if mode == CLAMP:
            return (a[0] if q < ts[0] else a[n - 1]), j
        if q < ts[0]:
            return a[0] + (a[1] - a[0]) / (ts[1] - ts[0]) * (q - ts[0]), j
        return a[n - 1] + (a[n - 1] - a[n - 2]) / (ts[n - 1] - ts[n - 2]) * (q - ts[n - 1]), j
    if n == 1 or q == ts[n - 1]:
        return a[n - 1], j
    j = _segment(ts, q, j)
    slope = (a[j + 1] - a[j]) / (ts[j + 1] - ts[j])
    return slope * (q - ts[j]) + a[j], j


@_inline
def _state(angle: float, deployed: float, lifted: float, tol: float) -> int:
    """DEPLOYED / LIFTED / BETWEEN of a lift-servo angle [rad]: within ``tol`` [rad] of
    an end; the lifted band wins where both hold; NaN (unknown) is BETWEEN."""
    state = BETWEEN
    if abs(angle - deployed) <= tol:
        state = DEPLOYED
    if abs(angle - lifted) <= tol:
        state = LIFTED
    return state


@_inline
def _pose(ts: np.ndarray, seg: np.ndarray, t: float, x: float, y: float, z: float,
          j: int) -> tuple[float, float, float, int]:
    """Robot-frame point ``(x, y, z)`` [m] at time ``t`` [s] -> world frame by the pose
    track (keyframe times ``ts`` (k,), table ``seg``, :data:`SEG`): the slerp
    ``R_i exp(f th_i [k_i])`` (the point turned about the pair's axis by ``f th_i``, then
    ``R_i``) and the linear translation, clamped outside the track. Returns the point and
    the keyframe pair (the next call's hint)."""
    f = 0.0
    if ts.size > 1:
        tq = min(max(t, ts[0]), ts[ts.size - 1])
        j = _segment(ts, tq, j)
        f = (tq - ts[j]) / (ts[j + 1] - ts[j])
    else:
        j = 0
    g = seg[j]
    c, s = cos_sin(f * g[0])
    qx, qy, qz = rodrigues(x, y, z, g[1], g[2], g[3], c, s)
    wx = g[4] * qx + g[5] * qy + g[6] * qz + g[13] + f * g[16]
    wy = g[7] * qx + g[8] * qy + g[9] * qz + g[14] + f * g[17]
    wz = g[10] * qx + g[11] * qy + g[12] * qz + g[15] + f * g[18]
    return wx, wy, wz, j


@_jit
def assemble_points(steps, ranges, scan, scan_time, step_min, step_dt, rows, row_mirror,
                    n_steps, step_side, clear, nod_t, nod_a, nod_mode, side_mode,
                    lift_t0, lift_a0, lift_t1, lift_a1, bands, range_offset, range_scale,
                    frame_mode, robot, pose_t, pose_seg,
                    xyz, t_out, r_out, nod_out, step_out, scan_out, mirror_out, lifted_out):
    """All beams of a batch -> the kept points, compressed, in one pass.

    Parameters (per beam: N; per step: S = n_steps; rows: 2 S)
    ----------
    steps, scan : (N,) int64
        Lidar step (checked in range) and scan index of each beam.
    ranges : (N,) float64
        Range [m] (NaN, inf, <= 0: an error code, dropped).
    scan_time : (m,) float64
        Each scan's step-0 time [s]; ``step_dt`` (S,) float64 each step's offset [s]
        (``LidarModel.beam_time_s(0, steps)``), ``step_min`` int.
    rows : (2 S, 13) float64
        Projection table (:data:`ROW`): row ``i`` = step ``step_min + i`` deployed, row
        ``S + i`` the same step lifted (direct); ``row_mirror`` (2 S,) int16 its mirror.
    step_side : (S,) int8
        Side (0 left, 1 right) of each step's deployed mirror, -1 direct; ``clear`` (S,)
        bool: the deployed path is clean.
    nod_t, nod_a, nod_mode
        Nod samples (k,) [s], [rad] and what happens outside them (NAN, CLAMP,
        EXTRAPOLATE; CONSTANT: ``nod_a[0]`` is the pitch).
    side_mode : (2,) int64
        Each side's state if constant (DEPLOYED, LIFTED), -1: from its lift samples
        ``lift_t<side>``, ``lift_a<side>`` [s], [rad] (NaN outside) against ``bands``
        (2, 3) float64 = deployed angle, lifted angle, tolerance [rad].
    range_offset, range_scale : float
        Range model, inverted: ``(r - offset) / (1 + scale)`` (0, 0: none).
    frame_mode : int
        0 sensor frame, 1 ``robot`` (3, 4) applied, 2 then the pose track ``pose_t``
        (k,) [s], ``pose_seg`` (:data:`SEG`).
    xyz : (N, 3) float64; t_out, r_out, nod_out : (N,) float64; step_out, scan_out : (N,)
    int32; mirror_out : (N,) int16; lifted_out : (N,) bool
        Outputs, the first ``n`` rows written: point [m], beam time [s], corrected range
        [m], nod [rad], step, scan, mirror index, projected as lifted.

    Returns
    -------
    (n, n_ok, n_no_nod, n_moving, n_blocked) : the kept points and the drop counts.
    """
    n = 0
    n_ok = 0
    n_no_nod = 0
    n_moving = 0
    n_blocked = 0
    j_nod = 0
    j_lift0 = 0
    j_lift1 = 0
    j_pose = 0
    correct = range_offset != 0.0 or range_scale != 0.0
    for b in range(ranges.size):
        r = ranges[b]
        if not (r > 0.0 and r < math.inf):
            continue
        n_ok += 1
        i = steps[b] - step_min
        t = scan_time[scan[b]] + step_dt[i]
        nod, j_nod = _interp(nod_t, nod_a, t, nod_mode, j_nod)
        if not (nod == nod):
            n_no_nod += 1
            continue
        side = step_side[i]
        state = DEPLOYED
        if side >= 0:
            state = side_mode[side]
            if state < 0:
                if side == 0:
                    lift, j_lift0 = _interp(lift_t0, lift_a0, t, NAN, j_lift0)
                else:
                    lift, j_lift1 = _interp(lift_t1, lift_a1, t, NAN, j_lift1)
                state = _state(lift, bands[side, 0], bands[side, 1], bands[side, 2])
        if state == BETWEEN:
            n_moving += 1
            continue
        if state == DEPLOYED and not clear[i]:
            n_blocked += 1
            continue
        if correct:
            r = (r - range_offset) / (1.0 + range_scale)
        k = i + n_steps if state == LIFTED else i
        row = rows[k]
        # BeamColumns.project: a + b r, or along the outgoing beam when r stops short of
        # the mirror; both relative to the pivot
        if r < row[6]:
            x = row[7] * r - row[10]
            y = row[8] * r - row[11]
            z = row[9] * r - row[12]
        else:
            x = row[0] + row[3] * r
            y = row[1] + row[4] * r
            z = row[2] + row[5] * r
        c, s = cos_sin(nod)
        # the nod R_y(nod) about the pivot (geometry.pitch_about_pivot)
        x, z = c * x + s * z, c * z - s * x
        x += row[10]
        y += row[11]
        z += row[12]
        if frame_mode >= 1:
            x, y, z = (robot[0, 0] * x + robot[0, 1] * y + robot[0, 2] * z + robot[0, 3],
                       robot[1, 0] * x + robot[1, 1] * y + robot[1, 2] * z + robot[1, 3],
                       robot[2, 0] * x + robot[2, 1] * y + robot[2, 2] * z + robot[2, 3])
        if frame_mode == 2:
            x, y, z, j_pose = _pose(pose_t, pose_seg, t, x, y, z, j_pose)
        xyz[n, 0] = x
        xyz[n, 1] = y
        xyz[n, 2] = z
        t_out[n] = t
        r_out[n] = r
        nod_out[n] = nod
        step_out[n] = steps[b]
        scan_out[n] = scan[b]
        mirror_out[n] = row_mirror[k]
        lifted_out[n] = state == LIFTED
        n += 1
    return n, n_ok, n_no_nod, n_moving, n_blocked


@_jit
def apply_poses(pose_t, pose_seg, t, xyz):
    """Points ``xyz`` (n, 3) float64 [m] in the robot frame at times ``t`` (n,) [s] ->
    world frame, in place, by the pose track (keyframe times ``pose_t`` (k,) [s], table
    ``pose_seg``, :data:`SEG`): the same slerp as :func:`assemble_points`."""
    j = 0
    for p in range(t.size):
        xyz[p, 0], xyz[p, 1], xyz[p, 2], j = _pose(pose_t, pose_seg, t[p], xyz[p, 0],
                                                   xyz[p, 1], xyz[p, 2], j)


@_jit
def apply_transforms(T, xyz):
    """Points ``xyz`` (n, 3) float64 [m] mapped by per-point rigid transforms ``T``
    (n, 4, 4) float64, in place (a per-point ``world_from_robot`` callable's poses)."""
    for p in range(xyz.shape[0]):
        x, y, z = xyz[p, 0], xyz[p, 1], xyz[p, 2]
        for j in range(3):
            xyz[p, j] = T[p, j, 0] * x + T[p, j, 1] * y + T[p, j, 2] * z + T[p, j, 3]


@_jit
def interp_angles(ts, a, q, mode, out):
    """Angles [rad] at times ``q`` (n,) float64 [s] from samples ``ts``, ``a`` (k,)
    float64 (strictly increasing times) into ``out`` (n,) float64: the interpolation
    :func:`assemble_points` applies per beam (``mode`` NAN, CLAMP or EXTRAPOLATE outside
    the samples), for :meth:`~nodlidar.runtime.assembly.AngleSamples.at`."""
    j = 0
    for p in range(q.size):
        out[p], j = _interp(ts, a, q[p], mode, j)


@_jit
def mirror_states(angle, deployed, lifted, tol, out):
    """States (DEPLOYED, LIFTED, BETWEEN) of lift-servo angles ``angle`` (n,) float64
    [rad] against the end angles ``deployed``, ``lifted`` and ``tol`` [rad] into ``out``
    (n,) int8: the classification :func:`assemble_points` applies per beam."""
    for p in range(angle.size):
        out[p] = _state(angle[p], deployed, lifted, tol)
