"""Per-mirror least-squares calibration against walls (paper Section IV, eq. 10).

For each mirror, find the mounting error ``(dalpha, dbeta, dd)`` that puts its reflected
beams on the walls fitted from the direct beams::

    argmin  sum_k sum_i ((v_i - v_i^d) . n_k)^2    s.t. bounds      (eq. 10)

``v_i`` is the reflected beam's point under the candidate perturbation. Two point models:

* ``"exact"`` (default): the geometry core - the mirror's patch perturbed by
  :meth:`~nodlidar.geometry.MirrorPatch.perturbed` (the only place perturbations are
  applied), a one-mirror :class:`~nodlidar.beams.BeamModel` built from it, and
  :meth:`~nodlidar.beams.BeamModel.points` with each beam's nod angle.
* ``"paper"``: the paper's eqs 4-8 as printed (:func:`~nodlidar.closed_form.eq4_8_point`),
  read in the sensor frame the way ``tests/test_paper_reproduction.py`` does (x/y swapped
  as eq. 7 writes them; the right side by mirror symmetry), then nodded. Kept for
  comparison; docs/paper-reproduction.md explains why it cannot fit.

Uncertainty: ``cov = s^2 (J^T J)^-1`` at the solution with ``s^2 = sum(res^2)/(n - 3)``
(``sigma_fit``), plus the wall planes' covariance propagated through the fit (``sigma``):
the planes come from noisy direct beams too, and for dalpha that term dominates.
Degenerate data is refused (:class:`~nodlidar.errors.CalibrationError`): fewer than three
wall orientations, too few reflected points on a mirror, an ill-conditioned ``J^T J``.

Beam map: the first round takes each beam's mirror (or none) from the design. An as-built
mirror turned by tens of mrad reaches into its neighbour's window or into the middle one
(Table I: steps 271-278 and 485-498 of the design's direct window are folded by R2 and
L2), and those beams, taken as direct, pull the wall plane off by centimetres once the
range noise (1 % beyond 1 m) hides them from the plane's outlier test. So each later round
re-traces which mirror every beam reaches through the mirrors fitted so far - exactly as
the runtime assembly does with a calibration (:func:`nodlidar.verify.verify`, first hit on
the finite patches) - refits the planes from the beams that are direct in both maps and each
mirror from the beams that reach it, warm-started, until the map stops changing (``rounds``).

The ``[calibration]`` table of a design file (all keys optional)::

    [calibration]
    dalpha_bound_rad = 0.1      # |dalpha| <= this
    dbeta_bound_rad = 0.1
    dd_bound_m = 0.03
    min_points = 100            # reflected points per mirror over all walls
    min_walls = 3
    min_wall_angle_deg = 10.0   # walls closer than this in orientation count as one
    max_condition = 1e10        # of the column-scaled J^T J
    band_m = 0.0225             # the paper's +-2.25 cm band in the residual statistics
    plane_mad_k = 4.0           # plane-fit outlier threshold [robust sigmas]
    outlier_mad_k = 5.0         # reflected-point outlier threshold after the first fit
    min_nod_span_rad = 0.1      # nod range a mirror's beams must cover (dbeta observability)
    rounds = 3                  # fit rounds (1 = the design's beam map only; see "Beam map")
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np
from scipy.optimize import least_squares

from ..beams import BeamModel
from ..closed_form import eq4_8_point
from ..errors import CalibrationError, require
from ..geometry import Perturbation
from .walls import Plane, WallCapture, check_wall_orientations, fit_plane

__all__ = ["CalibrationConfig", "calibration_config", "ResidualStats", "MirrorFit",
           "CaptureFit", "CalibrationResult", "calibrate", "fit_planes", "beam_map", "MODELS",
           "design_hash"]

MODELS = ("exact", "paper")
PARAMS = ("dalpha", "dbeta", "dd")


@dataclass(frozen=True)
class CalibrationConfig:
    """Bounds and thresholds of the fit (the design file's ``[calibration]`` table)."""

    dalpha_bound_rad: float = 0.1
    dbeta_bound_rad: float = 0.1
    dd_bound_m: float = 0.03
    min_points: int = 100
    min_walls: int = 3
    min_wall_angle_deg: float = 10.0
    max_condition: float = 1e10
    band_m: float = 0.0225
    plane_mad_k: float = 4.0
    outlier_mad_k: float = 5.0
    min_nod_span_rad: float = 0.1
    rounds: int = 3

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            require(isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)
                    and v > 0, f"calibration.{f.name}", v, "a finite number > 0")
        for name in ("min_points", "min_walls", "rounds"):
            v = getattr(self, name)
            require(float(v).is_integer(), f"calibration.{name}", v, "a whole number")
        require(self.min_walls >= 3, "calibration.min_walls", self.min_walls,
                ">= 3 (fewer walls cannot separate the three parameters)")
        require(self.rounds <= 50, "calibration.rounds", self.rounds, "1 .. 50")

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        b = np.array([self.dalpha_bound_rad, self.dbeta_bound_rad, self.dd_bound_m])
        return -b, b


