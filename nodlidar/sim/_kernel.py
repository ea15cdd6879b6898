"""Compiled per-beam kernels of the simulator (:mod:`nodlidar.sim.raycast`), issue 16.

A scan is ~700 beams; in numpy its per-beam work (world rays, float32 ray preparation for
embree, float64 distances from the triangles' planes, the movers' per-beam positions and
bounding-sphere cull, truth, noise and mm rounding) was about a hundred array calls of a
few microseconds each. Here each stage is one loop over the beams. Embree still casts
the triangles (the raycast module calls it between these kernels).

Every kernel is ``@numba.njit(cache=True, nogil=True)`` (compiled once per machine into the
numba cache; no fastmath, so IEEE order of operations is as written) and takes plain
float64 / int64 / bool arrays: rays are ``(n, 3)`` C-ordered rows because that is what
embree takes and :class:`~nodlidar.sim.raycast.ScanTruth` returns. Units: metres,
seconds, radians. The formulas are those of :mod:`nodlidar.geometry` (Rodrigues,
reflection, the nod pitch), of trimesh's ``intersects_first`` ray preparation and of
:mod:`nodlidar.sim.scene`'s trajectories, operation for operation (tests/test_sim_kernel.py
compares each with its numpy original).

This module imports numba; only the simulator imports it (never ``import nodlidar``).
"""

from __future__ import annotations

import numba
import numpy as np

from .._compiled_geometry import reflect as _reflect
from .._compiled_geometry import rodrigues as _rodrigues

__all__ = [
    "TRAJ_FIXED",
    "TRAJ_CONSTANT_VELOCITY",
    "TRAJ_BACK_AND_FORTH",
    "rodrigues",
    "reflect",
    "world_rays",
    "embree_rays",
    "first_hits",
    "mover_positions",
    "mover_rays",
    "merge_closer",
    "mirror_rays",
    "mirror_update",
    "bounce",
    "measure",
    "scan_truth",
]

_jit = numba.njit(cache=True, nogil=True)

#: trajectory kinds of :func:`mover_positions` (scene.Fixed, ConstantVelocity, BackAndForth)
TRAJ_FIXED = 0
TRAJ_CONSTANT_VELOCITY = 1
TRAJ_BACK_AND_FORTH = 2

# trimesh.util.unitize's zero threshold (trimesh.constants.tol.zero)
_UNIT_ZERO = 1e-13
# |d . n| below this: the ray runs along the triangle's plane (no distance)
_DEN_MIN = 1e-12


# -- scalar formulas (inlined into the loops) ---------------------------------------------
@_jit
def _meets_sphere(ox, oy, oz, dx, dy, dz, centre, radius2):
    """The half-line from o along d meets the ball of squared radius ``radius2`` about
    ``centre (3,)``: the centre's squared distance from the line is ``ww - wd^2/dd``; a
    ball behind the origin (wd < 0) is met only if the origin is inside it."""
    wx, wy, wz = centre[0] - ox, centre[1] - oy, centre[2] - oz
    wd = wx * dx + wy * dy + wz * dz
    dd = dx * dx + dy * dy + dz * dz
    ww = wx * wx + wy * wy + wz * wz
    return (ww * dd - wd * wd <= radius2 * dd) and (wd >= 0 or ww <= radius2)


@_jit
def _embree_row(o32, d32, j, ox, oy, oz, dx, dy, dz, origin, scale):
    """Row ``j`` of embree's float32 rays, exactly as trimesh prepares them:
    ``intersects_first`` casts to float32 and unitizes (float32 squares, float64 norm),
    ``_EmbreeWrap.run`` shifts/scales the float32 origin in float64 and casts back."""
    fx, fy, fz = np.float32(dx), np.float32(dy), np.float32(dz)
    sq = np.float64(fx * fx) + np.float64(fy * fy) + np.float64(fz * fz)
    norm = np.sqrt(sq)
    inv = 1.0 / norm if norm > _UNIT_ZERO else norm
    d32[j, 0] = np.float32(np.float64(fx) * inv)
    d32[j, 1] = np.float32(np.float64(fy) * inv)
    d32[j, 2] = np.float32(np.float64(fz) * inv)
    o32[j, 0] = np.float32((np.float64(np.float32(ox)) - origin[0]) * scale)
    o32[j, 1] = np.float32((np.float64(np.float32(oy)) - origin[1]) * scale)
    o32[j, 2] = np.float32((np.float64(np.float32(oz)) - origin[2]) * scale)


