"""Wall captures and the robust PCA plane fit of their direct (unreflected) beams.

A :class:`WallCapture` is one nodded sweep of the sensor facing a flat wall: per beam its
step, measured range and the head's nod angle at the beam's time. The middle window's
beams see the wall directly, so their sensor-frame points do not depend on any mirror
perturbation; their plane (paper Section IV: "PCA based plane fitting") is the reference
against which the reflected beams are calibrated.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import CalibrationError, ParameterError
from ..geometry import TOL, incidence_angle

__all__ = ["WallCapture", "Plane", "fit_plane", "fit_plane_msac", "check_wall_orientations",
           "save_capture", "load_capture"]


@dataclass(frozen=True, eq=False)
class WallCapture:
    """One capture of a flat wall (a nodded sweep).

    Attributes
    ----------
    steps : (n,) int
        Lidar step of each beam.
    ranges_m : (n,) float
        Measured range (total path length for reflected beams) [m]; NaN = no return.
    nod_rad : (n,) float
        Nod (pitch) angle of the head at each beam's time [rad].
    mirrors_deployed : bool
        Whether the mirrors were down (reflecting) during the capture.
    name : str
        Label used in reports and figures.
    """

    steps: np.ndarray
    ranges_m: np.ndarray
    nod_rad: np.ndarray
    mirrors_deployed: bool = True
    name: str = ""

    def __post_init__(self) -> None:
        steps = np.asarray(self.steps)
        r = np.asarray(self.ranges_m, dtype=float)
        nod = np.asarray(self.nod_rad, dtype=float)
        if steps.ndim != 1 or not np.issubdtype(steps.dtype, np.integer):
            raise ParameterError("capture.steps", f"shape {steps.shape} dtype {steps.dtype}",
                                 "a 1-D integer array")
        if r.shape != steps.shape or nod.shape != steps.shape:
            raise ParameterError("capture.ranges_m/nod_rad", f"shapes {r.shape}, {nod.shape}",
                                 f"the shape of steps, {steps.shape}")
        object.__setattr__(self, "steps", steps.astype(int))
        object.__setattr__(self, "ranges_m", r)
        object.__setattr__(self, "nod_rad", nod)

    def __len__(self) -> int:
        return len(self.steps)


@dataclass(frozen=True, eq=False)
class Plane:
    """A plane fitted to points: ``{p : (p - point) . normal = 0}``.

    ``normal`` points away from the sensor origin (``point . normal > 0``), so a positive
    signed distance means "behind the wall".

    Attributes
    ----------
    point : (3,) float
        Centroid of the inliers [m].
    normal : (3,) float
        Unit normal.
    rms_m : float
        RMS distance of the inliers to the plane [m].
    inliers : (n,) bool
        Which of the input points were kept.
    tangents : (2, 3) float
        Two unit in-plane directions (the principal axes).
    cov : (3, 3) float
        Covariance of the plane's small-motion parameters ``(ta, tb, dc)``: the normal
        tilts to ``normal + ta*tangents[0] + tb*tangents[1]`` and the plane moves by ``dc``
        along it; :meth:`distance_jacobian` gives how a point's signed distance changes.
    """

    point: np.ndarray
    normal: np.ndarray
    rms_m: float
    inliers: np.ndarray
    tangents: np.ndarray = field(default_factory=lambda: np.zeros((2, 3)))
    cov: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))

    def distance_jacobian(self, points: np.ndarray) -> np.ndarray:
        """d(signed distance)/d(ta, tb, dc) of ``points`` (n, 3) -> (n, 3)."""
        q = np.asarray(points, dtype=float) - self.point
        return np.stack([q @ self.tangents[0], q @ self.tangents[1], -np.ones(len(q))], -1)

    @property
    def offset_m(self) -> float:
        """Distance of the plane from the origin [m] (``point . normal``)."""
        return float(self.point @ self.normal)

    def signed_distance(self, points: np.ndarray) -> np.ndarray:
        """Signed distance [m] of ``points`` ``(n, 3)`` to the plane, ``(n,)``."""
        return np.asarray(points, dtype=float) @ self.normal - self.offset_m


def _pca(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    c = points.mean(axis=0)
    # the right singular vector of the smallest singular value is the plane normal
    _, _, vt = np.linalg.svd(points - c, full_matrices=False)
    return c, vt[-1]


def _require_spread(q: np.ndarray, centre: np.ndarray, min_spread: float, name: str) -> None:
    """Refuse points ``(n, 3)`` that lie almost on a line: their second singular value about
    ``centre`` below ``min_spread`` times the first. Points on a line (a capture without
    nodding) leave the plane's tilt about that line free."""
    sv = np.linalg.svd(q - centre, compute_uv=False)
    if sv[1] < min_spread * sv[0]:
        raise CalibrationError(f"{name}: the direct-beam points lie almost on a line (spread ratio "
                               f"{sv[1] / sv[0]:.3g} < {min_spread}); a wall plane needs the head to "
                               "nod during the capture")


