"""Per-mirror least-squares calibration against walls (paper Section IV, eq. 10), made
robust for real rooms.

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

A real room (issue 12) has doorways, furniture and a second wall behind; each stage keeps
only what the noise model says belongs to the wall:

1. **Wall planes** (:func:`fit_planes`): MSAC consensus over each capture's direct beams
   (:func:`~nodlidar.calibration.walls.fit_plane_msac`), inlier threshold ``gate_sigma``
   times the URG range noise at that range (data sheet +-30 mm / 3 % read as 3 sigma).
2. **Reflected points**, per mirror with the planes fixed: a loose gate around the plane
   at the starting pose (as wide as the parameter bounds can move a point), a robust
   (soft-L1) fit, then points gated to ``gate_sigma`` sigma of their predicted position and
   a plain least-squares refit until the inlier set is stable.
3. **Joint fit**: planes, all mirrors and (optionally, ``intrinsics=True``) the lidar's
   range offset and scale together, every residual weighted by its noise
   (``sigma_r(r) * |n . d|``, d the outgoing ray), inliers re-gated, until stable. Its
   ``s^2 (J^T J)^-1`` is the full covariance (``CalibrationResult.covariance``).

Beam map: the first round takes each beam's mirror (or none) from the design. An as-built
mirror turned by tens of mrad reaches into its neighbour's window or into the middle one
(Table I: steps 271-278 and 485-498 of the design's direct window are folded by R2 and
L2); so each later round re-traces which mirror every beam reaches through the mirrors
fitted so far - exactly as the runtime assembly does with a calibration
(:func:`nodlidar.verify.verify`, first hit on the finite patches) - and refits, until the
map stops changing (``rounds``). Beams whose mirror would change anywhere within
``ambiguity_sigma`` of the fitted parameters (edges, the L1/L2 joint, double bounces) are
listed as ``ambiguous_steps``; the calibration file carries them and the runtime drops them.

Quality gates (:func:`quality_gates`, ``CalibrationResult.problems``): a parameter on a
bound, too few of a mirror's points on the wall, in-band share below what the noise model
predicts, residual or plane RMS above ``max_rms_ratio`` times the noise, a parameter
determined worse than ``max_sigma_*`` (3 sigma = the 3 mrad / 1 mm target), a direct-beam
inlier share below ``min_inlier_share``. Degenerate data is refused outright
(:class:`~nodlidar.errors.CalibrationError`): fewer than three wall orientations, a wall
closer than ``min_wall_distance_m``, too few reflected points, no nodding, an
ill-conditioned ``J^T J``.

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
    plane_mad_k = 4.0           # (kept for old files; the planes use gate_sigma)
    outlier_mad_k = 5.0         # (kept for old files; the points use gate_sigma)
    min_nod_span_rad = 0.1      # nod range a mirror's beams must cover (dbeta observability)
    rounds = 3                  # fit rounds (1 = the design's beam map only; see "Beam map")
    gate_sigma = 4.0            # inlier threshold in range-noise sigmas (planes and points)
    min_inlier_share = 0.5      # of a capture's direct beams / a mirror's near-wall points
    max_rms_ratio = 1.5         # residual RMS / the noise model's prediction
    max_sigma_dalpha_rad = 0.001  # 3 sigma = 3 mrad
    max_sigma_dbeta_rad = 0.001
    max_sigma_dd_m = 0.00034      # 3 sigma ~ 1 mm
    min_wall_distance_m = 0.5   # nearer walls are refused (see quality gates)
    ambiguity_sigma = 3.0       # beams whose mirror changes within this many sigma
    range_offset_bound_m = 0.1  # intrinsics (optional): |offset| <= this
    range_scale_bound = 0.05    # |scale - 1| <= this
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from typing import TYPE_CHECKING, Any

import numpy as np

from ..beams import BeamModel
from ..closed_form import eq4_8_point
from ..errors import CalibrationError, require
from ..geometry import BLOCKED, CLEAR, DIRECT, Perturbation, pitch_about_pivot
from ..verify import verify
from .walls import Plane, WallCapture, check_wall_orientations, fit_plane_msac

if TYPE_CHECKING:
    from ..design import Design
    from ..spec import DesignSpec

__all__ = ["CalibrationConfig", "calibration_config", "ResidualStats", "MirrorFit",
           "CaptureFit", "CalibrationResult", "calibrate", "fit_planes", "beam_map", "MODELS",
           "design_hash", "quality_gates", "ambiguous_steps", "INTRINSICS"]

MODELS = ("exact", "paper")
PARAMS = ("dalpha", "dbeta", "dd")
UNITS = {"dalpha": ("mrad", 1e3), "dbeta": ("mrad", 1e3), "dd": ("mm", 1e3)}
#: The lidar's optional intrinsic parameters: ``r_measured = (1 + range_scale) * r + range_offset_m``.
INTRINSICS = ("range_offset_m", "range_scale")
#: The URG reports whole millimetres: rounding adds (1 mm)^2 / 12 of variance.
_QUANTUM_VAR = 1e-6 / 12


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
    gate_sigma: float = 4.0
    min_inlier_share: float = 0.5
    max_rms_ratio: float = 1.5
    max_sigma_dalpha_rad: float = 1e-3
    max_sigma_dbeta_rad: float = 1e-3
    max_sigma_dd_m: float = 3.4e-4
    min_wall_distance_m: float = 0.5
    ambiguity_sigma: float = 3.0
    range_offset_bound_m: float = 0.1
    range_scale_bound: float = 0.05

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
        require(self.min_inlier_share < 1, "calibration.min_inlier_share", self.min_inlier_share,
                "a fraction in (0, 1)")

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        b = np.array([self.dalpha_bound_rad, self.dbeta_bound_rad, self.dd_bound_m])
        return -b, b

    @property
    def max_sigma(self) -> np.ndarray:
        return np.array([self.max_sigma_dalpha_rad, self.max_sigma_dbeta_rad, self.max_sigma_dd_m])


def calibration_config(source: DesignSpec | dict[str, Any] | None = None) -> CalibrationConfig:
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


def design_hash(spec: DesignSpec) -> str:
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
        if res.size == 0:
            return cls(0, math.nan, math.nan, math.nan, math.nan, float(band_m))
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
        1-sigma of (dalpha [rad], dbeta [rad], dd [m]) from the joint fit (planes,
        mirrors and intrinsics together): ``sqrt(diag(cov))``.
    sigma_fit : (3,) float
        1-sigma with the wall planes taken as exact (this mirror's columns only).
    before, after : ResidualStats
        Residuals of the used points with no perturbation / the fitted one.
    capture : (n,) int
        Capture index of each reflected point (all finite ones, outliers included).
    residual_before, residual_after : (n,) float
        Signed point-to-plane distance of each point [m].
    points_after : (n, 3) float
        Calibrated points in the sensor frame [m].
    used : (n,) bool
        Points within ``gate_sigma`` of the fitted wall (the fit's inliers).
    condition : float
        Condition number of the column-scaled ``J^T J`` of this mirror at the solution.
    at_bound : tuple of str
        Parameters that ended on a bound (the fit is then not trustworthy).
    nfev : int
        Residual evaluations (robust per-mirror stage).
    cov : (3, 3) float
        This mirror's block of the joint covariance.
    near_wall : (n,) bool
        Points inside the loose gate (near the wall at the starting pose): the candidates
        whose share kept (``used``) is checked against ``min_inlier_share``.
    expected_rms_m, expected_within_band : float
        The noise model's RMS and in-band share for the used points.
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
    cov: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))
    near_wall: np.ndarray | None = None
    expected_rms_m: float = math.nan
    expected_within_band: float = math.nan

    @property
    def used_share(self) -> float:
        """Share of the near-wall points kept as inliers."""
        near = self.used if self.near_wall is None else self.near_wall
        return float(self.used.sum() / max(1, near.sum()))

    def to_dict(self) -> dict[str, Any]:
        p = self.perturbation
        return {"name": self.name, "dalpha_rad": p.dalpha, "dbeta_rad": p.dbeta, "dd_m": p.dd,
                "sigma_dalpha_rad": float(self.sigma[0]), "sigma_dbeta_rad": float(self.sigma[1]),
                "sigma_dd_m": float(self.sigma[2]),
                "sigma_fit": [float(v) for v in self.sigma_fit], "n_points": int(self.used.size),
                "n_used": int(self.used.sum()), "used_share": self.used_share,
                "before": self.before.to_dict(), "after": self.after.to_dict(),
                "expected_rms_m": self.expected_rms_m,
                "expected_within_band": self.expected_within_band,
                "condition": self.condition, "at_bound": list(self.at_bound), "nfev": self.nfev,
                "cov": np.asarray(self.cov).tolist()}


@dataclass(frozen=True, eq=False)
class CaptureFit:
    """One wall capture's plane and its direct points (sensor frame).

    ``inlier_share``: share of the capture's finite direct beams on the plane;
    ``expected_rms_m``: the noise model's RMS distance of those inliers from the plane.
    """

    name: str
    plane: Plane
    direct_points: np.ndarray
    inlier_share: float = math.nan
    expected_rms_m: float = math.nan

    @property
    def distance_m(self) -> float:
        """Distance of the wall plane from the sensor origin [m]."""
        return self.plane.offset_m

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "normal": self.plane.normal.tolist(),
                "offset_m": self.plane.offset_m, "plane_rms_m": self.plane.rms_m,
                "n_direct": int(self.plane.inliers.sum()), "inlier_share": self.inlier_share,
                "expected_rms_m": self.expected_rms_m,
                "rms_over_noise": self.plane.rms_m / self.expected_rms_m}


@dataclass(frozen=True, eq=False)
class CalibrationResult:
    """Everything :func:`calibrate` found.

    ``rounds``: fit rounds run (module docstring, "Beam map"); ``beams_remapped``: beams
    whose mirror (or none) in the last round's map differs from the design's.
    ``parameter_names`` / ``covariance``: the joint fit's mirror (and intrinsic) parameters,
    ``"L1.dalpha_rad"`` ..., and their full covariance (SI units). ``intrinsics``: fitted
    ``range_offset_m`` / ``range_scale`` (empty when not fitted). ``ambiguous_steps``: beams
    whose mirror changes within ``ambiguity_sigma`` of the fit. ``problems``: failed
    quality gates, one line each (empty: the calibration can be trusted).
    """

    design_name: str
    design_hash: str
    model: str
    captures: tuple[CaptureFit, ...]
    mirrors: dict[str, MirrorFit] = field(default_factory=dict)
    rounds: int = 1
    beams_remapped: int = 0
    parameter_names: tuple[str, ...] = ()
    covariance: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    intrinsics: dict[str, float] = field(default_factory=dict)
    ambiguous_steps: tuple[int, ...] = ()
    problems: tuple[str, ...] = ()

    @property
    def perturbations(self) -> dict[str, Perturbation]:
        """Mirror name -> fitted Perturbation (feed to ``design.beam_model``)."""
        return {k: m.perturbation for k, m in self.mirrors.items()}

    @property
    def ok(self) -> bool:
        """True when every quality gate passed."""
        return not self.problems

    def to_dict(self) -> dict[str, Any]:
        return {"design": self.design_name, "design_hash": self.design_hash, "model": self.model,
                "rounds": self.rounds, "beams_remapped": self.beams_remapped,
                "walls": [c.to_dict() for c in self.captures],
                "mirrors": {k: m.to_dict() for k, m in self.mirrors.items()},
                "intrinsics": dict(self.intrinsics),
                "parameter_names": list(self.parameter_names),
                "covariance": np.asarray(self.covariance).tolist(),
                "ambiguous_steps": [int(s) for s in self.ambiguous_steps],
                "problems": list(self.problems), "ok": self.ok}


# ---------------------------------------------------------------------------------------
def _range_sigma(lidar, r: np.ndarray) -> np.ndarray:
    """1-sigma of a measured range [m], mm rounding included."""
    return np.sqrt(lidar.range_sigma_m(np.nan_to_num(r)) ** 2 + _QUANTUM_VAR)


def _true_range(r: np.ndarray, intr: np.ndarray | None) -> np.ndarray:
    """Invert ``r_meas = (1 + scale) r + offset``."""
    if intr is None or not len(intr):
        return r
    return (r - intr[0]) / (1.0 + intr[1])


def fit_planes(design: Design, captures: list[WallCapture], config: CalibrationConfig,
               direct: np.ndarray | None = None, intrinsics: np.ndarray | None = None
               ) -> list[CaptureFit]:
    """Robust (MSAC) plane of each capture's direct beams (independent of the mirrors).

    ``direct`` : (n_steps,) bool over the lidar's valid steps, the beams taken as direct
    (default: the design's beam map; with the mirrors lifted every beam is direct).
    ``intrinsics``: (offset [m], scale) applied to the ranges first (default none).
    """
    lidar = design.lidar
    out = []
    for k, cap in enumerate(captures):
        name = cap.name or f"capture {k}"
        bm = design.beam_model(mirrors_deployed=cap.mirrors_deployed)
        if direct is None or not cap.mirrors_deployed:
            is_direct = bm.mirror_index(cap.steps) == DIRECT
        else:
            is_direct = np.asarray(direct)[cap.steps - lidar.step_min]
        sel = is_direct & np.isfinite(cap.ranges_m)
        r = _true_range(cap.ranges_m[sel], intrinsics)
        pts = bm.points(cap.steps[sel], r, cap.nod_rad[sel])
        sig = _range_sigma(lidar, cap.ranges_m[sel])
        plane = fit_plane_msac(pts, sig, k_sigma=config.gate_sigma, seed=k, name=name)
        inl = plane.inliers
        d = bm.rays(cap.steps[sel][inl], cap.nod_rad[sel][inl])[1]
        expected = float(np.sqrt(np.mean((sig[inl] * np.abs(d @ plane.normal)) ** 2)))
        out.append(CaptureFit(name=name, plane=plane, direct_points=pts[inl],
                              inlier_share=float(inl.mean()) if inl.size else 0.0,
                              expected_rms_m=expected))
    return out


def beam_map(design: Design, perturbations: dict[str, Perturbation] | None) -> np.ndarray:
    """(n_steps,) int over the valid steps: the mirror each beam reaches with the mirrors
    perturbed (``DIRECT`` none; ``BLOCKED`` reflected but blocked on its way out, by
    another mirror or the housing), by the same trace as the runtime assembly's
    (:func:`nodlidar.verify.verify`, first hit on the patches)."""
    v = verify(design, perturbations or None)
    return np.where((v.hit >= 0) & (v.blocker != CLEAR), BLOCKED, v.hit)


class _MirrorProblem:
    """The residual function of one mirror over all captures (vectorised over points)."""

    #: (n,) int: the capture of each point; set by whoever gathers the points
    #: (_mirror_problem), carried over by subset/with_ranges
    kidx: np.ndarray

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
        self.mos = np.full(lidar.n_steps, DIRECT, dtype=int)
        self.mos[self.mirror_steps - lidar.step_min] = 0
        self.pivot = np.asarray(design.spec.nod.pivot_m, dtype=float)
        if model == "paper":
            self._paper_setup()

    def subset(self, mask: np.ndarray) -> _MirrorProblem:
        """The same problem on the points selected by ``mask``."""
        out = _MirrorProblem(self.design, self.sol.name, self.steps[mask], self.ranges[mask],
                             self.nod[mask], self.normals[mask], self.offsets[mask], self.model,
                             self.mirror_steps)
        if hasattr(self, "kidx"):
            out.kidx = self.kidx[mask]
        return out

    def with_ranges(self, ranges: np.ndarray) -> _MirrorProblem:
        """The same problem with other ranges (e.g. corrected by the lidar intrinsics)."""
        out = _MirrorProblem(self.design, self.sol.name, self.steps, ranges, self.nod,
                             self.normals, self.offsets, self.model, self.mirror_steps)
        if hasattr(self, "kidx"):
            out.kidx = self.kidx
        return out

    def beam_model(self, x: np.ndarray) -> BeamModel:
        patch = self.sol.patch.perturbed(Perturbation.from_array(x))
        return BeamModel.build(self.design.lidar, [patch], self.mos, self.pivot)

    def points(self, x: np.ndarray, ranges: np.ndarray | None = None) -> np.ndarray:
        """Sensor-frame points (n, 3) of this mirror's beams under perturbation ``x``
        (``ranges``: the true ranges, default the measured ones)."""
        if self.model == "paper":
            return self._paper_points(x)
        return self.beam_model(x).points(self.steps, self.ranges if ranges is None else ranges,
                                         self.nod)

    def directions(self, x: np.ndarray) -> np.ndarray:
        """Outgoing ray directions (n, 3) under perturbation ``x`` (nodded)."""
        if self.model == "paper":
            return np.broadcast_to(np.asarray(self.normals), (len(self.steps), 3))
        return self.beam_model(x).rays(self.steps, self.nod)[1]

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
        q = np.stack([p[:, 1], -self.sgn * p[:, 0], p[:, 2]], -1)
        return pitch_about_pivot(q, self.nod, self.pivot)


def _scaled_condition(J: np.ndarray) -> float:
    scale = np.linalg.norm(J, axis=0)
    if np.any(scale == 0):
        return math.inf
    s = np.linalg.svd(J / scale, compute_uv=False)
    return float((s[0] / s[-1]) ** 2) if s[-1] > 0 else math.inf


def _fd_jacobian(fun, x: np.ndarray, h: np.ndarray) -> np.ndarray:
    """Central-difference Jacobian of ``fun`` at ``x`` (one column per parameter)."""
    cols = []
    for j in range(len(x)):
        e = np.zeros_like(x)
        e[j] = h[j]
        cols.append((fun(x + e) - fun(x - e)) / (2 * h[j]))
    return np.stack(cols, -1)


_H_MIRROR = np.array([1e-6, 1e-6, 1e-7])


def _erf(x: np.ndarray) -> np.ndarray:
    """scipy.special.erf, imported when first used (see _robust_mirror)."""
    from scipy.special import erf

    return erf(x)


def _robust_mirror(prob: _MirrorProblem, sig_r: np.ndarray, config: CalibrationConfig,
                   x0: np.ndarray, warm: bool = False
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Stage 2 (module docstring): the mirror's inliers and pose with the planes fixed.

    ``warm``: ``x0`` is already a fit (a later round): skip the robust (soft-L1) pass.
    Returns ``(x, used (n,) bool, near_wall (n,) bool, nfev)``.
    """
    lo, hi = config.bounds
    x = np.clip(x0, lo * 0.999, hi * 0.999)
    # noise of each residual: range noise along the plane normal (the ray's obliquity)
    cosi = np.abs(np.einsum("ij,ij->i", prob.directions(x), prob.normals))
    sig = sig_r * np.maximum(cosi, 0.1)
    e0 = prob.residuals(x)
    J0 = _fd_jacobian(prob.residuals, x, _H_MIRROR)
    # as far as the bounds let the fit move a point, plus the noise: beyond it the point
    # hit something else (a box, the wall behind a doorway)
    near = np.abs(e0) <= config.gate_sigma * sig + np.abs(J0) @ hi
    name = prob.sol.name
    if near.sum() < config.min_points:
        raise CalibrationError(f"mirror {name}: only {int(near.sum())} of its {near.size} "
                               "reflected points come near the wall planes; need "
                               f"{int(config.min_points)} (is the wall in front of the mirror's "
                               "window, and nothing in between?)")
    # lazy: importing scipy.optimize costs ~0.5 s, which `nodlidar design` (it validates
    # the [calibration] table through this module) must not pay (issue 16)
    from scipy.optimize import least_squares

    nfev = 0
    if not warm:
        sub = prob.subset(near)
        sol = least_squares(lambda v: sub.residuals(v) / sig[near], x, bounds=(lo, hi),
                            method="trf", x_scale="jac", loss="soft_l1", f_scale=2.0,
                            max_nfev=200)
        x, nfev = sol.x, sol.nfev
    used = near.copy()
    # the joint fit re-gates and refits; this only starts it well (a later round: the
    # previous fit's pose, gated once)
    for _ in range(1 if warm else 2):
        new = near & (np.abs(prob.residuals(x)) <= config.gate_sigma * sig)
        if new.sum() < config.min_points:
            raise CalibrationError(f"mirror {name}: only {int(new.sum())} reflected points "
                                   f"agree with one mirror pose; need {int(config.min_points)}")
        if np.array_equal(new, used) or warm:
            used = new
            break
        used = new
        sub, w = prob.subset(used), 1.0 / sig[used]
        sol = least_squares(lambda v, sub=sub, w=w: sub.residuals(v) * w, x, bounds=(lo, hi),
                            method="trf", x_scale="jac", xtol=1e-12, ftol=1e-12, gtol=1e-12,
                            max_nfev=200)
        x, nfev = sol.x, nfev + sol.nfev
    return x, used, near, nfev


class _Joint:
    """Stage 3: planes + mirrors (+ intrinsics) fitted together over the inliers.

    Residuals are in **range**: each beam's measured range minus the range at which its ray
    (through the candidate mirror) meets its capture's candidate plane, weighted by the
    lidar's range noise. The noise is along the ray, so this is the model the data obey; a
    point-to-plane distance instead carries noise whose size depends on the candidate plane
    (its obliquity to the ray), and minimising it biases the fit (measured: the range
    offset by +5 mm, 5 sigma, with noise only). ``model="paper"`` (no rays) falls back to
    the point-to-plane distance.

    Parameter vector: per capture ``(ta, tb, dc)`` (the plane's normal tilted by ``ta``,
    ``tb`` along its tangents, moved ``dc`` along it, about its inlier centroid), per mirror
    ``(dalpha, dbeta, dd)``, then the fitted ones of ``(range_offset_m, range_scale)``
    (``active``: their indices; the others stay at ``intr_base``). ``known``: (capture,
    distance [m], sigma [m]) of walls whose distance from the sensor origin was measured:
    one prior row each.
    """

    def __init__(self, design, planes: list[Plane], direct: list[tuple], probs: dict,
                 active: tuple[int, ...] = (), intr_base=None, known=()):
        self.design, self.lidar = design, design.lidar
        self.planes = planes
        self.K, self.names = len(planes), list(probs)
        self.active = tuple(active)
        self.intr_base = np.zeros(2) if intr_base is None else np.asarray(intr_base, float)
        self.known = list(known)
        self.M, self.n_intr = len(probs), len(self.active)
        self.direct = direct      # per capture: (steps, ranges, nod) of the direct beams
        self.probs = probs        # per mirror: _MirrorProblem (with .kidx) of its beams
        self.paper = any(p.model == "paper" for p in probs.values())
        dm = design.beam_model(mirrors_deployed=False)
        self.drays = [dm.rays(s, n) for s, _, n in direct]
        self._rays: dict[tuple, tuple] = {}
        self.nd = sum(len(s) for s, _, _ in direct)
        self.cap_rows = np.concatenate([np.full(len(s), k) for k, (s, _, _) in enumerate(direct)]
                                       + [probs[n].kidx for n in self.names]).astype(int)
        self.mir_rows = np.concatenate([np.full(len(s), DIRECT) for s, _, _ in direct]
                                       + [np.full(len(probs[n].kidx), m)
                                          for m, n in enumerate(self.names)]).astype(int)
        self.r_meas = np.concatenate([r for _, r, _ in direct]
                                     + [probs[n].ranges for n in self.names])
        self.n_points = len(self.cap_rows)
        self.w = np.ones(self.n_points + len(self.known))

    @property
    def n_params(self) -> int:
        return 3 * self.K + 3 * self.M + self.n_intr

    def plane_of(self, theta: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray, float]:
        pl = self.planes[k]
        ta, tb, dc = theta[3 * k:3 * k + 3]
        n = pl.normal + ta * pl.tangents[0] + tb * pl.tangents[1]
        return n / np.linalg.norm(n), pl.point, dc

    def mirror_x(self, theta: np.ndarray, m: int) -> np.ndarray:
        i = 3 * self.K + 3 * m
        return theta[i:i + 3]

    def intr(self, theta: np.ndarray) -> np.ndarray | None:
        """(offset [m], scale) of ``theta``; None when no intrinsics are modelled."""
        if not self.n_intr and not self.intr_base.any():
            return None
        out = self.intr_base.copy()
        out[list(self.active)] = theta[3 * self.K + 3 * self.M:]
        return out

    def _mirror_rays(self, m: int, x: np.ndarray):
        prob = self.probs[self.names[m]]
        key = (m, *x.tolist())
        rays = self._rays.get(key)
        if rays is None:
            if len(self._rays) > 64:
                self._rays.clear()
            if prob.model == "paper":
                rays = (prob.points(x), None, None)
            else:
                rays = prob.beam_model(x).rays(prob.steps, prob.nod)
            self._rays[key] = rays
        return rays

    def rays(self, theta: np.ndarray, only_mirrors: np.ndarray | None = None):
        """Ray starts, directions, path offsets (rows over all points); the reflected
        rows of ``only_mirrors`` (default all) from ``theta``'s mirror poses."""
        parts = [self._mirror_rays(m, self.mirror_x(theta, m)) for m in range(self.M)]
        if self.paper:
            return None, None, None, np.concatenate([p[0] for p in parts])
        S = np.concatenate([r[0] for r in self.drays] + [p[0] for p in parts])
        D = np.concatenate([r[1] for r in self.drays] + [p[1] for p in parts])
        O = np.concatenate([r[2] for r in self.drays] + [p[2] for p in parts])
        return S, D, O, None

    def _planes(self, theta: np.ndarray):
        """Per-row plane normal (n, 3), centroid (n, 3) and offset (n,) of ``theta``."""
        pl = [self.plane_of(theta, k) for k in range(self.K)]
        rows = self.cap_rows
        N = np.stack([p[0] for p in pl])[rows]
        C = np.stack([p[1] for p in pl])[rows]
        return N, C, np.array([p[2] for p in pl])[rows]

    def residuals(self, theta: np.ndarray, rays) -> np.ndarray:
        """Unweighted residuals of all rows: measured range - predicted range [m] (paper
        model: point-to-plane distance), then the known-distance rows [m]."""
        S, D, O, P = rays
        intr = self.intr(theta)
        if P is None:
            # per row, by capture: (S . n_k), (D . n_k) for all K normals at once, then pick
            pl = [self.plane_of(theta, k) for k in range(self.K)]
            Nk = np.stack([q[0] for q in pl])
            ck = np.array([q[0] @ q[1] + q[2] for q in pl])  # n.c + dc: the plane offset
            idx = np.arange(self.n_points)
            sn = (S @ Nk.T)[idx, self.cap_rows]
            dn = (D @ Nk.T)[idx, self.cap_rows]
            dn = np.where(np.abs(dn) < 1e-3, 1e-3, dn)
            r_hat = O + (ck[self.cap_rows] - sn) / dn
            if intr is not None:
                r_hat = (1.0 + intr[1]) * r_hat + intr[0]
            e = self.r_meas - r_hat
            if not self.known:
                return e
            return np.concatenate([e, [ck[k] - dist for k, dist, _ in self.known]])
        N, C, dc = self._planes(theta)
        if P is not None:  # paper model: the direct rows as points too
            r = _true_range(self.r_meas[:self.nd], intr)
            pd = S if S is not None else np.concatenate(
                [st + (r_k - off)[:, None] * d for (st, d, off), r_k in
                 zip(self.drays, np.split(r, np.cumsum([len(x[0]) for x in self.drays])[:-1]))])
            e = -(np.einsum("ij,ij->i", np.concatenate([pd, P]) - C, N) - dc)
        else:
            nd = np.einsum("ij,ij->i", D, N)
            nd = np.where(np.abs(nd) < 1e-3, 1e-3, nd)
            t = (dc - np.einsum("ij,ij->i", S - C, N)) / nd
            r_hat = O + t
            if intr is not None:
                r_hat = (1.0 + intr[1]) * r_hat + intr[0]
            e = self.r_meas - r_hat
        if not self.known:
            return e
        prior = [float(self.plane_of(theta, k)[0] @ self.plane_of(theta, k)[1]
                       + self.plane_of(theta, k)[2] - dist) for k, dist, _ in self.known]
        return np.concatenate([e, prior])

    def normal_residuals(self, theta: np.ndarray) -> np.ndarray:
        """Point-to-plane distances [m] of all point rows (for RMS reports)."""
        S, D, O, P = self.rays(theta)
        N, C, dc = self._planes(theta)
        r = _true_range(self.r_meas, self.intr(theta))
        if P is None:
            pts = S + (r - O)[:, None] * D
        else:
            pts = np.concatenate([st + (r_k - off)[:, None] * d for (st, d, off), r_k in
                                  zip(self.drays, np.split(r[:self.nd], np.cumsum(
                                      [len(x[0]) for x in self.drays])[:-1]))] + [P])
        return np.einsum("ij,ij->i", pts - C, N) - dc

    def fun(self, theta: np.ndarray) -> np.ndarray:
        return self.residuals(theta, self.rays(theta)) * self.w

    def set_weights(self, theta: np.ndarray) -> None:
        """1/sigma of every row: the range noise (0 for rays within ~6 deg of grazing)."""
        sig = _range_sigma(self.lidar, self.r_meas)
        w = 1.0 / sig
        S, D, _, P = self.rays(theta)
        if P is None:
            N = self._planes(theta)[0]
            w = np.where(np.abs(np.einsum("ij,ij->i", D, N)) >= 0.1, w, 0.0)
        else:
            w = w  # paper model: distance residuals, same noise scale
        self.w = np.concatenate([w, [1.0 / sd for _, _, sd in self.known]])

    def _plane_columns(self, theta: np.ndarray, rays, J: np.ndarray) -> None:
        """Analytic plane columns (unweighted) of the range residuals, into ``J``:
        ``e = r - (1 + s) (O + (n.c + dc - S.n) / (D.n)) - b`` with ``n`` tilted by
        ``(ta, tb)``."""
        S, D, _, _ = rays
        intr = self.intr(theta)
        k1 = 1.0 + (intr[1] if intr is not None else 0.0)
        for k in range(self.K):
            sel = np.flatnonzero(self.cap_rows == k)
            pl = self.planes[k]
            ta, tb, dc = theta[3 * k:3 * k + 3]
            u = pl.normal + ta * pl.tangents[0] + tb * pl.tangents[1]
            nu = np.linalg.norm(u)
            n = u / nu
            Sk, Dk = S[sel], D[sel]
            dn = Dk @ n
            dn = np.where(np.abs(dn) < 1e-3, 1e-3, dn)
            num = n @ pl.point + dc - Sk @ n
            J[sel, 3 * k + 2] = -k1 / dn
            for j in range(2):
                dnj = (pl.tangents[j] - n * (n @ pl.tangents[j])) / nu   # d n / d t_j
                dt = ((dnj @ pl.point - Sk @ dnj) * dn - num * (Dk @ dnj)) / dn**2
                J[sel, 3 * k + j] = -k1 * dt
            for i, (kk, _, _) in enumerate(self.known):
                if kk == k:  # the prior row n . c + dc - D
                    row = self.n_points + i
                    J[row, 3 * k + 2] = 1.0
                    for j in range(2):
                        J[row, 3 * k + j] = pl.point @ ((pl.tangents[j] - n * (n @ pl.tangents[j]))
                                                        / nu)

    def jac(self, theta: np.ndarray, rays=None) -> np.ndarray:
        """Weighted Jacobian by central differences: plane and intrinsic parameters reuse
        the rays (only the planes / the range model move); parameter j of every mirror is
        stepped at once (their rows do not overlap) and only its rays recomputed."""
        rays = self.rays(theta) if rays is None else rays
        J = np.zeros((len(self.w), self.n_params))
        cols = list(range(3 * self.K + 3 * self.M, self.n_params))
        if rays[3] is None:
            self._plane_columns(theta, rays, J)
        else:
            cols = list(range(3 * self.K)) + cols
        for col in cols:
            h = 1e-7 if col < 3 * self.K else 1e-6
            e = np.zeros(self.n_params)
            e[col] = h
            J[:, col] = (self.residuals(theta + e, rays) - self.residuals(theta - e, rays)) / (2 * h)
        base = self.residuals(theta, rays)
        for j in range(3):
            # forward differences: each step rebuilds every mirror's patch (the costly part);
            # with h = 1e-6 rad / 1e-7 m the truncation error is ~1e-6 relative
            h = _H_MIRROR[j]
            th = theta.copy()
            th[3 * self.K + j:3 * self.K + 3 * self.M:3] += h
            d = (self.residuals(th, self.rays(th)) - base) / h
            for m in range(self.M):
                sel = self.mir_rows == m
                J[:self.n_points][sel, 3 * self.K + 3 * m + j] = d[:self.n_points][sel]
        return J * self.w[:, None]


def _gauss_newton(joint: _Joint, theta: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                  max_iter: int = 10) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Levenberg-Marquardt on the joint problem (it starts next to the optimum: the robust
    stage's poses), bounds by clipping. Returns (theta, weighted residuals, Jacobian)."""
    rays = joint.rays(theta)
    f = joint.residuals(theta, rays) * joint.w
    cost = float(f @ f)
    lam = 0.0
    J = joint.jac(theta, rays)
    for _ in range(max_iter):
        A, g = J.T @ J, J.T @ f
        D = np.diag(np.diag(A)) + 1e-30
        for _ in range(8):
            step = np.linalg.solve(A + lam * D, -g)
            new = np.clip(theta + step, lo, hi)
            rays_n = joint.rays(new)
            f_n = joint.residuals(new, rays_n) * joint.w
            c_n = float(f_n @ f_n)
            if c_n <= cost:
                lam = lam / 10 if lam > 1e-6 else 0.0
                break
            lam = max(lam * 10, 1e-4)
        else:
            break
        small = np.all(np.abs(new - theta) <= 1e-3 * np.sqrt(np.diag(np.linalg.pinv(A))) + 1e-12)
        theta, f, cost, rays = new, f_n, c_n, rays_n
        if small:
            # converged: a step of 1e-3 sigma leaves the Jacobian as it was (to ~1e-3)
            break
        J = joint.jac(theta, rays)
    return theta, f, J


def _fit_joint(design, dcands: list[tuple], fits: list[CaptureFit], robust: dict,
               config: CalibrationConfig, active: tuple[int, ...], intr0: np.ndarray | None,
               known: list):
    """Stage 3 (module docstring). ``robust``: name -> (prob over all candidates, x, used,
    near, nfev, sig_r). Returns (theta, cov, joint, J, direct_used per capture, used per
    mirror)."""
    planes = [cf.plane for cf in fits]
    direct_used = [cf.plane.inliers.copy() for cf in fits]
    used = {name: rb[2].copy() for name, rb in robust.items()}
    lo, hi = config.bounds
    theta = np.concatenate([np.zeros(3 * len(planes))]
                           + [robust[n][1] for n in robust]
                           + [(intr0 if intr0 is not None else np.zeros(2))[list(active)]])
    b_lo = np.concatenate([np.full(3 * len(planes), -np.inf)] + [lo] * len(robust)
                          + [np.array([-config.range_offset_bound_m,
                                       -config.range_scale_bound])[list(active)]])
    b_hi = -b_lo
    theta = np.clip(theta, b_lo, b_hi)
    full = _Joint(design, planes, dcands, {n: rb[0] for n, rb in robust.items()},
                  active=active, intr_base=intr0, known=known)
    for _ in range(4):
        full.set_weights(theta)
        rows = np.concatenate(direct_used + [used[n] for n in robust]
                              + [np.ones(len(known), bool)])
        direct = [(s[u], r[u], n[u]) for (s, r, n), u in zip(dcands, direct_used)]
        joint = _Joint(design, planes, direct, {n: rb[0].subset(used[n]) for n, rb in
                                                robust.items()},
                       active=active, intr_base=intr0, known=known)
        joint.w = full.w[rows]
        theta, f, J = _gauss_newton(joint, theta, b_lo, b_hi)
        # re-gate every candidate against the joint solution
        full.set_weights(theta)
        ok = np.abs(full.fun(theta)) <= config.gate_sigma
        new_direct, new_used, i = [], {}, 0
        for s, _, _ in dcands:
            new_direct.append(ok[i:i + len(s)])
            i += len(s)
        for name, rb in robust.items():
            n = len(rb[0].steps)
            new_used[name] = ok[i:i + n] & rb[3]
            i += n
        same = (all(np.array_equal(a, b) for a, b in zip(new_direct, direct_used))
                and all(np.array_equal(new_used[n], used[n]) for n in used))
        direct_used, used = new_direct, new_used
        if same:
            break
    dof = max(1, J.shape[0] - J.shape[1])
    s2 = float(np.sum(f**2) / dof)
    cov = s2 * np.linalg.pinv(J.T @ J)
    return theta, cov, joint, J, direct_used, used


def ambiguous_steps(design: Design, perturbations: dict[str, Perturbation], names: list[str],
                    cov: np.ndarray, k_sigma: float = 3.0) -> np.ndarray:
    """Steps whose mirror (or none/blocked) changes within ``k_sigma`` of the fit.

    ``cov``: (3M, 3M) covariance of the mirrors ``names`` (order dalpha, dbeta, dd each).
    The beam map is re-traced at the fit moved ``+-k_sigma`` along each principal axis of
    ``cov`` (the extremes of the ``k_sigma`` ellipsoid along its axes); any step whose map
    differs from the fit's is ambiguous (edges, the L1/L2 joint, double bounces). Returns
    sorted steps.
    """
    base = beam_map(design, perturbations)
    x = np.concatenate([perturbations[n].as_array() for n in names])
    cov = 0.5 * (cov + cov.T)
    lam, V = np.linalg.eigh(cov)
    dirs = [np.sqrt(max(v, 0.0)) * V[:, i] for i, v in enumerate(lam)]
    changed = np.zeros(base.shape, bool)
    for d in dirs:
        for s in (1.0, -1.0):
            y = x + s * k_sigma * d
            p = dict(perturbations)
            p.update({n: Perturbation.from_array(y[3 * i:3 * i + 3]) for i, n in enumerate(names)})
            changed |= beam_map(design, p) != base
    return np.flatnonzero(changed) + design.lidar.step_min


def calibrate(design: Design, captures: list[WallCapture], *, model: str = "exact",
              config: CalibrationConfig | None = None, mirrors: list[str] | None = None,
              x0: dict[str, Perturbation] | None = None,
              intrinsics: bool | tuple[str, ...] = False,
              intrinsics0: tuple[float, float] = (0.0, 0.0),
              known_distances_m: list[float | None] | None = None,
              known_distance_sigma_m: float = 0.003) -> CalibrationResult:
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
    intrinsics : bool or tuple of str
        Also fit the lidar's range offset [m] and/or scale (``r_meas = (1 + scale) r +
        offset``): True for both, or a subset of :data:`INTRINSICS`. ``intrinsics0``: the
        starting (and, for one not fitted, the fixed) values. The scale needs at least one
        ``known_distances_m``: a uniformly scaled room looks the same to the walls.
    known_distances_m : list of (float or None), optional
        Per capture, the measured distance of the wall from the sensor origin [m] (None:
        not measured), each with 1-sigma ``known_distance_sigma_m`` [m].

    Returns
    -------
    CalibrationResult
        Check ``.problems`` (failed quality gates) before using it.

    Raises
    ------
    CalibrationError
        Degenerate data, with what is wrong.
    """
    require(model in MODELS, "model", model, " or ".join(MODELS))
    if intrinsics is True:
        intrinsics = INTRINSICS
    intrinsics = tuple(intrinsics or ())
    for it in intrinsics:
        require(it in INTRINSICS, "intrinsics", it, " and/or ".join(INTRINSICS))
    active = tuple(INTRINSICS.index(it) for it in INTRINSICS if it in intrinsics)
    require(not (intrinsics and model == "paper"), "intrinsics", intrinsics,
            "none with model 'paper' (eqs 4-8 take no range model)")
    require(known_distance_sigma_m > 0, "known_distance_sigma_m", known_distance_sigma_m, "> 0 m")
    known_d = list(known_distances_m or [])
    require(len(known_d) in (0, len(captures)), "known_distances_m", known_distances_m,
            f"one per capture ({len(captures)}; None where not measured)")
    known = [(k, float(v), float(known_distance_sigma_m)) for k, v in enumerate(known_d)
             if v is not None]
    if "range_scale" in intrinsics and not known:
        raise CalibrationError("the lidar's range scale cannot be fitted from walls alone (a "
                               "uniformly scaled room looks the same); measure at least one "
                               "wall's distance from the sensor and give it, or fit the range "
                               "offset only")
    config = config or calibration_config(design.spec)
    captures = list(captures)
    if not captures:
        raise CalibrationError("no wall captures given; calibration needs at least "
                               f"{config.min_walls} captures at different orientations")
    lidar = design.lidar
    names = list(mirrors or [m.name for m in design.mirrors])
    index = {m.name: i for i, m in enumerate(design.mirrors)}
    design_map = np.asarray(design.mirror_of_step)
    hit = design_map
    start = {name: (x0 or {}).get(name, Perturbation()) for name in names}
    intr = np.asarray(intrinsics0, dtype=float) if (intrinsics or any(intrinsics0)) else None
    out: dict[str, MirrorFit] = {}
    for rnd in range(int(config.rounds)):
        # beams direct in the design's map and in the current one give the planes
        direct_ok = (design_map == DIRECT) & (hit == DIRECT)
        fits = fit_planes(design, captures, config, direct=direct_ok, intrinsics=intr)
        check_wall_orientations([c.plane for c in fits], [c.name for c in fits],
                                min_walls=int(config.min_walls),
                                min_angle_rad=np.radians(config.min_wall_angle_deg))
        if rnd == 0:
            _check_distances(design, fits, config)
        # direct candidates: the beams the plane fit was given (its inliers and outliers)
        dcands = []
        for cap in captures:
            bm = design.beam_model(mirrors_deployed=cap.mirrors_deployed)
            isd = (bm.mirror_index(cap.steps) == DIRECT if not cap.mirrors_deployed
                   else direct_ok[cap.steps - lidar.step_min])
            sel = isd & np.isfinite(cap.ranges_m)
            dcands.append((cap.steps[sel], cap.ranges_m[sel], cap.nod_rad[sel]))
        robust = {}
        for name in names:
            prob, sig_r = _mirror_candidates(design, name, captures, fits, config, model,
                                             np.flatnonzero(hit == index[name]) + lidar.step_min)
            prob_t = prob if intr is None else prob.with_ranges(_true_range(prob.ranges, intr))
            x, used, near, nfev = _robust_mirror(prob_t, sig_r, config, start[name].as_array(),
                                                 warm=rnd > 0)
            robust[name] = (prob, x, used, near, nfev, sig_r)
        fitted = {name: Perturbation.from_array(robust[name][1]) for name in names}
        last = rnd + 1 == int(config.rounds)
        if not last:
            # mirrors not fitted here keep their starting pose
            new_hit = beam_map(design, {**{m.name: (x0 or {}).get(m.name, Perturbation())
                                           for m in design.mirrors}, **fitted})
            last = bool(np.array_equal(new_hit, hit))
        # the joint fit once the beam map is settled (every round with intrinsics: they
        # change the direct points the planes come from)
        if last or active:
            theta, cov, joint, J, direct_used, used = _fit_joint(
                design, dcands, fits, robust, config, active, intr, known)
            fitted = {name: Perturbation.from_array(joint.mirror_x(theta, m))
                      for m, name in enumerate(names)}
            if active:
                intr = joint.intr(theta).copy()
        if last:
            break
        hit = new_hit
        start = fitted
    # the planes as the joint fit moved them
    nres = joint.normal_residuals(theta)
    new_fits = []
    for k, cf in enumerate(fits):
        n, c, dc = joint.plane_of(theta, k)
        if c @ n + dc < 0:
            n = -n
            dc = -dc
        t0 = cf.plane.tangents[0] - (cf.plane.tangents[0] @ n) * n
        t0 /= np.linalg.norm(t0)
        t = np.stack([t0, np.cross(n, t0)])
        rows3 = slice(3 * k, 3 * k + 3)
        ek = nres[:joint.nd][joint.cap_rows[:joint.nd] == k]
        pl = Plane(point=c + dc * n, normal=n,
                   rms_m=float(np.sqrt(np.mean(ek**2))) if ek.size else cf.plane.rms_m,
            inliers=np.asarray(direct_used[k], bool), tangents=t, cov=cov[rows3, rows3])
        new_fits.append(CaptureFit(name=cf.name, plane=pl, direct_points=cf.direct_points,
                                   inlier_share=float(direct_used[k].mean()),
                                   expected_rms_m=cf.expected_rms_m))
    fits = new_fits
    planes = [cf.plane for cf in fits]
    M0 = 3 * len(planes)
    wres = joint.fun(theta)
    for m, name in enumerate(names):
        prob, _, _, near, nfev, sig_r = robust[name]
        x = joint.mirror_x(theta, m)
        u = used[name]
        ranges = _true_range(prob.ranges, intr)
        pts = prob.points(x, ranges if intr is not None else None)
        pts0 = prob.points(np.zeros(3), ranges if intr is not None else None)
        nk = np.stack([p.normal for p in planes])[prob.kidx]
        ok = np.array([p.offset_m for p in planes])[prob.kidx]
        res = np.einsum("ij,ij->i", pts, nk) - ok
        res0 = np.einsum("ij,ij->i", pts0, nk) - ok
        cols = slice(M0 + 3 * m, M0 + 3 * m + 3)
        Jm = J[:, cols]
        cond = _scaled_condition(Jm[np.any(Jm != 0, axis=1)])
        if not cond <= config.max_condition:
            raise CalibrationError(
                f"mirror {name}: the walls do not determine (dalpha, dbeta, dd) - the "
                f"least-squares problem is ill-conditioned (cond(J^T J) = {cond:.3g} > "
                f"{config.max_condition:.3g}); capture the wall at more distinct orientations "
                f"and with the head nodding")
        dof = max(1, int(u.sum()) - 3)
        rows = np.concatenate([joint.mir_rows == m, np.zeros(len(joint.known), bool)])
        s2 = float(np.sum(wres[rows] ** 2) / dof)
        cov_fit = s2 * np.linalg.pinv(Jm[rows].T @ Jm[rows])
        cosi = np.abs(np.einsum("ij,ij->i", prob.directions(x), nk))
        sig_n = sig_r * np.maximum(cosi, 0.1)
        lo, hi = config.bounds
        at_bound = tuple(p for p, v, a, b in zip(PARAMS, x, lo, hi)
                         if abs(v - a) < 1e-6 * (b - a) or abs(v - b) < 1e-6 * (b - a))
        out[name] = MirrorFit(
            name=name, perturbation=Perturbation.from_array(x),
            sigma=np.sqrt(np.diag(cov[cols, cols])), sigma_fit=np.sqrt(np.diag(cov_fit)),
            before=ResidualStats.of(res0[u], config.band_m),
            after=ResidualStats.of(res[u], config.band_m), capture=prob.kidx,
            residual_before=res0, residual_after=res, points_after=pts, used=u,
            condition=cond, at_bound=at_bound, nfev=nfev, cov=cov[cols, cols].copy(),
            near_wall=near,
            expected_rms_m=float(np.sqrt(np.mean(sig_n[u] ** 2))),
            expected_within_band=float(np.mean(_erf(config.band_m / (np.sqrt(2) * sig_n[u])))))
    pnames = tuple(f"{n}.{p}" for n in names for p in ("dalpha_rad", "dbeta_rad", "dd_m"))
    sel = list(range(M0, M0 + 3 * len(names)))
    intr_d: dict[str, float] = {}
    if active:
        pnames += tuple(INTRINSICS[i] for i in active)
        sel += [M0 + 3 * len(names) + j for j in range(len(active))]
        it = joint.intr(theta)
        sd = np.sqrt(np.diag(cov)[-len(active):])
        for j, i in enumerate(active):
            intr_d[INTRINSICS[i]] = float(it[i])
            intr_d["sigma_" + INTRINSICS[i]] = float(sd[j])
        for i in set(range(2)) - set(active):
            intr_d[INTRINSICS[i]] = float(it[i])  # held at its given value
    elif intr is not None:
        intr_d = {INTRINSICS[i]: float(intr[i]) for i in range(2)}
    cov_p = cov[np.ix_(sel, sel)]
    fitted = {n: out[n].perturbation for n in names}
    allp = {**{m.name: (x0 or {}).get(m.name, Perturbation()) for m in design.mirrors}, **fitted}
    amb = ambiguous_steps(design, allp, names, cov[M0:M0 + 3 * len(names), M0:M0 + 3 * len(names)],
                          config.ambiguity_sigma)
    result = CalibrationResult(design_name=design.spec.name, design_hash=design_hash(design.spec),
                               model=model, captures=tuple(fits), mirrors=out, rounds=rnd + 1,
                               beams_remapped=int(np.count_nonzero(hit != design_map)),
                               parameter_names=pnames, covariance=cov_p, intrinsics=intr_d,
                               ambiguous_steps=tuple(int(s) for s in amb))
    object.__setattr__(result, "problems", tuple(quality_gates(result, config)))
    return result


def _check_distances(design, fits: list[CaptureFit], config: CalibrationConfig) -> None:
    """Refuse walls nearer than ``min_wall_distance_m`` or inside the mirrors' reach."""
    reach = max(float(np.linalg.norm(p.corners(), axis=1).max()) for p in design.patches())
    limit = max(config.min_wall_distance_m, reach + 0.1)
    near = [cf for cf in fits if cf.distance_m < limit]
    if near:
        raise CalibrationError("\n".join(
            f"{cf.name}: the wall is {cf.distance_m:.2f} m from the sensor, closer than "
            f"{limit:.2f} m (the mirrors reach {reach:.2f} m; nearer walls leave the reflected "
            "beams too short a lever arm): move the sensor back" for cf in near))


def _mirror_candidates(design, name: str, captures: list[WallCapture], fits: list[CaptureFit],
                       config: CalibrationConfig, model: str, mirror_steps: np.ndarray):
    """All finite beams of ``mirror_steps`` over the deployed captures, as one problem."""
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
    sig_r = _range_sigma(design.lidar, ranges)
    prob = _MirrorProblem(design, name, steps, ranges, nod, normals, offsets, model, mirror_steps)
    prob.kidx = kidx
    return prob, sig_r


def quality_gates(result: CalibrationResult, config: CalibrationConfig) -> list[str]:
    """The checks that stand between a fit and a calibration file: one line per problem,
    naming the capture or mirror and what to do. Empty: every gate passed."""
    out = []
    for cf in result.captures:
        if cf.inlier_share < config.min_inlier_share:
            out.append(f"{cf.name}: only {cf.inlier_share:.0%} of the direct beams lie on one "
                       f"plane (need {config.min_inlier_share:.0%}): clutter, a doorway or a "
                       "second wall fills the view - clear the wall or turn the sensor to a "
                       "clear stretch of it")
        ratio = cf.plane.rms_m / cf.expected_rms_m
        if ratio > config.max_rms_ratio:
            out.append(f"{cf.name}: the wall is not flat within the lidar's noise (plane RMS "
                       f"{cf.plane.rms_m * 1e3:.1f} mm = {ratio:.1f}x the noise, limit "
                       f"{config.max_rms_ratio:g}x): use a flat wall, or move to a flat stretch")
    for name, m in result.mirrors.items():
        for par in m.at_bound:
            i = PARAMS.index(par)
            u, k = UNITS[par]
            out.append(f"mirror {name}: {par} ended on its bound "
                       f"({m.perturbation.as_array()[i] * k:+.1f} "
                       f"{u}): the fit is not trustworthy - check the mirror is seated, and the "
                       f"walls are clear; widen calibration.{par}_bound_* only if it really is "
                       "mounted that far off")
        if m.used_share < config.min_inlier_share:
            out.append(f"mirror {name}: only {m.used_share:.0%} of its reflected points near the "
                       f"walls fit them (need {config.min_inlier_share:.0%}): something stands "
                       "in its view of the wall (furniture, a doorway) - clear the wall or turn "
                       "the sensor")
        n = m.after.n
        p_band = m.expected_within_band
        # 5 % slack: the used points are gated at gate_sigma, so a sound fit is at or above
        # the prediction; a wrong one (issue 12: L2 off by 32 mrad) had 7-39 % in band
        if n and m.after.within_band < p_band - 4 * math.sqrt(p_band * (1 - p_band) / n) - 0.05:
            out.append(f"mirror {name}: {m.after.within_band:.1%} of its points lie within "
                       f"+-{m.after.band_m * 100:.2f} cm of the wall, the noise model predicts "
                       f"{p_band:.1%}: the wall or the fit is off - clear the wall, check it is flat")
        ratio = m.after.rms_m / m.expected_rms_m
        if ratio > config.max_rms_ratio:
            out.append(f"mirror {name}: residual RMS {m.after.rms_m * 1e3:.1f} mm is {ratio:.1f}x "
                       f"the lidar's noise (limit {config.max_rms_ratio:g}x): the wall is not "
                       "flat or something in front of it was taken for it - use a flat, clear wall")
        for i, p in enumerate(PARAMS):
            if m.sigma[i] > config.max_sigma[i]:
                u, k = UNITS[p]
                out.append(f"mirror {name}: {p} is poorly determined (sigma {m.sigma[i] * k:.2f} "
                           f"{u} > {config.max_sigma[i] * k:.2f} {u}): turn the sensor further "
                           "between captures (wider wall angles) and keep the wall 0.7-1.5 m away")
    return out