@_jit
def _plane_t(ox, oy, oz, dx, dy, dz, tri, normals, offset):
    """float64 distance along d from o to triangle ``tri``'s plane ``x . n = offset``
    (inf when the ray runs along the plane)."""
    nx, ny, nz = normals[tri, 0], normals[tri, 1], normals[tri, 2]
    num = offset[tri] - (ox * nx + oy * ny + oz * nz)
    den = dx * nx + dy * ny + dz * nz
    return num / den if abs(den) > _DEN_MIN else np.inf


@_jit
def _measure_one(r, z, noise, near_m, knee_m, rel):
    """LidarModel.range_sigma_m noise (``z`` a standard normal draw) and mm rounding of
    one true range [m]; not finite -> NaN."""
    if not np.isfinite(r):
        return np.nan
    if noise:
        sig = near_m if r <= knee_m else rel * r
        r = r + z * sig
    return np.rint(r * 1000.0) / 1000.0


# -- array kernels ---------------------------------------------------------------------
# (rodrigues, reflect and mover_positions are the scalar helpers the fused kernels use, on
# arrays: tests/test_sim_kernel.py checks the helpers through them)
@_jit
def rodrigues(v, axis, c, s):
    """geometry.rotate_about_axis row by row: ``v (n, 3)`` about unit ``axis (n, 3)`` by
    the angles whose cosine and sine are ``c, s (n,)``. Returns ``(n, 3)``."""
    out = np.empty_like(v)
    for i in range(v.shape[0]):
        out[i, 0], out[i, 1], out[i, 2] = _rodrigues(v[i, 0], v[i, 1], v[i, 2], axis[i, 0],
                                                     axis[i, 1], axis[i, 2], c[i], s[i])
    return out


@_jit
def reflect(d, nrm):
    """geometry.reflect row by row: ``d - 2 (d.n) n``, ``d, nrm (n, 3)`` -> ``(n, 3)``."""
    out = np.empty_like(d)
    for i in range(d.shape[0]):
        out[i, 0], out[i, 1], out[i, 2] = _reflect(d[i, 0], d[i, 1], d[i, 2], nrm[i, 0],
                                                   nrm[i, 1], nrm[i, 2])
    return out