def calibration_config(source=None) -> CalibrationConfig:
    """The ``[calibration]`` table of a DesignSpec (or a dict); defaults where absent."""
    if source is None:
        table: dict[str, Any] = {}
    elif isinstance(source, dict):
        table = source
    else:
        table = source.sections.get("calibration", {})
    from ..validation import check_keys  # unknown keys: the nearest valid one named

    check_keys(table, [f.name for f in fields(CalibrationConfig)], "calibration")
    return CalibrationConfig(**table)


def design_hash(spec) -> str:
    """Short hash [16 hex] of a design's geometric parameters (lidar, layout, placement,
    mirror, nod) - not its name, description, reference numbers or tool tables, which do
    not change the geometry a calibration belongs to."""
    import hashlib
    import json

    d = spec.to_dict()
    geo = {k: d[k] for k in ("lidar", "layout", "placement", "mirror", "nod")}
    return hashlib.sha256(json.dumps(geo, sort_keys=True).encode()).hexdigest()[:16]


@dataclass(frozen=True)
class ResidualStats:
    """Point-to-plane residuals of one set of points [m]."""

    n: int
    mean_m: float
    rms_m: float
    max_abs_m: float
    within_band: float
    band_m: float

    @classmethod
    def of(cls, res: np.ndarray, band_m: float) -> ResidualStats:
        res = np.asarray(res, dtype=float)
        return cls(n=int(res.size), mean_m=float(res.mean()), rms_m=float(np.sqrt(np.mean(res**2))),
                   max_abs_m=float(np.max(np.abs(res))),
                   within_band=float(np.mean(np.abs(res) <= band_m)), band_m=float(band_m))

    def to_dict(self) -> dict[str, float]:
        return {f.name: getattr(self, f.name) for f in fields(self)}