def fit_plane(points: np.ndarray, *, mad_k: float = 4.0, max_iter: int = 20,
              min_points: int = 20, min_spread: float = 0.02, name: str = "capture") -> Plane:
    """PCA plane fit with iterative outlier trimming.

    Fit by PCA, then drop points further than ``mad_k`` robust sigmas (1.4826 MAD of the
    signed distances) and refit, until the inlier set stops changing.

    Parameters
    ----------
    points : (n, 3) float
        Points [m]; rows with NaN are ignored.
    mad_k : float
        Rejection threshold in robust sigmas.
    max_iter : int
        Maximum number of trimming rounds.
    min_points : int
        Refuse fewer finite points than this.
    min_spread : float
        Refuse points whose second principal spread is below this fraction of the first
        (collinear points do not define a plane).
    name : str
        Capture name for error messages.

    Raises
    ------
    CalibrationError
        Too few points, or points on a line.
    """
    p = np.asarray(points, dtype=float)
    finite = np.all(np.isfinite(p), axis=1)
    if finite.sum() < min_points:
        raise CalibrationError(f"{name}: only {int(finite.sum())} direct-beam points on the wall; "
                               f"a plane fit needs at least {min_points}")
    keep = finite.copy()
    for _ in range(max_iter):
        c, n = _pca(p[keep])
        dist = np.where(finite, (np.where(finite[:, None], p, 0.0) - c) @ n, np.inf)
        med = np.median(dist[keep])
        mad = 1.4826 * np.median(np.abs(dist[keep] - med))
        # floor the scale at 0.1 mm so noise-free data does not reject rounding error
        new = finite & (np.abs(dist - med) <= mad_k * max(mad, 1e-4))
        if new.sum() < min_points:
            raise CalibrationError(f"{name}: fewer than {min_points} direct-beam points are "
                                   f"consistent with one plane; is the wall flat and in view?")
        if np.array_equal(new, keep):
            break
        keep = new
    c, n = _pca(p[keep])
    _require_spread(p[keep], c, min_spread, name)
    if c @ n < 0:
        n = -n
    rms = float(np.sqrt(np.mean(((p[keep] - c) @ n) ** 2)))
    _, _, vt = np.linalg.svd(p[keep] - c, full_matrices=False)
    pl = Plane(point=c, normal=n, rms_m=rms, inliers=keep, tangents=vt[:2])
    # least-squares covariance of the plane parameters from its own residual scatter
    A = pl.distance_jacobian(p[keep])
    s2 = rms**2 * len(A) / max(1, len(A) - 3)
    object.__setattr__(pl, "cov", s2 * np.linalg.inv(A.T @ A))
    return pl