@_jit
def world_rays(rel, d_head, pivot, cos_nod, sin_nod, t, rot, position, velocity, t0, origin, scale):
    """Head-frame rays at per-beam nod and time -> world rays, also prepared for embree.

    ``rel (n, 3)``: start points relative to the nod pivot [m]; ``d_head (n, 3)``: unit
    directions; ``pivot (3,)`` [m]; ``cos_nod, sin_nod (n,)``: cosine and sine of each
    beam's nod (numpy's ``np.cos``/``np.sin``, as geometry.pitch_about_pivot takes them:
    the same last bits, and vectorised); ``t (n,)`` [s]; the sensor pose
    ``p_w = rot (3, 3) p_s + position (3,) + (t - t0) velocity (3,)``; ``origin (3,)``,
    ``scale``: the static embree scene's shift and scale (see :func:`embree_rays`).
    The nod is geometry.pitch_about_pivot (``R_y(nod)`` about the pivot), the pose
    scene.SensorPose.to_world. Returns ``origins (n, 3) [m], directions (n, 3)`` and the
    same as embree's float32 ``o32, d32 (n, 3)``.
    """
    n = rel.shape[0]
    o = np.empty((n, 3))
    d = np.empty((n, 3))
    o32 = np.empty((n, 3), dtype=np.float32)
    d32 = np.empty((n, 3), dtype=np.float32)
    # the constants in locals: the compiler cannot know the outputs do not alias them
    r00, r01, r02 = rot[0, 0], rot[0, 1], rot[0, 2]
    r10, r11, r12 = rot[1, 0], rot[1, 1], rot[1, 2]
    r20, r21, r22 = rot[2, 0], rot[2, 1], rot[2, 2]
    cx, cy, cz = pivot[0], pivot[1], pivot[2]
    for i in range(n):
        c, s = cos_nod[i], sin_nod[i]
        x, y, z = rel[i, 0], rel[i, 1], rel[i, 2]
        px = c * x + s * z + cx
        py = y + cy
        pz = -s * x + c * z + cz
        x, y, z = d_head[i, 0], d_head[i, 1], d_head[i, 2]
        qx = c * x + s * z
        qy = y
        qz = -s * x + c * z
        dt = t[i] - t0
        ox = (px * r00 + py * r01 + pz * r02) + (position[0] + dt * velocity[0])
        oy = (px * r10 + py * r11 + pz * r12) + (position[1] + dt * velocity[1])
        oz = (px * r20 + py * r21 + pz * r22) + (position[2] + dt * velocity[2])
        dx = qx * r00 + qy * r01 + qz * r02
        dy = qx * r10 + qy * r11 + qz * r12
        dz = qx * r20 + qy * r21 + qz * r22
        o[i, 0], o[i, 1], o[i, 2] = ox, oy, oz
        d[i, 0], d[i, 1], d[i, 2] = dx, dy, dz
        _embree_row(o32, d32, i, ox, oy, oz, dx, dy, dz, origin, scale)
    return o, d, o32, d32


@_jit
def embree_rays(o, d, origin, scale):
    """Every ray ``o, d (n, 3)`` as embree's float32 ``(n, 3)`` origins and directions of a
    trimesh scene shifted by ``origin (3,)`` and scaled by ``scale``."""
    n = o.shape[0]
    o32 = np.empty((n, 3), dtype=np.float32)
    d32 = np.empty((n, 3), dtype=np.float32)
    for i in range(n):
        _embree_row(o32, d32, i, o[i, 0], o[i, 1], o[i, 2], d[i, 0], d[i, 1], d[i, 2],
                    origin, scale)
    return o32, d32


@_jit
def first_hits(o, d, tri, normals, offset, face_part, object_id):
    """One mesh's hits as the scan's first nearest hits: rays ``o, d (n, 3)`` hit triangle
    ``tri (n,)`` (-1 none) of planes ``normals (T, 3)``, ``offset (T,)``, triangle ``k``
    belonging to part ``face_part[k]``. Returns ``(dist (n,) [m] float64, inf none;
    obj (n,) object_id or -1; part (n,) or -1)``."""
    n = tri.shape[0]
    dist = np.full(n, np.inf)
    obj = np.full(n, -1, dtype=np.int64)
    part = np.full(n, -1, dtype=np.int64)
    for i in range(n):
        if tri[i] < 0:
            continue
        t = _plane_t(o[i, 0], o[i, 1], o[i, 2], d[i, 0], d[i, 1], d[i, 2], tri[i], normals, offset)
        if np.isfinite(t):
            dist[i] = t
            obj[i] = object_id
            part[i] = face_part[tri[i]]
    return dist, obj, part


@_jit
def _position(kind, p0, p1, leg_s, t0, t, out):
    """One trajectory point ``out (3,)`` [m] at ``t`` [s]: Fixed (p0), ConstantVelocity
    (``p0 + (t - t0) p1``, p1 the velocity) or BackAndForth (p0 -> p1 -> p0, one leg in
    ``leg_s`` [s]), the formulas of scene.py."""
    if kind == TRAJ_FIXED:
        for j in range(3):
            out[j] = p0[j]
    elif kind == TRAJ_CONSTANT_VELOCITY:
        dt = t - t0
        for j in range(3):
            out[j] = p0[j] + dt * p1[j]
    else:
        ph = (t - t0) % (2 * leg_s)  # Python/np.mod semantics: in [0, 2 leg)
        frac = (ph if ph < leg_s else 2 * leg_s - ph) / leg_s
        for j in range(3):
            out[j] = p0[j] + frac * (p1[j] - p0[j])