@dataclass(frozen=True, eq=False)
class MirrorFit:
    """One mirror's calibration.

    Attributes
    ----------
    name : str
    perturbation : Perturbation
        The fitted mounting error.
    sigma : (3,) float
        1-sigma of (dalpha [rad], dbeta [rad], dd [m]): the Jacobian's ``sigma_fit`` plus
        the wall planes' own uncertainty propagated through the fit.
    sigma_fit : (3,) float
        1-sigma from the Jacobian alone, ``sqrt(diag(s^2 (J^T J)^-1))`` (the planes taken
        as exact).
    before, after : ResidualStats
        Residuals of the used points with no perturbation / the fitted one.
    capture : (n,) int
        Capture index of each reflected point (all finite ones, outliers included).
    residual_before, residual_after : (n,) float
        Signed point-to-plane distance of each point [m].
    points_after : (n, 3) float
        Calibrated points in the sensor frame [m].
    used : (n,) bool
        Points kept by the outlier rejection.
    condition : float
        Condition number of the column-scaled ``J^T J`` at the solution.
    at_bound : tuple of str
        Parameters that ended on a bound (the fit is then not trustworthy).
    nfev : int
        Residual evaluations.
    """

    name: str
    perturbation: Perturbation
    sigma: np.ndarray
    sigma_fit: np.ndarray
    before: ResidualStats
    after: ResidualStats
    capture: np.ndarray
    residual_before: np.ndarray
    residual_after: np.ndarray
    points_after: np.ndarray
    used: np.ndarray
    condition: float
    at_bound: tuple[str, ...]
    nfev: int

    def to_dict(self) -> dict[str, Any]:
        p = self.perturbation
        return {"name": self.name, "dalpha_rad": p.dalpha, "dbeta_rad": p.dbeta, "dd_m": p.dd,
                "sigma_dalpha_rad": float(self.sigma[0]), "sigma_dbeta_rad": float(self.sigma[1]),
                "sigma_dd_m": float(self.sigma[2]),
                "sigma_fit": [float(v) for v in self.sigma_fit], "n_points": int(self.used.size),
                "n_used": int(self.used.sum()), "before": self.before.to_dict(),
                "after": self.after.to_dict(), "condition": self.condition,
                "at_bound": list(self.at_bound), "nfev": self.nfev}


@dataclass(frozen=True, eq=False)
class CaptureFit:
    """One wall capture's plane and its direct points (sensor frame)."""

    name: str
    plane: Plane
    direct_points: np.ndarray


@dataclass(frozen=True, eq=False)
class CalibrationResult:
    """Everything :func:`calibrate` found.

    ``rounds``: fit rounds run (module docstring, "Beam map"); ``beams_remapped``: beams
    whose mirror (or none) in the last round's map differs from the design's.
    """

    design_name: str
    design_hash: str
    model: str
    captures: tuple[CaptureFit, ...]
    mirrors: dict[str, MirrorFit] = field(default_factory=dict)
    rounds: int = 1
    beams_remapped: int = 0

    @property
    def perturbations(self) -> dict[str, Perturbation]:
        """Mirror name -> fitted Perturbation (feed to ``design.beam_model``)."""
        return {k: m.perturbation for k, m in self.mirrors.items()}

    def to_dict(self) -> dict[str, Any]:
        return {"design": self.design_name, "design_hash": self.design_hash, "model": self.model,
                "rounds": self.rounds, "beams_remapped": self.beams_remapped,
                "walls": [{"name": c.name, "normal": c.plane.normal.tolist(),
                           "offset_m": c.plane.offset_m, "plane_rms_m": c.plane.rms_m,
                           "n_direct": int(c.plane.inliers.sum())} for c in self.captures],
                "mirrors": {k: m.to_dict() for k, m in self.mirrors.items()}}


# ---------------------------------------------------------------------------------------


def fit_planes(design, captures: list[WallCapture], config: CalibrationConfig,
               direct: np.ndarray | None = None) -> list[CaptureFit]:
    """Robust PCA plane of each capture's direct beams (independent of the mirrors).

    ``direct`` : (n_steps,) bool over the lidar's valid steps, the beams taken as direct
    (default: the design's beam map; with the mirrors lifted every beam is direct).
    """
    lidar = design.lidar
    out = []
    for k, cap in enumerate(captures):
        name = cap.name or f"capture {k}"
        bm = design.beam_model(mirrors_deployed=cap.mirrors_deployed)
        if direct is None or not cap.mirrors_deployed:
            is_direct = bm.mirror_index(cap.steps) == -1
        else:
            is_direct = np.asarray(direct)[cap.steps - lidar.step_min]
        sel = is_direct & np.isfinite(cap.ranges_m)
        pts = bm.points(cap.steps[sel], cap.ranges_m[sel], cap.nod_rad[sel])
        plane = fit_plane(pts, mad_k=config.plane_mad_k, name=name)
        out.append(CaptureFit(name=name, plane=plane, direct_points=pts[plane.inliers]))
    return out