def _weighted_plane(p: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted least-squares plane (centroid, unit normal) of points ``p`` with weights ``w``."""
    c = (w[:, None] * p).sum(0) / w.sum()
    q = (p - c) * np.sqrt(w)[:, None]
    _, _, vt = np.linalg.svd(q, full_matrices=False)
    return c, vt[-1]


def fit_plane_msac(points: np.ndarray, sigma_m: np.ndarray, *, k_sigma: float = 4.0,
                   n_hypotheses: int = 128, n_score: int = 3000, min_points: int = 20,
                   min_spread: float = 0.02,
                   seed: int = 0, name: str = "capture") -> Plane:
    """Robust plane of ``points`` by MSAC consensus, refined by weighted least squares.

    Each hypothesis is the plane through three random points; its cost is
    ``sum(min((d_i / t_i)^2, 1))`` with the per-point threshold ``t_i = k_sigma * sigma_m[i]``
    (the lidar's range noise at that point's range: a point on the wall is within it with
    probability > 99.99 % for ``k_sigma = 4``). The best hypothesis's inliers are refitted
    by least squares weighted with ``1/sigma^2``, the inliers re-selected, until stable.
    Clutter in front of the wall, a doorway's second wall behind it, a pole: they form
    smaller consensus sets and end up as outliers rather than pulling the plane.

    Parameters
    ----------
    points : (n, 3) float
        Points [m]; rows with NaN are ignored.
    sigma_m : (n,) float
        1-sigma range noise of each point [m].
    k_sigma : float
        Inlier threshold in sigmas.
    n_hypotheses : int
        Three-point samples tried (vectorised: all at once). With half the points on the
        wall, 128 samples all miss it with probability 4e-8.
    n_score : int
        Hypotheses are scored on this many random points (the refinement uses all).
    min_points, min_spread, name
        As :func:`fit_plane`.
    seed : int
        Sampling seed (the result is deterministic).

    Returns
    -------
    Plane
        ``inliers`` over the input rows; ``rms_m`` over the inliers; ``cov`` from the
        weighted fit.
    """
    p = np.asarray(points, dtype=float)
    sig = np.broadcast_to(np.asarray(sigma_m, dtype=float), (len(p),))
    finite = np.all(np.isfinite(p), axis=1) & np.isfinite(sig) & (sig > 0)
    n_fin = int(finite.sum())
    if n_fin < min_points:
        raise CalibrationError(f"{name}: only {n_fin} direct-beam points on the wall; "
                               f"a plane fit needs at least {min_points}")
    idx = np.flatnonzero(finite)
    q, t = p[idx], k_sigma * sig[idx]
    rng = np.random.default_rng(seed)
    tri = rng.integers(0, len(q), size=(n_hypotheses, 3))
    a, b, c = q[tri[:, 0]], q[tri[:, 1]], q[tri[:, 2]]
    nrm = np.cross(b - a, c - a)
    ln = np.linalg.norm(nrm, axis=1)
    good = ln > TOL.collinear_m2
    nrm, a = nrm[good] / ln[good, None], a[good]
    if len(nrm) == 0:
        raise CalibrationError(f"{name}: the direct-beam points do not span a plane")
    # (points, hypotheses) distances in threshold units, on a random subset of the points
    sub = rng.choice(len(q), size=min(n_score, len(q)), replace=False)
    d = (q[sub] @ nrm.T - np.einsum("ij,ij->i", a, nrm)[None, :]) / t[sub, None]
    best = int(np.argmin(np.minimum(d**2, 1.0).sum(axis=0)))
    inl = np.abs(q @ nrm[best] - a[best] @ nrm[best]) <= t
    w = 1.0 / sig[idx] ** 2
    for _ in range(20):
        if inl.sum() < min_points:
            raise CalibrationError(f"{name}: fewer than {min_points} direct-beam points are "
                                   f"consistent with one plane; is the wall flat and in view?")
        cen, n = _weighted_plane(q[inl], w[inl])
        new = np.abs((q - cen) @ n) <= t
        if np.array_equal(new, inl):
            break
        inl = new
    cen, n = _weighted_plane(q[inl], w[inl])
    _require_spread(q[inl], q[inl].mean(0), min_spread, name)
    if cen @ n < 0:
        n = -n
    dist = (q[inl] - cen) @ n
    rms = float(np.sqrt(np.mean(dist**2)))
    _, _, vt = np.linalg.svd(q[inl] - cen, full_matrices=False)
    keep = np.zeros(len(p), dtype=bool)
    keep[idx[inl]] = True
    pl = Plane(point=cen, normal=n, rms_m=rms, inliers=keep, tangents=vt[:2])
    A = pl.distance_jacobian(q[inl]) * np.sqrt(w[inl])[:, None]
    # weighted LS covariance, scaled by the observed chi^2 per degree of freedom
    s2 = float(np.sum(w[inl] * dist**2)) / max(1, int(inl.sum()) - 3)
    object.__setattr__(pl, "cov", s2 * np.linalg.inv(A.T @ A))
    return pl


def check_wall_orientations(planes: list[Plane], names: list[str], *, min_walls: int = 3,
                            min_angle_rad: float = np.radians(10.0)) -> int:
    """Refuse captures that do not show ``min_walls`` mutually non-parallel wall planes.

    Planes whose normals are within ``min_angle_rad`` of each other count as one
    orientation (greedy grouping). Returns the number of distinct orientations.

    Raises
    ------
    CalibrationError
        Naming the captures and the angles between their walls.
    """
    if len(planes) < min_walls:
        raise CalibrationError(f"{len(planes)} wall capture(s) given; calibration needs at least "
                               f"{min_walls} captures of the wall at different orientations")
    reps: list[np.ndarray] = []
    for pl in planes:
        # the angle between two planes: a normal's incidence on the other plane
        if all(incidence_angle(pl.normal, r) >= min_angle_rad for r in reps):
            reps.append(pl.normal)
    if len(reps) < min_walls:
        pairs = []
        for i in range(len(planes)):
            for j in range(i + 1, len(planes)):
                a = np.degrees(incidence_angle(planes[i].normal, planes[j].normal))
                pairs.append(f"{names[i]}/{names[j]} {a:.1f} deg")
        raise CalibrationError(
            f"the walls are not mutually non-parallel: only {len(reps)} distinct orientation(s) "
            f"among {len(planes)} captures (angles between wall normals: {', '.join(pairs)}); "
            f"need {min_walls} with at least {np.degrees(min_angle_rad):.1f} deg between each pair")
    return len(reps)


def save_capture(path: str | Path, capture: WallCapture) -> None:
    """Write a capture as ``.npz`` (steps, ranges_m, nod_rad, mirrors_deployed, name)."""
    np.savez_compressed(path, steps=capture.steps, ranges_m=capture.ranges_m,
                        nod_rad=capture.nod_rad, mirrors_deployed=capture.mirrors_deployed,
                        name=capture.name)


def load_capture(path: str | Path) -> WallCapture:
    """Read a capture written by :func:`save_capture`."""
    from ..errors import DesignFileError

    p = Path(path)
    if not p.is_file():
        raise DesignFileError(f"wall capture not found: {p}")
    try:
        with np.load(p) as z:
            return WallCapture(steps=z["steps"], ranges_m=z["ranges_m"], nod_rad=z["nod_rad"],
                               mirrors_deployed=bool(z["mirrors_deployed"]),
                               name=str(z["name"]) or p.stem)
    except (KeyError, ValueError, OSError) as exc:
        raise DesignFileError(f"{p}: not a wall capture (.npz with steps, ranges_m, nod_rad): "
                              f"{exc}") from None