@_jit
def mover_positions(kind, p0, p1, leg_s, t0, t):
    """Trajectory points ``(n, 3)`` [m] at times ``t (n,)`` [s] (see ``_position``)."""
    out = np.empty((t.shape[0], 3))
    for i in range(t.shape[0]):
        _position(kind, p0, p1, leg_s, t0, t[i], out[i])
    return out


@_jit
def mover_rays(o, d, t, kind, p0, p1, leg_s, t0, speed, pos, centre, radius2, origin, scale):
    """World rays ``o, d (n, 3)`` at times ``t (n,)`` [s] in a rigidly translating mover's
    frame (``o - position(t)``), culled to those meeting its bounding sphere (``centre
    (3,)``, squared radius [m^2]). The position is the trajectory ``kind, p0, p1, leg_s, t0``
    (see ``_position``) moving at most at ``speed`` [m/s], or for ``kind < 0`` given per
    ray in ``pos (n, 3)`` [m].
    Returns ``(index (m,), origins in the mover frame (m, 3) float64, o32 (m, 3),
    d32 (m, 3))`` (embree rays of the mover's scene: ``origin (3,)``, ``scale``).

    A trajectory's positions over the rays' times lie within ``speed (t_max - t_min) / 2``
    of its position at the middle time, so a ray that misses the sphere grown by that
    (and 1 um for rounding) about the middle position misses every per-ray sphere: only
    the rays that meet it get their own position (the trajectory's mod is the costly part).
    """
    n = o.shape[0]
    idx = np.empty(n, dtype=np.int64)
    om = np.empty((n, 3))
    p = np.empty(3)
    pm = np.zeros(3)
    swept2 = np.inf
    if kind >= 0 and n > 0:
        lo, hi = t[0], t[0]
        for i in range(n):
            lo, hi = min(lo, t[i]), max(hi, t[i])
        _position(kind, p0, p1, leg_s, t0, 0.5 * (lo + hi), pm)
        grow = np.sqrt(radius2) + speed * 0.5 * (hi - lo) + 1e-6
        swept2 = grow * grow
    m = 0
    for i in range(n):
        if kind < 0:
            p[0], p[1], p[2] = pos[i, 0], pos[i, 1], pos[i, 2]
        elif not _meets_sphere(o[i, 0] - pm[0], o[i, 1] - pm[1], o[i, 2] - pm[2], d[i, 0],
                               d[i, 1], d[i, 2], centre, swept2):
            continue
        else:
            _position(kind, p0, p1, leg_s, t0, t[i], p)
        x, y, z = o[i, 0] - p[0], o[i, 1] - p[1], o[i, 2] - p[2]
        if _meets_sphere(x, y, z, d[i, 0], d[i, 1], d[i, 2], centre, radius2):
            idx[m] = i
            om[m, 0], om[m, 1], om[m, 2] = x, y, z
            m += 1
    o32 = np.empty((m, 3), dtype=np.float32)
    d32 = np.empty((m, 3), dtype=np.float32)
    for j in range(m):
        i = idx[j]
        _embree_row(o32, d32, j, om[j, 0], om[j, 1], om[j, 2], d[i, 0], d[i, 1], d[i, 2],
                    origin, scale)
    return idx[:m].copy(), om[:m].copy(), o32, d32


@_jit
def merge_closer(idx, o, d, tri, normals, offset, object_id, dist, obj, part):
    """A mover's hits into the scan's nearest hits, in place: ray ``idx[j]`` (origin
    ``o[j]`` in the mover frame, direction ``d[idx[j]]``) hit triangle ``tri[j]``; where its
    float64 distance is below ``dist``, set ``dist``, ``obj = object_id``, ``part = -1``."""
    for j in range(idx.shape[0]):
        if tri[j] < 0:
            continue
        i = idx[j]
        t = _plane_t(o[j, 0], o[j, 1], o[j, 2], d[i, 0], d[i, 1], d[i, 2], tri[j], normals, offset)
        if t < dist[i]:
            dist[i] = t
            obj[i] = object_id
            part[i] = -1