def beam_map(design, perturbations: dict[str, Perturbation] | None) -> np.ndarray:
    """(n_steps,) int over the valid steps: the mirror each beam reaches with the mirrors
    perturbed (``-1`` none; ``-2`` reflected but blocked on its way out), by the same trace
    as the runtime assembly's (:func:`nodlidar.verify.verify`, first hit on the patches)."""
    from ..verify import verify

    v = verify(design, perturbations or None)
    return np.where((v.hit >= 0) & (v.blocker != -1), -2, v.hit)


class _MirrorProblem:
    """The residual function of one mirror over all captures (vectorised over points)."""

    def __init__(self, design, name: str, steps, ranges, nod, normals, offsets, model: str,
                 mirror_steps: np.ndarray | None = None):
        self.design = design
        self.sol = design.mirror(name)
        self.steps, self.ranges, self.nod = steps, ranges, nod
        self.normals, self.offsets = normals, offsets
        self.model = model
        lidar = design.lidar
        # a one-mirror beam map: the steps reaching this mirror (default: the design's) ->
        # index 0, everything else direct
        self.mirror_steps = self.sol.steps if mirror_steps is None else np.asarray(mirror_steps)
        self.mos = np.full(lidar.n_steps, -1, dtype=int)
        self.mos[self.mirror_steps - lidar.step_min] = 0
        self.pivot = np.asarray(design.spec.nod.pivot_m, dtype=float)
        if model == "paper":
            self._paper_setup()

    def subset(self, mask: np.ndarray) -> _MirrorProblem:
        """The same problem on the points selected by ``mask``."""
        return _MirrorProblem(self.design, self.sol.name, self.steps[mask], self.ranges[mask],
                              self.nod[mask], self.normals[mask], self.offsets[mask], self.model,
                              self.mirror_steps)

    def points(self, x: np.ndarray) -> np.ndarray:
        """Sensor-frame points (n, 3) of this mirror's beams under perturbation ``x``."""
        if self.model == "paper":
            return self._paper_points(x)
        patch = self.sol.patch.perturbed(Perturbation.from_array(x))
        bm = BeamModel.build(self.design.lidar, [patch], self.mos, self.pivot)
        return bm.points(self.steps, self.ranges, self.nod)

    def residuals(self, x: np.ndarray) -> np.ndarray:
        return np.einsum("ij,ij->i", self.points(x), self.normals) - self.offsets

    # -- the paper's eqs 4-8 ---------------------------------------------------------
    def _paper_setup(self) -> None:
        sol = self.sol
        # eqs 4-8 are written for a left mirror; a right one is its mirror image (y -> -y)
        self.sgn = float(sol.sign)
        th = self.design.lidar.bearing_from_step(self.steps)
        self.theta = self.sgn * th
        self.alpha = self.sgn * sol.patch.normal_azimuth
        self.d = sol.standoff_m
        self.h = -sol.patch.hinge_z

    def _paper_points(self, x: np.ndarray) -> np.ndarray:
        p = eq4_8_point(self.ranges, self.theta, self.alpha, self.d, self.h,
                        self.sgn * x[0], x[1], x[2])
        # eq. 7 gives x = r sin(theta_a), y = r cos(theta_a): swap to the sensor's x/y
        q = np.stack([p[:, 1], -self.sgn * p[:, 0], p[:, 2]], -1) - self.pivot
        c, s = np.cos(self.nod), np.sin(self.nod)
        return np.stack([c * q[:, 0] + s * q[:, 2], q[:, 1], -s * q[:, 0] + c * q[:, 2]], -1) + self.pivot


def _scaled_condition(J: np.ndarray) -> float:
    scale = np.linalg.norm(J, axis=0)
    if np.any(scale == 0):
        return math.inf
    s = np.linalg.svd(J / scale, compute_uv=False)
    return float((s[0] / s[-1]) ** 2) if s[-1] > 0 else math.inf


