"""Motion of a moving object: coarse estimate from centroids, refinement by entropy (eqs 11-13).

Model: constant velocity ``v`` [m/s] along a constant heading ``phi`` [rad] (world frame,
anticlockwise from +x) on the ground plane. Eq. 11 accumulates the object's scans in one
reference time ``t_ref``: every point moves back along the motion by its own time,

    q_i = p_i + v (t_ref - t_i) (cos phi, sin phi, 0)

(``compensate``), using the per-beam time (each beam of a 100 ms scan has its own).

Two sharpness measures of the accumulated cloud, both minimal when the motion is right:

* ``"voxel"`` - the paper's eq. 12: binary occupancy entropy summed over the voxels the cloud
  occupies, ``H = sum_v h(p_v)`` with ``h(p) = -p ln p - (1-p) ln(1-p)``. The paper leaves
  ``p`` open; here ``p_v = n_v / (n_v + 1)`` from the voxel's point count ``n_v`` (one hit is
  an even bet, many hits make the voxel surely occupied), so a blurred cloud spread over many
  thinly filled voxels has more entropy than a sharp one. Piecewise constant in (v, phi):
  minimised by grid search (coarse then fine) around the initial guess, taking the mean of
  the tied minima.
* ``"renyi"`` - Rényi's quadratic entropy of the cloud's Gaussian kernel density
  (Sheehan, Harrison, Newman, IJRR 2012, the method the paper adapts):
  ``H = -ln( 1/N^2 sum_ij exp(-|q_i - q_j|^2 / (4 sigma^2)) )``. Smooth: Nelder-Mead on
  (vx, vy). Pairs are found once (cKDTree, within the kernel cutoff plus the largest motion
  change the search can make), so one evaluation is a vectorised sum over a fixed pair list.

Both are evaluated on the **ground-plane projection** by default (``plane=True``): the nod
visits each height once per sweep, so within a sweep the 3D slices of different scans hardly
overlap and 3D sharpness cannot tell one ground-plane motion from another (measured: Rényi in
3D drifted to 0.3-0.6 m/s over the first sweep of the paper scenario); in the top view every
scan's slice of an upright object overlaps the others. ``plane=False`` keeps 3D. The Rényi sum
uses at most ``max_points`` points (evenly spaced in time order), or every point with as many
randomly drawn pairs as ``max_points`` points have (``renyi_subsample="pairs"``), which bounds
one evaluation's cost as scans accumulate.

The coarse estimate (paper Section V-B) is the least-squares line through the per-scan
centroids projected on the ground plane against their mean times.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import cast

import numpy as np
from numpy.typing import ArrayLike
from scipy.optimize import minimize
from scipy.spatial import cKDTree

from ..errors import require

__all__ = ["MotionEstimate", "compensate", "coarse_motion", "voxel_entropy", "RenyiCost",
           "refine_motion", "velocity_from_motion", "motion_from_velocity", "incidence_weights",
           "labels_observe_motion", "smooth_along_scan"]

ENTROPIES = ("voxel", "renyi")


@dataclass(frozen=True)
class MotionEstimate:
    """Constant-velocity motion on the ground plane.

    Attributes
    ----------
    v_m_s : float
        Speed [m/s] (>= 0).
    heading_rad : float
        Direction of motion, anticlockwise from world +x [rad], in (-pi, pi].
    cov : (2, 2) float or None
        Covariance of (vx, vy) [m^2/s^2] where available.
    cost : float
        Entropy at the estimate (nan for the coarse one).
    n_points, n_scans : int
    """

    v_m_s: float
    heading_rad: float
    cov: np.ndarray | None = None
    cost: float = float("nan")
    n_points: int = 0
    n_scans: int = 0

    @property
    def velocity(self) -> np.ndarray:
        """(2,) ground-plane velocity [m/s]."""
        return velocity_from_motion(self.v_m_s, self.heading_rad)


def velocity_from_motion(v: float, heading: float) -> np.ndarray:
    """Speed [m/s] and heading [rad] -> (2,) ground-plane velocity (vx, vy) [m/s]."""
    return np.array([v * np.cos(heading), v * np.sin(heading)])


def motion_from_velocity(vel: np.ndarray | Sequence[float]) -> tuple[float, float]:
    """(2,) ground-plane velocity (vx, vy) [m/s] -> (speed [m/s], heading [rad])."""
    vx, vy = float(vel[0]), float(vel[1])
    return float(np.hypot(vx, vy)), float(np.arctan2(vy, vx))


def compensate(points: ArrayLike, t_s: ArrayLike, velocity: np.ndarray | Sequence[float],
               t_ref_s: float) -> np.ndarray:
    """Eq. 11: move each point back to ``t_ref_s`` along the ground-plane ``velocity``.

    Parameters
    ----------
    points : (n, 3) float [m]
    t_s : (n,) float
        Per-point time [s].
    velocity : (2,) float
        (vx, vy) [m/s].
    t_ref_s : float

    Returns
    -------
    (n, 3) float
    """
    q = np.array(points, dtype=float, copy=True)
    dt = t_ref_s - np.asarray(t_s, float)
    q[:, 0] += velocity[0] * dt
    q[:, 1] += velocity[1] * dt
    return q


def coarse_motion(centroids_xy: np.ndarray, t_s: np.ndarray) -> MotionEstimate:
    """Least-squares constant-velocity line through per-scan centroids.

    Parameters
    ----------
    centroids_xy : (k, 2) float
        Ground-plane centroid of the object in each scan [m] (k >= 2).
    t_s : (k,) float
        Mean time of the object's points in each scan [s].
    """
    c = np.asarray(centroids_xy, float)
    t = np.asarray(t_s, float)
    require(len(c) >= 2, "centroids", len(c), ">= 2 scans")
    tc = t - t.mean()
    den = float(np.sum(tc ** 2))
    require(den > 0, "t_s", t_s, "at least two different times")
    vel = (tc @ (c - c.mean(axis=0))) / den
    v, h = motion_from_velocity(vel)
    return MotionEstimate(v, h, n_scans=len(c))


def voxel_entropy(points: np.ndarray, voxel_m: float, plane: bool = True) -> float:
    """Eq. 12 with ``p_v = n_v / (n_v + 1)`` (module docstring) [nats].

    The voxels' counts come from one sort of packed integer keys (faster than
    ``np.unique`` over rows; the test suite checks the two agree).

    Parameters
    ----------
    points : (n, 2) or (n, 3) float [m]
    voxel_m : float
        Voxel edge [m] (fine grained: of the order of the range noise).
    plane : bool
        Ground-plane projection (pixels in x, y) instead of 3D voxels.
    """
    q = np.asarray(points, float)
    ijk = np.floor((q[:, :2] if plane else q[:, :3]) / voxel_m).astype(np.int64)
    ijk -= ijk.min(axis=0)
    dims = ijk.max(axis=0) + 1
    key = ijk[:, 0] * dims[1] + ijk[:, 1]
    if not plane:
        key = key * dims[2] + ijk[:, 2]
    key.sort()
    brk = np.flatnonzero(np.diff(key)) + 1
    n = np.diff(np.concatenate([[0], brk, [len(key)]])).astype(float)
    p = n / (n + 1.0)
    return float(-np.sum(p * np.log(p) + (1 - p) * np.log1p(-p)))


def _voxel_entropy_grid(p_xy: np.ndarray, t: np.ndarray, W: np.ndarray, t_ref: float,
                        voxel_m: float, shift_m: float = 0.0,
                        bins_per_point: float = 8.0) -> np.ndarray:
    """:func:`voxel_entropy` (plane) of the cloud compensated by every velocity of ``W``
    ``(m, 2)`` at once: one (m, n) sort of packed pixel keys, run lengths per row, entropy
    summed per row by ``bincount`` - the whole grid in one batched pass (no Python loop
    over the grid). The pixels are counted by one ``bincount`` when the key space has at
    most ``bins_per_point`` bins per (velocity, point) entry (a compact cloud: no sort),
    else by sorting each row."""
    dt = (t_ref - t)[None, :]

    def pixel(axis: int) -> np.ndarray:
        # floor((p + w dt + shift) / voxel), the same float operations in place (one
        # (m, n) temporary instead of four; a + b is b + a exactly, and + 0.0 changes
        # nothing)
        a = W[:, axis:axis + 1] * dt
        a += p_xy[None, :, axis]
        if shift_m:
            a += shift_m
        a /= voxel_m
        return np.floor(a, out=a).astype(np.int64)

    ix, iy = pixel(0), pixel(1)
    ix -= ix.min()
    iy -= iy.min()
    ny = int(iy.max()) + 1
    nx = int(ix.max()) + 1
    m, n = ix.shape
    # rows apart in one key space
    key = ix * ny + iy
    key += np.arange(m, dtype=np.int64)[:, None] * (nx * ny)
    if m * nx * ny <= bins_per_point * key.size:
        # pixel counts by one bincount over the (small) key space, no sort: the nonzero
        # counts come out in key order, the order of the sorted runs below (same sums)
        c = np.bincount(key.ravel(), minlength=m * nx * ny)
        nz = np.flatnonzero(c)
        cnt, row = c[nz].astype(float), nz // (nx * ny)
    else:  # a wide cloud: sorted runs per row
        flat = np.sort(key, axis=1).ravel()
        start = np.concatenate([[0], np.flatnonzero(np.diff(flat)) + 1])
        cnt = np.diff(np.concatenate([start, [flat.size]])).astype(float)
        row = start // n
    pr = cnt / (cnt + 1.0)
    h = -(pr * np.log(pr) + (1 - pr) * np.log1p(-pr))
    return np.bincount(row, weights=h, minlength=m)


def _draw_label_pairs(labels: np.ndarray, m: int,
                      rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, float]:
    """About ``m`` ordered pairs ``(i, j)``, ``i != j``, drawn uniformly among the pairs of
    points with the same label, and the weight of one drawn pair in the sum over the
    unordered same-label pairs (an unbiased estimate, as :class:`RenyiCost`'s draw over
    all pairs).

    ``i`` uniform over the points, ``j`` uniform over the other points of ``i``'s label
    (``n_l`` points), kept with probability ``(n_l - 1) / (n_max - 1)``: every ordered
    same-label pair is then kept with the same probability ``1 / (N (n_max - 1))`` per
    draw, so each kept one stands for ``N (n_max - 1) / (2 m_drawn)`` unordered pairs.
    ``m_drawn`` is ``m`` over the expected acceptance, so about ``m`` are kept.

    Parameters
    ----------
    labels : (N,) int
    m : int
    rng : numpy Generator

    Returns
    -------
    i, j : (k,) int; weight : float
    """
    n = len(labels)
    _, g, size = np.unique(labels, return_inverse=True, return_counts=True)
    order = np.argsort(g, kind="stable")
    start = np.concatenate([[0], np.cumsum(size)[:-1]])
    rank = np.empty(n, np.int64)
    rank[order] = np.arange(n) - start[g[order]]
    nmax = int(size.max())
    if nmax < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), 1.0
    accept = float(np.sum(size * (size - 1))) / (n * (nmax - 1))
    md = int(np.ceil(m / accept))
    i = rng.integers(0, n, md)
    ni = size[g[i]]
    keep = rng.random(md) * (nmax - 1) < ni - 1
    i, ni = i[keep], ni[keep]
    k = np.minimum((rng.random(len(i)) * (ni - 1)).astype(np.int64), ni - 2)
    k += k >= rank[i]  # uniform over the others of the label
    j = order[start[g[i]] + k]
    return i, j, n * (nmax - 1) / (2.0 * md)


class RenyiCost:
    """Rényi quadratic entropy of the compensated cloud as a function of (vx, vy).

    Parameters
    ----------
    points : (n, 3) float; t_s : (n,) float
    t_ref_s : float
    sigma_m : float
        Kernel width [m] (of the order of the range noise).
    center_velocity : (2,) float
        The motion around which pairs are gathered [m/s].
    max_dv_m_s : float
        Largest change of velocity the evaluations will make from ``center_velocity``; pairs
        are gathered within ``cutoff + max_dv * max |t_i - t_j|``.
    cutoff_sigmas : float
        Kernel truncation (5 sigma: exp(-25/4) = 0.2 % of the peak).
    plane : bool
        Ground-plane projection (z ignored).
    max_points : int
        Bounds the work: with ``subsample="points"`` at most this many points (evenly spaced
        in time order) enter the sum; with ``"pairs"`` every point does, and the pair sum is
        estimated from ``max_points (max_points - 1) / 2`` pairs drawn at random (the same
        number of pairs as ``max_points`` points have).
    subsample : {"points", "pairs"}
        How a cloud of more than ``max_points`` points is cut down. ``"pairs"``: an
        incomplete U-statistic (Blom 1976): the sum over all ``N (N - 1) / 2`` pairs is
        estimated, unbiased, by the drawn pairs times ``N (N - 1) / (2 m)``; ``m`` pairs over
        ``N`` points vary less than all the pairs of ``max_points`` points (which share
        their points), so what a denser cloud adds is kept at the same cost. The draw is
        seeded by ``N`` (deterministic).
    labels : (n,) int, optional
        A label per point (its mirror window): the sum then keeps only the pairs of points
        with the same label (drawn within labels by :func:`_draw_label_pairs` beyond
        ``max_points``). None, or one label for every point: all pairs.
    weights : (n,) float, optional
        A weight per point: the sum is ``sum_i w_i^2 + sum_{i != j} w_i w_j k_ij`` over
        ``(sum_i w_i)^2`` (None: all ones, the plain cost). Used to give every part of a
        surface the same mass (:func:`incidence_weights`).
    edges : (n, 2, 5) float, optional
        Per point, the lines where its scan's view of the object was cut (further
        columns are ignored)
        (:func:`~nodlidar.tracking.segment.cut_edges`; NaN: none). A pair of points of
        two scans then enters the sum only if each point, moved by ``center_velocity`` to
        the other's time, lies on the seen side of the other's lines (1 mm tolerance): a
        part of the object that one of the two scans could not see has no partner there,
        and the pairs it does have pull the motion towards the cut, a line fixed in the
        sensor. The pairs kept are chosen once, at ``center_velocity`` (the cost stays
        smooth); the tracker's next refinement starts from this one's minimum.
        ``dt_kept_s`` says how far apart in time the kept pairs reach.
    """

    def __init__(self, points: ArrayLike, t_s: ArrayLike, t_ref_s: float, sigma_m: float,
                 center_velocity: np.ndarray | Sequence[float],
                 max_dv_m_s: float = 0.1, cutoff_sigmas: float = 5.0, plane: bool = True,
                 max_points: int = 800, subsample: str = "points",
                 labels: ArrayLike | None = None, weights: ArrayLike | None = None,
                 edges: ArrayLike | None = None) -> None:
        require(subsample in ("points", "pairs"), "subsample", subsample, "points or pairs")
        p = np.asarray(points, float)
        t = np.asarray(t_s, float)
        lab = None if labels is None else np.asarray(labels)
        wt = None if weights is None else np.asarray(weights, float)
        ed = None if edges is None else np.asarray(edges, float)
        if ed is not None and not np.isfinite(ed[:, :, 0]).any():
            ed = None  # no cut: every pair
        if lab is not None and (len(lab) == 0 or np.all(lab == lab[0])):
            lab = None  # one view: every pair is within it
        sample_pairs = subsample == "pairs" and len(p) > max_points
        if len(p) > max_points and not sample_pairs:
            order = np.argsort(t, kind="stable")
            sel = order[np.linspace(0, len(p) - 1, max_points).round().astype(int)]
            p, t = p[sel], t[sel]
            lab = None if lab is None else lab[sel]
            wt = None if wt is None else wt[sel]
            ed = None if ed is None else ed[sel]
        p_xy = p[:, :2]
        if plane:
            p = np.column_stack([p[:, :2], np.zeros(len(p))])
        self.n = len(p)
        q = compensate(p, t, center_velocity, t_ref_s)
        span = float(t.max() - t.min()) if len(t) else 0.0
        r = cutoff_sigmas * sigma_m + max_dv_m_s * span
        # coordinates as 1D arrays: gathering pairs from them is several times faster than
        # gathering rows of q (same values)
        qx, qy, qz = (np.ascontiguousarray(q[:, k]) for k in range(3))

        def diffs(i, j):
            """q_i - q_j per axis; z only off the plane (in it z is 0 and adds nothing)."""
            return qx[i] - qx[j], qy[i] - qy[j], (None if plane else qz[i] - qz[j])

        def drawn_within(i, j):
            """The drawn pairs within the cutoff ``r`` (as query_pairs), in order, with
            their :func:`diffs`: one compiled pass, where numpy made ~10 arrays of all the
            drawn pairs, most of which are dropped (the same values)."""
            from ._kernel import pairs_within  # numba: loaded when first used

            i, j, dx, dy, dz = pairs_within(qx, qy, qz, np.ascontiguousarray(i),
                                            np.ascontiguousarray(j), r * r, not plane)
            return i, j, dx, dy, (None if plane else dz)

        #: weight of one pair in the sum (1: every pair within the cutoff is in the list)
        self.w = 1.0
        if sample_pairs and lab is None:
            n = self.n
            m = max_points * (max_points - 1) // 2
            rng = np.random.default_rng(n)
            # int32: the same numbers as int64 draws (numpy draws 32 bits for a range
            # below 2^32 either way), half the memory to write and read
            i = rng.integers(0, n, m, dtype=np.int32)
            j = rng.integers(0, n - 1, m, dtype=np.int32)
            j += j >= i  # uniform over the ordered pairs i != j: each stands for one pair
            i, j, dx, dy, dz = drawn_within(i, j)
            self.w = n * (n - 1) / (2.0 * m)
        elif sample_pairs and lab is not None:
            i, j, self.w = _draw_label_pairs(lab, max_points * (max_points - 1) // 2,
                                             np.random.default_rng(self.n))
            i, j, dx, dy, dz = drawn_within(i, j)
        else:
            pairs = cKDTree(q).query_pairs(r, output_type="ndarray")
            if lab is not None:
                pairs = pairs[lab[pairs[:, 0]] == lab[pairs[:, 1]]]
            i, j = pairs[:, 0], pairs[:, 1]
            dx, dy, dz = diffs(i, j)
        # q_i - q_j at velocity c + dw is (q_i - q_j)|_c + dw (t_j - t_i): stored once, in
        # float32 (the sum is over exp terms in [0, 1]; float32 halves the memory traffic)
        self.dx, self.dy = dx.astype(np.float32), dy.astype(np.float32)
        self.dz2 = (np.zeros(len(i), np.float32) if dz is None
                    else (dz.astype(np.float32) ** 2).astype(np.float32))
        self.n_pairs = len(i)
        # point weights: the self terms sum w_i^2, each pair w_i w_j, normalised by (sum w)^2
        # (all ones: the plain sum, n self terms over n^2), times whether both scans could
        # see the pair (where the window has cut lines)
        cut = ed is not None and len(i) > 0
        self.dt, pw, dt_kept = _pair_terms(i, j, t, wt, p_xy, ed if cut else None,
                                           np.asarray(center_velocity, float))
        self.pw = pw if wt is not None or cut else None
        #: the longest time between the two points of a pair the sum keeps [s] (the motion
        #: is observed only through pairs of points seen at different times)
        self.dt_kept_s = float(dt_kept)
        self.s0 = float(self.n) if wt is None else float(np.sum(wt ** 2))
        self.norm = float(self.n) ** 2 if wt is None else float(np.sum(wt)) ** 2
        self.c = np.asarray(center_velocity, float)
        self.inv4s2 = np.float32(1.0 / (4.0 * sigma_m ** 2))
        self.plane = bool(plane)

    def __call__(self, velocity: ArrayLike) -> float:
        dw = (np.asarray(velocity, float) - self.c).astype(np.float32)
        # dx + dw_x dt, squared, + the same in y (+ dz^2 in 3D), times -1/(4 sigma^2), exp:
        # the same float32 operations in place (two temporaries instead of eight); in the
        # plane dz2 is zero and adding it changed nothing
        dx = self.dt * dw[0]
        dx += self.dx
        dy = self.dt * dw[1]
        dy += self.dy
        dx *= dx
        dy *= dy
        dx += dy
        if not self.plane:
            dx += self.dz2
        dx *= -self.inv4s2
        e = np.exp(dx, out=dx)
        if self.pw is not None:
            e *= self.pw
        s = self.s0 + 2.0 * self.w * float(np.sum(e, dtype=np.float64))
        return float(-np.log(s / self.norm))


def _pair_terms(i: np.ndarray, j: np.ndarray, t: np.ndarray, wt: np.ndarray | None,
                p_xy: np.ndarray, edges: np.ndarray | None, c: np.ndarray,
                tol_m: float = 1e-3) -> tuple[np.ndarray, np.ndarray, float]:
    """A Rényi cost's per-pair terms for the pairs ``(i, j)`` (m,) of points ``p_xy``
    (n, 2) [m] at times ``t`` (n,) [s]:

    - ``dt = t[j] - t[i]``, (m,) float32 [s];
    - the pair weights, (m,) float32: ``wt[i] wt[j]`` (ones without ``wt``), times whether
      both scans could see the pair (with ``edges`` (n, L, >=5),
      :func:`~nodlidar.tracking.segment.cut_edges`; NaN: no line): point ``i`` moved at
      velocity ``c`` (2,) [m/s] to ``t[j]`` lies on the seen side of ``j``'s cut lines,
      and ``j`` moved to ``t[i]`` of ``i``'s, within ``tol_m`` [m];
    - the longest ``|dt|`` of a pair kept [s].

    One compiled pass (:func:`~nodlidar.tracking._kernel.pair_terms`); numpy's gathers,
    casts and products were ~8 passes over the pairs, the same numbers."""
    from ._kernel import pair_terms  # numba: loaded when first used

    one = np.ones(1)
    ed = np.zeros((1, 1, 5)) if edges is None else np.ascontiguousarray(edges[:, :, :5], float)
    return pair_terms(np.ascontiguousarray(i, np.int64), np.ascontiguousarray(j, np.int64),
                      np.ascontiguousarray(t, float),
                      one if wt is None else np.ascontiguousarray(wt, float), wt is not None,
                      np.ascontiguousarray(p_xy[:, 0], float),
                      np.ascontiguousarray(p_xy[:, 1], float), ed, edges is not None,
                      float(c[0]), float(c[1]), float(tol_m))


def _renyi_derivatives(cost: RenyiCost, velocity: ArrayLike) -> tuple[float, np.ndarray, np.ndarray]:
    """The Rényi cost, its gradient (2,) and Hessian (2, 2) in (vx, vy) in one pass over
    the pairs, in closed form: with ``e = exp(-c d^2)``, ``c = 1/(4 sigma^2)``,
    ``d = dq + dw dt`` and ``S = n + 2 sum e``, ``f = -ln(S / n^2)``,
    ``dS/dw_a = -4c sum e d_a dt``, ``d2S/dw_a dw_b = 2 sum e dt^2 (4c^2 d_a d_b - 2c [a=b])``,
    ``grad f = -grad S / S``, ``H f = -H S / S + grad S grad S^T / S^2``."""
    return _renyi_slopes(cost, _RenyiTerms(cost, velocity))


class _RenyiTerms:
    """The first half of :func:`_renyi_derivatives` at one velocity: the pair terms ``e``
    and offsets ``d`` (kept for the slopes) and the cost ``f``. Newton's line search needs
    only ``f`` at a trial step; the slopes (:func:`_renyi_slopes`) follow for the step it
    takes, from the same arrays (the same numbers as in one pass)."""

    def __init__(self, cost: RenyiCost, velocity: ArrayLike) -> None:
        dw = (np.asarray(velocity, float) - cost.c).astype(np.float32)
        dx = cost.dt * dw[0]
        dx += cost.dx
        dy = cost.dt * dw[1]
        dy += cost.dy
        # the same float32 operations as written out in the docstring, into two scratch
        # arrays instead of a new one per product (six pair-length arrays instead of ~15)
        e = dx * dx
        scratch = dy * dy
        e += scratch  # d^2
        if not cost.plane:
            e += cost.dz2
        e *= -cost.inv4s2
        np.exp(e, out=e)
        if cost.pw is not None:
            e *= cost.pw
        s_e = float(np.sum(e, dtype=np.float64))
        if cost.w != 1.0:  # sampled pairs, each standing for w pairs (RenyiCost)
            s_e = cost.w * s_e
        self.dx, self.dy, self.e, self.scratch, self.s_e = dx, dy, e, scratch, s_e
        self.S = cost.s0 + 2.0 * s_e
        self.f = float(-np.log(self.S / cost.norm))


def _renyi_slopes(cost: RenyiCost, r: _RenyiTerms) -> tuple[float, np.ndarray, np.ndarray]:
    """The cost, gradient and Hessian from :class:`_RenyiTerms` (whose arrays it spends)."""
    f64 = np.float64
    c = float(cost.inv4s2)
    dx, dy, e = r.dx, r.dy, r.e
    edt = np.multiply(e, cost.dt, out=r.scratch)
    ex, ey = edt * dx, edt * dy  # e d dt
    gx, gy = float(np.sum(ex, dtype=f64)), float(np.sum(ey, dtype=f64))

    buf = e  # spent: its sum is taken

    def dt_sum(a: np.ndarray, b: np.ndarray) -> float:
        """sum a b dt, as float64."""
        np.multiply(a, b, out=buf)
        np.multiply(buf, cost.dt, out=buf)
        return float(np.sum(buf, dtype=f64))

    h0 = float(np.sum(np.multiply(edt, cost.dt, out=buf), dtype=f64))  # sum e dt^2
    hxx = dt_sum(ex, dx)  # sum e d_x^2 dt^2
    hyy = dt_sum(ey, dy)
    hxy = dt_sum(ex, dy)
    if cost.w != 1.0:
        gx, gy, hxx, hyy, hxy, h0 = (cost.w * x for x in (gx, gy, hxx, hyy, hxy, h0))
    S = r.S
    gS = -4.0 * c * np.array([gx, gy])
    HS = 2.0 * (4.0 * c * c * np.array([[hxx, hxy], [hxy, hyy]]) - 2.0 * c * h0 * np.eye(2))
    return (r.f, -gS / S, -HS / S + np.outer(gS, gS) / S ** 2)


def _newton(cost: RenyiCost, w0: np.ndarray, max_step: float, xtol: float = 5e-5,
            max_iter: int = 30):
    """Newton's method on the Rényi cost from ``w0`` with steps capped at ``max_step``
    [m/s] and halved until the cost decreases. Returns (w, f, H) or None where the Hessian
    is not positive definite (the caller then falls back to Nelder-Mead)."""
    w = np.asarray(w0, float)
    f, g, H = _renyi_derivatives(cost, w)
    for _ in range(max_iter):
        try:
            if not np.all(np.linalg.eigvalsh(H) > 0):
                return None
            step = -np.linalg.solve(H, g)
        except np.linalg.LinAlgError:
            return None
        n = float(np.linalg.norm(step))
        if n > max_step:
            step *= max_step / n
        for _ in range(8):
            trial = _RenyiTerms(cost, w + step)  # the cost alone until a step is taken
            if trial.f <= f:
                f1, g1, H1 = _renyi_slopes(cost, trial)
                break
            step /= 2
        else:
            return w, f, H  # no descent along the Newton direction: at the minimum
        w, f, g, H = w + step, f1, g1, H1
        if float(np.linalg.norm(step)) < xtol:
            break
    return w, f, H


def _hessian(f, x, h):
    """Central-difference Hessian of scalar ``f`` at ``x`` (2,) with steps ``h`` (2,)."""
    x = np.asarray(x, float)
    H = np.zeros((2, 2))
    f0 = f(x)
    for a in range(2):
        ea = np.zeros(2)
        ea[a] = h[a]
        H[a, a] = (f(x + ea) - 2 * f0 + f(x - ea)) / h[a] ** 2
        for b in range(a + 1, 2):
            eb = np.zeros(2)
            eb[b] = h[b]
            H[a, b] = H[b, a] = (f(x + ea + eb) - f(x + ea - eb) - f(x - ea + eb)
                                 + f(x - ea - eb)) / (4 * h[a] * h[b])
    return H


def _beam_neighbour(steps: ArrayLike, mirror: ArrayLike):
    """For one scan's cluster (``steps``, ``mirror``: (n,) int per point), a function of a
    step offset ``off`` returning ``(j, ok)``: per point, the index of the point ``off``
    steps on seen through the same window (any index where there is none) and whether
    there is one ((n,) int, (n,) bool)."""
    key = np.asarray(steps, np.int64) * 16 + (np.asarray(mirror, np.int64) + 1)
    order = np.argsort(key)
    ks = key[order]
    n = len(ks)

    def find(off: int) -> tuple[np.ndarray, np.ndarray]:
        want = key + off * 16
        pos = np.minimum(np.searchsorted(ks, want), max(n - 1, 0))
        ok = (ks[pos] == want) if n else np.zeros(0, bool)
        return order[pos], ok

    return find


def incidence_weights(points: ArrayLike, ray_dir: ArrayLike, steps: ArrayLike,
                      mirror: ArrayLike, k: int = 2, max_weight: float = 4.0) -> np.ndarray:
    """Weight ``1 / cos(incidence)`` per point of one scan's cluster, in the top view.

    Equally spaced beams put more points per metre of surface where the surface faces
    the ray than where it grazes it (density ~ cos(incidence)). An object's visible front
    turns with the bearing as it passes, so an entropy that counts points pulls the dense
    fronts of successive scans together and reads a passing object slow (docs/tracking.md,
    "Fast walkers read slow"); these weights give every part of the surface the same mass.
    The surface direction at a point is the chord to the points ``k`` beams either side (one
    side at the cluster's ends) seen through the same window; a point with no such
    neighbour keeps weight 1.

    points, ray_dir : (n, 3); steps, mirror : (n,) int (beam step and window per point).
    Returns (n,) float in [1, max_weight].
    """
    p = np.asarray(points, float)[:, :2]
    d = np.asarray(ray_dir, float)[:, :2]
    n = len(p)
    find = _beam_neighbour(steps, mirror)
    # no neighbour that far: the point itself (one side of the chord at a cluster's end)
    nxt, prv = (np.where(ok, j, np.arange(n)) for j, ok in (find(k), find(-k)))
    t = p[nxt] - p[prv]
    tl = np.hypot(t[:, 0], t[:, 1])
    dl = np.hypot(d[:, 0], d[:, 1])
    ok = (tl > 0) & (dl > 0)
    cos_inc = np.ones(n)
    cos_inc[ok] = np.abs(t[ok, 0] * d[ok, 1] - t[ok, 1] * d[ok, 0]) / (tl[ok] * dl[ok])
    return 1.0 / np.maximum(cos_inc, 1.0 / max_weight)


def smooth_along_scan(points: ArrayLike, ray_dir: ArrayLike, range_m: ArrayLike,
                      steps: ArrayLike, mirror: ArrayLike, k: int = 2,
                      jump_m: float = 0.05) -> np.ndarray:
    """One scan's cluster with each point's range replaced by a straight-line fit of range
    against beam step over the beams within ``k`` steps either side (same window, in the
    cluster, no range jump of more than ``jump_m`` [m] per step to the point): the points
    move along their own rays only.

    The range noise (1 % of the range beyond 1 m) acts on the entropy like a wider kernel
    and reads a passing object slow (docs/tracking.md, "Why fast movers read slow"); a
    surface is smooth over a few beams, so their mean carries less noise. A line, not a
    parabola: its error on a curved face is a fixed shape error that moves with the object.

    points, ray_dir : (n, 3); range_m : (n,); steps, mirror : (n,) int.
    Returns (n, 3) float.
    """
    p = np.asarray(points, float)
    d = np.asarray(ray_dir, float)
    r = np.asarray(range_m, float)
    n = len(p)
    if n < 2:
        return p.copy()
    find = _beam_neighbour(steps, mirror)
    S0 = np.ones(n)
    S1 = np.zeros(n)
    S2 = np.zeros(n)
    R0 = r.copy()
    R1 = np.zeros(n)
    for off in range(-k, k + 1):
        if off == 0:
            continue
        j, ok = find(off)
        ok &= np.abs(r[j] - r) <= jump_m * abs(off)
        S0 += ok
        S1 += ok * off
        S2 += ok * off * off
        R0 += np.where(ok, r[j], 0.0)
        R1 += np.where(ok, r[j] * off, 0.0)
    det = S0 * S2 - S1 * S1
    fit = np.where(det > 0, (R0 * S2 - S1 * R1) / np.where(det > 0, det, 1.0), r)
    du = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    return p + (fit - r)[:, None] * du


def labels_observe_motion(labels: ArrayLike, t_s: ArrayLike, min_fraction: float = 0.25) -> bool:
    """Whether the pairs within ``labels`` observe the motion of points at times ``t_s``.

    The Rényi sum over pairs within labels depends on the velocity only through the time
    differences of those pairs. When every label's points are from (nearly) one moment -
    a new track seen through one mirror window in one scan and through another in the
    next - the cost is flat in the velocity and its minimiser wanders off (measured: a
    person seen through window 3 (6 points) and then directly (6 points) was given
    201 m/s, and the track lost its person). True when some label's points span at least
    ``min_fraction`` of all the points' time span (or the points are all from one moment).

    labels, t_s : (n,) arrays. Returns a bool.
    """
    lab = np.asarray(labels)
    t = np.asarray(t_s, float)
    span = float(np.ptp(t)) if len(t) else 0.0
    if span <= 0 or len(lab) != len(t):
        return True
    _, g = np.unique(lab, return_inverse=True)
    lo = np.full(g.max() + 1, np.inf)
    hi = np.full(g.max() + 1, -np.inf)
    np.minimum.at(lo, g, t)
    np.maximum.at(hi, g, t)
    return bool(np.max(hi - lo) >= min_fraction * span)


def refine_motion(points: np.ndarray, t_s: np.ndarray, guess: MotionEstimate, *,
                  entropy: str = "renyi", t_ref_s: float | None = None, sigma_m: float = 0.02,
                  voxel_m: float = 0.03, search_m_s: float = 0.08, n_scans: int = 0,
                  plane: bool = True, max_points: int = 800,
                  voxel_offsets: int = 1, voxel_grid: tuple[int, ...] = (17, 9, 9),
                  voxel_max_points: int | None = None,
                  renyi_method: str = "nelder-mead",
                  renyi_subsample: str = "points",
                  labels: ArrayLike | None = None,
                  weights: ArrayLike | None = None,
                  edges: ArrayLike | None = None,
                  newton_recentre: bool = False) -> MotionEstimate:
    """Eq. 13: the motion whose compensated accumulation has the least entropy.

    Parameters
    ----------
    points : (n, 3) float
        The object's points over its scans, world frame [m].
    t_s : (n,) float
        Per-point time [s].
    guess : MotionEstimate
        Start (e.g. :func:`coarse_motion`).
    entropy : {"voxel", "renyi"}
    t_ref_s : float, optional
        Reference time (default: the latest point's).
    sigma_m : float
        Rényi kernel width [m].
    voxel_m : float
        Voxel edge of eq. 12 [m].
    search_m_s : float
        Half width of the velocity search around the guess [m/s].
    plane : bool
        Entropy of the ground-plane projection (module docstring) or of the 3D cloud.
    max_points : int
        Rényi: at most this many points in the pair sum.
    voxel_offsets : int
        Voxel: average eq. 12 over this many grids shifted along the diagonal by
        ``voxel_m / voxel_offsets`` (1 = the paper's single grid). Averaging shifted grids
        makes the cost less sensitive to where the grid happens to cut the cloud.
    voxel_grid : tuple of int
        Voxel: points per axis of each level of the grid search (level ``i`` spans
        ``+-search_m_s / 8**i`` around the previous level's minimum); in the plane, each
        level is evaluated in one batched pass.
    renyi_method : {"nelder-mead", "newton"}
        Rényi minimiser: Nelder-Mead on the cost, or Newton's method on its closed-form
        gradient and Hessian (a few passes over the pairs instead of ~50; Nelder-Mead is
        used where the Hessian is not positive definite or the minimum leaves the search
        region).
    voxel_max_points : int, optional
        Voxel: at most this many points (evenly spaced in time order; None: all).
    renyi_subsample : {"points", "pairs"}
        Rényi: beyond ``max_points``, keep that many points, or keep every point and draw
        as many pairs as ``max_points`` points have (:class:`RenyiCost`).
    labels : (n,) int, optional
        Rényi: only pairs of points with the same label (e.g. the mirror window) enter
        the sum (:class:`RenyiCost`); None: all pairs. Ignored (all pairs) when no label's
        points span at least a quarter of the points' time span
        (:func:`labels_observe_motion`): the pairs they allow would leave the velocity
        unobserved.
    weights : (n,) float, optional
        Rényi: a weight per point (:class:`RenyiCost`); None: all ones.
    edges : (n, 2, >=5) float, optional
        Rényi: per point, the lines where its scan's view was cut; pairs are kept only
        where both scans could see both points (:class:`RenyiCost`); None: every pair.
        Ignored (every pair) when the pairs kept span less than a quarter of the points'
        time span: they would leave the velocity unobserved.
    newton_recentre : bool
        Rényi with ``"newton"``: where Newton's minimum lies farther than ``search_m_s``
        from the guess (outside the region whose pairs were gathered), gather the pairs
        again around it and go on with Newton, up to three times, before falling back to
        Nelder-Mead (which in that case ran twice, at several times the cost).

    Returns
    -------
    MotionEstimate with ``cov`` = the inverse Hessian of the Rényi cost at the minimum
    (central differences, 2 mm/s steps; unscaled, so a curvature measure rather than a
    calibrated covariance; None if the Hessian is not positive definite) for ``"renyi"``;
    for ``"voxel"`` from the spread of the tied grid minima (at least the fine grid's
    resolution).
    """
    require(entropy in ENTROPIES, "entropy", entropy, " or ".join(ENTROPIES))
    require(renyi_method in ("nelder-mead", "newton"), "renyi_method", renyi_method,
            "nelder-mead or newton")
    require(len(voxel_grid) >= 1 and all(int(n) == n and n >= 3 for n in voxel_grid),
            "voxel_grid", voxel_grid, "one or more integers >= 3 (points per axis)")
    p = np.asarray(points, float)
    t = np.asarray(t_s, float)
    require(len(p) >= 3, "points", len(p), ">= 3")
    t_ref = float(t.max()) if t_ref_s is None else float(t_ref_s)
    w0 = guess.velocity
    if labels is not None and not labels_observe_motion(labels, t):
        labels = None
    cov: np.ndarray | None
    if entropy == "renyi":
        cost = RenyiCost(p, t, t_ref, sigma_m, w0, max_dv_m_s=search_m_s, plane=plane,
                         max_points=max_points, subsample=renyi_subsample, labels=labels,
                         weights=weights, edges=edges)
        if edges is not None and cost.dt_kept_s < 0.25 * float(np.ptp(t)):
            # the cut lines left no pair of points seen at different times (an object
            # entering the view, seen as a sliver at its edge in each scan: each scan's
            # points lie where the scan before could not see): the cost would be flat in
            # the velocity and the minimiser run off (233 m/s, measured). Every pair, as
            # for labels that never span two scans.
            edges = None
            cost = RenyiCost(p, t, t_ref, sigma_m, w0, max_dv_m_s=search_m_s, plane=plane,
                             max_points=max_points, subsample=renyi_subsample, labels=labels,
                             weights=weights)
        nt = _newton(cost, w0, search_m_s / 4) if renyi_method == "newton" else None
        for _ in range(3 if newton_recentre else 0):
            if nt is None or np.linalg.norm(nt[0] - w0) <= search_m_s:
                break
            # Newton's minimum lies beyond the pairs gathered around the start (a young
            # track's warm start): gather them around it and go on from there. Nelder-Mead
            # from the start did the same in two runs at 5-10x the cost (measured)
            w0 = nt[0]
            cost = RenyiCost(p, t, t_ref, sigma_m, w0, max_dv_m_s=search_m_s, plane=plane,
                             max_points=max_points, subsample=renyi_subsample, labels=labels,
                             weights=weights, edges=edges)
            nt = _newton(cost, w0, search_m_s / 4)
        if nt is not None and np.linalg.norm(nt[0] - w0) <= search_m_s:
            w, fval, H = nt
            cov = np.linalg.inv(H)
            v, h = motion_from_velocity(w)
            return MotionEstimate(v, h, cov, float(fval), len(p), n_scans)
        # xatol 0.5 mm/s: 20x finer than the 10 mm/s the tracker is judged by; 1e-4 took
        # ~40 % more evaluations for changes below 0.3 mm/s
        res = minimize(cost, w0, method="Nelder-Mead",
                       options={"xatol": 5e-4, "fatol": 1e-6, "initial_simplex":
                                [w0, w0 + [search_m_s / 4, 0], w0 + [0, search_m_s / 4]]})
        w = res.x
        if np.linalg.norm(w - w0) > search_m_s:  # left the region whose pairs were gathered
            cost = RenyiCost(p, t, t_ref, sigma_m, w, max_dv_m_s=search_m_s, plane=plane,
                             max_points=max_points, subsample=renyi_subsample, labels=labels,
                             weights=weights, edges=edges)
            res = minimize(cost, w, method="Nelder-Mead", options={"xatol": 5e-4, "fatol": 1e-6})
            w = res.x
        H = _hessian(cost, w, np.array([2e-3, 2e-3]))
        try:
            cov = np.linalg.inv(H) if np.all(np.linalg.eigvalsh(H) > 0) else None
        except np.linalg.LinAlgError:
            cov = None
        fval = float(res.fun)
    else:
        def f(wv):
            q = q_xy(wv)
            return sum(voxel_entropy(q + o * voxel_m / voxel_offsets, voxel_m, plane)
                       for o in range(voxel_offsets)) / voxel_offsets

        def q_xy(wv):
            q = compensate(p, t, wv, t_ref)
            return q[:, :2] if plane else q

        if voxel_max_points is not None and len(p) > voxel_max_points:
            # bounded work per evaluation: evenly spaced in time order, as the Rényi sum
            sel = np.argsort(t, kind="stable")[
                np.linspace(0, len(p) - 1, voxel_max_points).round().astype(int)]
            p, t = p[sel], t[sel]
        centre = w0
        cov = None
        for half, n in zip(search_m_s / 8.0 ** np.arange(len(voxel_grid)), voxel_grid):
            g = np.linspace(-half, half, n)
            W = centre + np.stack(np.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2)
            if plane:
                # a sum of (m,) arrays: an array (mypy sees sum()'s int start)
                vals = cast(np.ndarray, sum(_voxel_entropy_grid(p[:, :2], t, W, t_ref, voxel_m,
                                                                o * voxel_m / voxel_offsets)
                                            for o in range(voxel_offsets)) / voxel_offsets)
            else:
                vals = np.array([f(wv) for wv in W])
            best = W[vals <= vals.min() + 1e-12]
            centre = best.mean(axis=0)
            fval = float(vals.min())
            step = g[1] - g[0]
        spread = np.cov(best.T) if len(best) > 2 else np.zeros((2, 2))
        cov = spread + np.eye(2) * step ** 2 / 12.0
        w = centre
    v, h = motion_from_velocity(w)
    return MotionEstimate(v, h, cov, fval, len(p), n_scans)