@_jit
def mirror_rays(o, d, alive, last, mirror, window_centre, window_r2, axis_point, axis, c, s,
                normal, centre, radius2, origin, scale):
    """Head-frame rays ``o, d (n, 3)`` that may meet mirror ``mirror``, in its unturned frame.

    The live rays (``alive (n,)``) not just reflected by it (``last (n,) != mirror``) that
    meet its beam window (a ball about ``window_centre (3,)``, squared radius
    ``window_r2`` [m^2], holding the glass at every lift angle: turning a ray about the lift
    axis does not change its distance from the centre) are turned back about the lift axis
    (``axis_point (3,)``, unit ``axis (3,)``) by the beam's lift angle, whose cosine and sine
    are ``c, s (n,)`` (geometry.rotate_about_line / rotate_about_axis by ``-angle``), and
    kept if they meet the glass mesh's bounding sphere (``centre``, ``radius2``). The glass
    normal ``normal (3,)`` is turned forward by the same angle.
    Returns ``(index (m,), origins (m, 3), directions (m, 3) in the unturned frame,
    turned normals (m, 3), o32 (m, 3), d32 (m, 3))`` (embree rays of the glass mesh).
    """
    n = o.shape[0]
    idx = np.empty(n, dtype=np.int64)
    ol = np.empty((n, 3))
    dl = np.empty((n, 3))
    nrm = np.empty((n, 3))
    px, py, pz = axis_point[0], axis_point[1], axis_point[2]
    kx, ky, kz = axis[0], axis[1], axis[2]
    m = 0
    for i in range(n):
        if not alive[i] or last[i] == mirror:
            continue
        if not _meets_sphere(o[i, 0], o[i, 1], o[i, 2], d[i, 0], d[i, 1], d[i, 2],
                             window_centre, window_r2):
            continue
        x, y, z = _rodrigues(o[i, 0] - px, o[i, 1] - py, o[i, 2] - pz, kx, ky, kz, c[i], -s[i])
        x, y, z = px + x, py + y, pz + z
        u, v, w = _rodrigues(d[i, 0], d[i, 1], d[i, 2], kx, ky, kz, c[i], -s[i])
        if not _meets_sphere(x, y, z, u, v, w, centre, radius2):
            continue
        idx[m] = i
        ol[m, 0], ol[m, 1], ol[m, 2] = x, y, z
        dl[m, 0], dl[m, 1], dl[m, 2] = u, v, w
        nrm[m, 0], nrm[m, 1], nrm[m, 2] = _rodrigues(normal[0], normal[1], normal[2], kx, ky,
                                                     kz, c[i], s[i])
        m += 1
    o32 = np.empty((m, 3), dtype=np.float32)
    d32 = np.empty((m, 3), dtype=np.float32)
    for j in range(m):
        _embree_row(o32, d32, j, ol[j, 0], ol[j, 1], ol[j, 2], dl[j, 0], dl[j, 1], dl[j, 2],
                    origin, scale)
    return idx[:m].copy(), ol[:m].copy(), dl[:m].copy(), nrm[:m].copy(), o32, d32


@_jit
def mirror_update(idx, ol, dl, nrm, tri, normals, offset, mirror, best_t, best_m, best_nrm):
    """Mirror ``mirror``'s hits into the nearest mirror hit of each ray, in place: ray
    ``idx[j]`` (``ol, dl (m, 3)`` in the unturned frame) hit triangle ``tri[j]`` (-1 none)
    of the glass (``normals (2, 3)``, ``offset (2,)``); a hit ahead (distance > 0) nearer
    than ``best_t (n,)`` [m] sets ``best_t``, ``best_m`` and the turned normal ``best_nrm``."""
    for j in range(idx.shape[0]):
        if tri[j] < 0:
            continue
        t = _plane_t(ol[j, 0], ol[j, 1], ol[j, 2], dl[j, 0], dl[j, 1], dl[j, 2], tri[j],
                     normals, offset)
        i = idx[j]
        if t > 0 and t < best_t[i]:
            best_t[i] = t
            best_m[i] = mirror
            best_nrm[i, 0], best_nrm[i, 1], best_nrm[i, 2] = nrm[j, 0], nrm[j, 1], nrm[j, 2]