def _fit_mirror(prob: _MirrorProblem, config: CalibrationConfig, x0: np.ndarray,
                capture: np.ndarray, planes: list[Plane]) -> MirrorFit:
    lo, hi = config.bounds
    n = prob.ranges.size
    used = np.ones(n, dtype=bool)
    r0 = prob.residuals(np.zeros(3))
    x = np.clip(x0, lo * 0.999, hi * 0.999)
    nfev = 0
    for _ in range(4):
        fit_mask = used
        sol = least_squares(prob.subset(fit_mask).residuals, x, bounds=(lo, hi), method="trf",
                            x_scale="jac", xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=200)
        x, nfev = sol.x, nfev + sol.nfev
        res = prob.residuals(x)
        # after the first fit, drop points that no mirror pose explains (beams clipped by
        # the glass edge, hitting something other than the wall)
        med = np.median(res[used])
        mad = 1.4826 * np.median(np.abs(res[used] - med))
        new = np.abs(res - med) <= config.outlier_mad_k * max(mad, 1e-4)
        if new.sum() < config.min_points:
            raise CalibrationError(f"mirror {prob.sol.name}: only {int(new.sum())} reflected points "
                                   f"agree with one mirror pose; need {int(config.min_points)}")
        if np.array_equal(new, used):
            break
        used = new
    used = fit_mask  # the points of the last fit (its Jacobian and residuals)
    J = sol.jac
    cond = _scaled_condition(J)
    if not cond <= config.max_condition:
        raise CalibrationError(
            f"mirror {prob.sol.name}: the walls do not determine (dalpha, dbeta, dd) - the "
            f"least-squares problem is ill-conditioned (cond(J^T J) = {cond:.3g} > "
            f"{config.max_condition:.3g}); capture the wall at more distinct orientations "
            f"and with the head nodding")
    dof = max(1, int(used.sum()) - 3)
    s2 = float(np.sum(sol.fun**2) / dof)
    JtJ_inv = np.linalg.inv(J.T @ J)
    cov_fit = s2 * JtJ_inv
    # the walls are estimates too: propagate each plane's covariance through the fit,
    # dx/dtheta_k = -(J^T J)^-1 J^T G_k (G_k: d residual / d plane k, zero off capture k)
    pts = prob.points(x)
    cov_planes = np.zeros((3, 3))
    kk = capture[used]
    for k, pl in enumerate(planes):
        sel = kk == k
        if np.any(sel):
            H = -JtJ_inv @ (J[sel].T @ pl.distance_jacobian(pts[used][sel]))
            cov_planes += H @ pl.cov @ H.T
    at_bound = tuple(p for p, v, a, b in zip(PARAMS, x, lo, hi)
                     if abs(v - a) < 1e-6 * (b - a) or abs(v - b) < 1e-6 * (b - a))
    return MirrorFit(name=prob.sol.name, perturbation=Perturbation.from_array(x),
                     sigma=np.sqrt(np.diag(cov_fit + cov_planes)),
                     sigma_fit=np.sqrt(np.diag(cov_fit)),
                     before=ResidualStats.of(r0[used], config.band_m),
                     after=ResidualStats.of(res[used], config.band_m),
                     capture=capture, residual_before=r0, residual_after=res,
                     points_after=pts, used=used, condition=cond,
                     at_bound=at_bound, nfev=nfev)


