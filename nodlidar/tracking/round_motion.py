"""A round object's motion from its outline: a moving circle fitted to a window's points.

The entropy refinement (:mod:`nodlidar.tracking.motion`) aligns a window's slices with one
another and needs no model of the object's shape; that is its strength, and where a slice
is cut (an object entering a mirror's view, the floor under the scan line) it is its
weakness: the cut end moves with the sensor, not with the object, and the alignment of the
rest reads the speed across the cut weakly (docs/tracking.md, "A cut object's speed across
the cut is weakly determined": 10-20 deg off for a person entering the view). A vertical
cylinder - a person, a post, the paper's target - projects onto the ground plane as a circle
whatever part of it a scan sees, so its centre moves with the object even when every slice
is cut.

Model, on the ground plane, for the points ``p_i`` (seen at ``t_i``) of a window::

    | p_i - c_k(i) - v (t_i - t_ref) | = R

with one velocity ``v`` and radius ``R`` for the window and one centre ``c_k`` per label
``k`` (the mirror window the point was seen through): a mirror's small calibration error
shifts its points rigidly, and a centre per window absorbs the shift instead of reading it
as motion when the object passes from one window to the next.

Fitted by Gauss-Newton with Huber weights on the residuals normalised by each point's
range noise ``sigma_i``; started from an algebraic (Kasa) circle through the points moved
back along a start velocity. The result says how well a circle explains the points
(``rms_norm``, the normalised residuals' RMS: about 1 or below for a cylinder, since a
beam's range noise reaches the circle's normal at ``|cos incidence| <= 1`` of it) and how
well the window determines the velocity (``cov``); the caller decides whether to use it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike

__all__ = ["RoundFit", "fit_moving_circle"]


@dataclass(frozen=True)
class RoundFit:
    """A moving circle fitted to a window (:func:`fit_moving_circle`).

    Attributes
    ----------
    velocity : (2,) float
        Ground-plane velocity [m/s].
    radius_m : float
        Radius [m].
    cov : (2, 2) float
        Covariance of ``velocity`` [m^2/s^2] (Gauss-Newton, the residuals' own scale).
    rms_norm : float
        RMS of the residuals divided by each point's range noise (1: as noisy as the lidar).
    serial : float
        Correlation of consecutive points' normalised residuals (neighbours along one
        scan's slice, same window): about 0 where the circle leaves only the range noise,
        towards 1 where it leaves a shape (a box's corner and faces).
    n_points : int
    labels : (K,) int
        The windows' labels, sorted.
    centres : (K, 2) float
        Each window's centre at ``t_ref_s`` [m].
    t_ref_s : float
        The reference time of ``centres`` [s].
    """

    velocity: np.ndarray
    radius_m: float
    cov: np.ndarray
    rms_norm: float
    serial: float
    n_points: int
    labels: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    centres: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    t_ref_s: float = 0.0


def _kasa(p: np.ndarray, dt: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, float] | None:
    """Algebraic (Kasa) circle through ``p`` (n, 2) [m] moved back to the reference time at
    ``v`` (2,) [m/s] (``dt`` (n,) [s]): centre (2,) and radius, None if degenerate. By its
    3 x 3 normal equations, from one compiled pass: only Gauss-Newton's start, and cheap."""
    from ._kernel import circle_start_sums  # numba: loaded when first used

    n, sx, sy, sxx, sxy, syy, sxz, syz, sz = circle_start_sums(p, dt, v)
    M = np.array([[4 * sxx, 4 * sxy, 2 * sx], [4 * sxy, 4 * syy, 2 * sy], [2 * sx, 2 * sy, n]])
    try:
        sol = np.linalg.solve(M, np.array([2 * sxz, 2 * syz, sz]))
    except np.linalg.LinAlgError:
        return None
    c = sol[:2]
    r2 = sol[2] + c @ c
    if not (np.all(np.isfinite(sol)) and r2 > 0):
        return None
    return c + (p[0] - v * dt[0]), float(np.sqrt(r2))  # the sums were about the first point


def fit_moving_circle(points_xy: ArrayLike, t_s: ArrayLike, t_ref_s: float,
                      velocity0: ArrayLike, sigma_m: ArrayLike,
                      labels: ArrayLike | None = None, scans: ArrayLike | None = None,
                      max_radius_m: float = 2.0, max_points: int = 5000,
                      iterations: int = 12, huber: float = 2.0,
                      start: RoundFit | None = None) -> RoundFit | None:
    """Fit a circle of constant radius moving at constant velocity to a window's points.

    Parameters
    ----------
    points_xy : (n, 2) float
        Ground-plane points [m].
    t_s : (n,) float
        Their times [s].
    t_ref_s : float
        Reference time [s] (the centres are at it).
    velocity0 : (2,) float
        Start velocity [m/s] (the entropy estimate, or the centroid line).
    sigma_m : (n,) float or float
        Each point's range noise (1 sd) [m], > 0.
    labels : (n,) int, optional
        A centre per label (the mirror window); None: one centre.
    scans : (n,) int, optional
        Each point's scan, the points of a scan in beam order (for ``serial``); None: by
        time, a new scan wherever the time steps back or by more than 10 ms.
    max_radius_m : float
        A start circle wider than this [m] is no round object (a flat face): None.
    max_points : int
        At most this many points, evenly spaced in their order, enter the fit: bounds its
        cost. Not fewer: a slow mover's heading needs the whole window's precision (the
        paper's cylinder at 0.05 m/s, mirrors, seed 1: windows of 2000-3000 points read up
        to 2.9 deg off from 500 of them, 1.4 deg from all, and it converged at scan 23
        instead of 8; the convergence tolerance is 2 deg).
    iterations : int
        Gauss-Newton steps (stops earlier once the step is below 0.1 mm, 0.1 mm/s).
    huber : float
        Huber threshold on the normalised residual (robust to a stray point).
    start : RoundFit, optional
        A previous fit of the same object (the last scan's window) to start from: its
        radius, velocity and centres, moved to ``t_ref_s`` at its velocity. Used where it
        has a centre for every label here; else the algebraic start. Gauss-Newton then
        needs fewer steps to the same minimum. Where the fit from it fails (diverges, a
        singular system), the fit is made again from the algebraic start: a start only
        saves steps, it never loses a fit.

    Returns
    -------
    RoundFit or None
        None where the points do not determine a circle (too few, a degenerate start, or
        a singular system).
    """
    fit = _fit(points_xy, t_s, t_ref_s, velocity0, sigma_m, labels, scans, max_radius_m,
               max_points, iterations, huber, start)
    if fit is None and start is not None:
        # rare: on five scenes with mirrors 12 of 573 warm fits failed, and 1 of those
        # fitted from the algebraic start
        fit = _fit(points_xy, t_s, t_ref_s, velocity0, sigma_m, labels, scans, max_radius_m,
                   max_points, iterations, huber, None)
    return fit


def _fit(points_xy: ArrayLike, t_s: ArrayLike, t_ref_s: float, velocity0: ArrayLike,
         sigma_m: ArrayLike, labels: ArrayLike | None, scans: ArrayLike | None,
         max_radius_m: float, max_points: int, iterations: int, huber: float,
         start: RoundFit | None) -> RoundFit | None:
    """:func:`fit_moving_circle` from ``start`` (None: the algebraic start) only."""
    p = np.asarray(points_xy, float).reshape(-1, 2)
    dt = np.asarray(t_s, float).reshape(-1) - float(t_ref_s)
    sig = np.broadcast_to(np.asarray(sigma_m, float), dt.shape)
    v = np.asarray(velocity0, float).reshape(2).copy()
    lab = np.zeros(len(p), int) if labels is None else np.asarray(labels).reshape(-1)
    scan_of = None if scans is None else np.asarray(scans).reshape(-1)
    if len(p) > max_points >= 1:
        take = np.unique(np.linspace(0, len(p) - 1, max_points).round().astype(int))
        p, dt, sig, lab = p[take], dt[take], sig[take], lab[take]
        scan_of = None if scan_of is None else scan_of[take]
    if len(lab):  # np.unique's labels and inverse, by counting (labels are a few small ints)
        lo = int(lab.min())
        present = np.bincount(lab - lo) > 0
        keys = np.flatnonzero(present) + lo
        k = (np.cumsum(present) - 1)[lab - lo]
    else:
        keys, k = np.zeros(0, int), np.zeros(0, int)
    K = len(keys)
    if len(p) < 3 * K + 3 + 2:
        return None
    p, dt, sig = np.ascontiguousarray(p), np.ascontiguousarray(dt), np.ascontiguousarray(sig)
    k = np.ascontiguousarray(k, dtype=np.int64)
    # the start's centre for each label here (searchsorted: its labels are sorted)
    at = np.zeros(0, int) if start is None else np.minimum(
        np.searchsorted(start.labels, keys), max(len(start.labels) - 1, 0))
    if start is not None and len(start.labels) and np.array_equal(start.labels[at], keys):
        v = np.asarray(start.velocity, float).copy()
        c = start.centres[at] + (float(t_ref_s) - start.t_ref_s) * v
        R = start.radius_m
    else:
        kasa = _kasa(p, dt, v)
        if kasa is None or kasa[1] > max_radius_m:
            return None
        # every window starts at the common circle: their shifts are millimetres to
        # centimetres, well inside Gauss-Newton's reach (a circle per window cost a
        # least-squares solve each)
        c = np.repeat(kasa[0][None], K, axis=0)
        R = kasa[1]
    # numba: loaded when first used
    from ._kernel import circle_normal_equations, circle_residual_stats

    n_par = 2 * K + 3
    Ak, gk = np.zeros((K, 5, 5)), np.zeros((K, 5))
    for _ in range(max(iterations, 1)):  # at least one: the covariance is its system's
        # per window, over (its centre, v, R): a centre touches its own points only
        circle_normal_equations(p, dt, sig, k, c, v, float(R), huber, Ak, gk)
        A = np.zeros((n_par, n_par))
        g = np.zeros(n_par)
        for kk in range(K):
            cs = slice(2 * kk, 2 * kk + 2)
            A[cs, cs] = Ak[kk, :2, :2]
            A[cs, 2 * K:] = Ak[kk, :2, 2:]
            A[2 * K:, cs] = Ak[kk, 2:, :2]
            A[2 * K:, 2 * K:] += Ak[kk, 2:, 2:]
            g[cs] = gk[kk, :2]
            g[2 * K:] += gk[kk, 2:]
        try:
            step = -np.linalg.solve(A, g)
        except np.linalg.LinAlgError:
            return None
        if not np.all(np.isfinite(step)):
            return None
        c = c + step[:2 * K].reshape(K, 2)
        v = v + step[2 * K:2 * K + 2]
        R = R + step[-1]
        if not 0 < R <= 10 * max_radius_m:
            return None  # diverged: no circle explains these points
        if np.max(np.abs(step)) < 1e-4:
            break
    if scan_of is None:  # a new scan wherever the time steps back or by 10 ms or more
        gap = np.diff(dt)
        scan_of = np.concatenate([[0], np.cumsum(~((gap >= 0) & (gap < 0.01)))])
    rr, rs, m = circle_residual_stats(p, dt, sig, k, c, v, float(R),
                                      np.ascontiguousarray(scan_of, dtype=np.int64))
    rms = float(np.sqrt(rr / len(p)))
    serial = rs / rr * len(p) / max(m, 1) if rr > 0 else 0.0
    dof = max(len(p) - n_par, 1)
    scale = rr / dof
    if not np.isfinite(scale):
        return None
    try:
        with np.errstate(over="ignore", invalid="ignore"):  # a near-singular system: inf
            cov_all = np.linalg.inv(A) * max(scale, 1e-12)
    except np.linalg.LinAlgError:
        return None
    cov = cov_all[2 * K:2 * K + 2, 2 * K:2 * K + 2]
    if not (np.all(np.isfinite(cov)) and np.isfinite(R) and R > 0):
        return None
    return RoundFit(velocity=v, radius_m=float(R), cov=cov, rms_norm=rms, serial=serial,
                    n_points=len(p), labels=keys, centres=c, t_ref_s=float(t_ref_s))