@_jit
def bounce(o, d, off, first, bounces, alive, last, best_t, best_m, best_nrm, housed):
    """One mirror bounce of head-frame rays, in place on ``o, d (n, 3)``, path offset
    ``off (n,)`` [m], ``first, bounces, last (n,)``, ``alive (n,)``.

    Rays ``housed (n,)`` (reflected into the lidar's housing before their mirror) die; a ray
    with a mirror hit at ``best_t`` [m] (mirror ``best_m``, normal ``best_nrm (n, 3)``) on the
    glass's back (``d . n >= 0``) is absorbed, on its front it moves to the hit, reflects
    (geometry.reflect: ``d - 2 (d.n) n``) and counts the bounce. Returns whether any ray
    had a mirror hit."""
    any_hit = False
    for i in range(o.shape[0]):
        if housed[i]:
            alive[i] = False
            continue
        t = best_t[i]
        if not np.isfinite(t):
            continue
        any_hit = True
        nx, ny, nz = best_nrm[i, 0], best_nrm[i, 1], best_nrm[i, 2]
        dn = d[i, 0] * nx + d[i, 1] * ny + d[i, 2] * nz
        if not dn < 0:
            alive[i] = False
            continue
        o[i, 0], o[i, 1], o[i, 2] = o[i, 0] + t * d[i, 0], o[i, 1] + t * d[i, 1], o[i, 2] + t * d[i, 2]
        off[i] = off[i] + t
        d[i, 0], d[i, 1], d[i, 2] = _reflect(d[i, 0], d[i, 1], d[i, 2], nx, ny, nz)
        if first[i] < 0:
            first[i] = best_m[i]
        bounces[i] += 1
        last[i] = best_m[i]
    return any_hit


@_jit
def measure(r, z, noise, near_m, knee_m, rel):
    """The URG measurement of true ranges ``r (n,)`` [m] with standard normal draws
    ``z (n,)`` (unused if not ``noise``): ``r + z sigma(r)`` rounded to the mm, sigma
    ``near_m`` up to ``knee_m`` and ``rel r`` beyond (LidarModel.range_sigma_m); NaN where
    ``r`` is not finite."""
    out = np.empty(r.shape[0])
    for i in range(r.shape[0]):
        out[i] = _measure_one(r[i], z[i] if noise else 0.0, noise, near_m, knee_m, rel)
    return out


@_jit
def scan_truth(alive, dist, off, o, d, obj, part, z, noise, near_m, knee_m, rel):
    """Per-beam truth of one scan from its world rays ``o, d (n, 3)``, their nearest hits
    ``dist (n,)`` [m] (inf none), ``obj, part (n,)`` and head-path offsets ``off (n,)`` [m];
    ``alive (n,)`` false: no return. Returns ``(true range (n,) [m] NaN none, reported
    range (n,) [m], object id (n,), part (n,), hit point (n, 3) [m] NaN none)``."""
    n = dist.shape[0]
    true_r = np.empty(n)
    r = np.empty(n)
    obj_out = np.empty(n, dtype=np.int64)
    part_out = np.empty(n, dtype=np.int64)
    pts = np.empty((n, 3))
    for i in range(n):
        if alive[i] and np.isfinite(dist[i]):
            true_r[i] = off[i] + dist[i]
            for j in range(3):
                pts[i, j] = o[i, j] + dist[i] * d[i, j]
            obj_out[i] = obj[i]
            part_out[i] = part[i]
        else:
            true_r[i] = np.nan
            pts[i, 0] = pts[i, 1] = pts[i, 2] = np.nan
            obj_out[i] = -1
            part_out[i] = -1
        r[i] = _measure_one(true_r[i], z[i] if noise else 0.0, noise, near_m, knee_m, rel)
    return true_r, r, obj_out, part_out, pts