def calibrate(design, captures: list[WallCapture], *, model: str = "exact",
              config: CalibrationConfig | None = None, mirrors: list[str] | None = None,
              x0: dict[str, Perturbation] | None = None) -> CalibrationResult:
    """Fit every mirror's (dalpha, dbeta, dd) from wall captures.

    Parameters
    ----------
    design : Design
        The solved design the sensor was built to.
    captures : list of WallCapture
        At least three sweeps of a flat wall at distinct orientations, mirrors deployed.
    model : "exact" or "paper"
        Point model (module docstring).
    config : CalibrationConfig, optional
        Default: the design file's ``[calibration]`` table.
    mirrors : list of str, optional
        Subset of mirrors to fit (default all).
    x0 : dict, optional
        Starting perturbations (default zero: the design).

    Raises
    ------
    CalibrationError
        Degenerate data, with what is wrong.
    """
    require(model in MODELS, "model", model, " or ".join(MODELS))
    config = config or calibration_config(design.spec)
    captures = list(captures)
    if not captures:
        raise CalibrationError("no wall captures given; calibration needs at least "
                               f"{config.min_walls} captures at different orientations")
    lidar = design.lidar
    names = mirrors or [m.name for m in design.mirrors]
    index = {m.name: i for i, m in enumerate(design.mirrors)}
    design_map = np.asarray(design.mirror_of_step)
    hit = design_map
    start = {name: (x0 or {}).get(name, Perturbation()) for name in names}
    out: dict[str, MirrorFit] = {}
    for rnd in range(int(config.rounds)):
        # beams direct in the design's map and in the current one give the planes
        fits = fit_planes(design, captures, config, direct=(design_map == -1) & (hit == -1))
        check_wall_orientations([c.plane for c in fits], [c.name for c in fits],
                                min_walls=int(config.min_walls),
                                min_angle_rad=np.radians(config.min_wall_angle_deg))
        out = {name: _fit_one(design, name, captures, fits, config, model, start[name],
                              np.flatnonzero(hit == index[name]) + lidar.step_min)
               for name in names}
        if rnd + 1 == int(config.rounds):
            break
        fitted = {name: m.perturbation for name, m in out.items()}
        # mirrors not fitted here keep their starting pose
        new_hit = beam_map(design, {**{m.name: (x0 or {}).get(m.name, Perturbation())
                                       for m in design.mirrors}, **fitted})
        if np.array_equal(new_hit, hit):
            break
        hit = new_hit
        start = fitted
    return CalibrationResult(design_name=design.spec.name, design_hash=design_hash(design.spec),
                             model=model, captures=tuple(fits), mirrors=out, rounds=rnd + 1,
                             beams_remapped=int(np.count_nonzero(hit != design_map)))


def _fit_one(design, name: str, captures: list[WallCapture], fits: list[CaptureFit],
             config: CalibrationConfig, model: str, start: Perturbation,
             mirror_steps: np.ndarray) -> MirrorFit:
    """Fit one mirror from the beams of ``mirror_steps`` over all deployed captures."""
    parts = []
    for k, (cap, cf) in enumerate(zip(captures, fits)):
        if not cap.mirrors_deployed:
            continue
        sel = np.isin(cap.steps, mirror_steps) & np.isfinite(cap.ranges_m)
        parts.append((k, cap.steps[sel], cap.ranges_m[sel], cap.nod_rad[sel], cf.plane))
    n_pts = sum(p[1].size for p in parts)
    if n_pts < config.min_points:
        raise CalibrationError(f"mirror {name}: only {n_pts} reflected points on the walls; "
                               f"need at least {int(config.min_points)} (are the mirrors deployed "
                               "and is the wall in front of the sensor?)")
    steps, ranges, nod = (np.concatenate([p[i] for p in parts]) for i in (1, 2, 3))
    span = float(np.ptp(nod))
    if span < config.min_nod_span_rad:
        # without nodding a tilted beam meets a vertical wall at a range change of
        # order dbeta^2: the sign of dbeta is lost and the fit finds a mirror image
        raise CalibrationError(
            f"mirror {name}: its reflected beams cover a nod range of only {span:.3g} rad; "
            f"the tilt dbeta is observable only with the head nodding (need >= "
            f"{config.min_nod_span_rad:g} rad)")
    kidx = np.concatenate([np.full(p[1].size, p[0]) for p in parts])
    normals = np.concatenate([np.broadcast_to(p[4].normal, (p[1].size, 3)) for p in parts])
    offsets = np.concatenate([np.full(p[1].size, p[4].offset_m) for p in parts])
    prob = _MirrorProblem(design, name, steps, ranges, nod, normals, offsets, model, mirror_steps)
    return _fit_mirror(prob, config, start.as_array(), kidx, [c.plane for c in fits])
