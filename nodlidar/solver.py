"""The mirror design solver (paper Section III) and the solved :class:`Design`.

The field of view of ``I`` valid steps is split into ``k`` windows; the middle one is
seen directly, the ``k-1`` side windows are folded by flat mirrors into the middle one so
that on the arc of radius D the reflected beams fall between the direct ones at offsets of
``q * res / k`` (``res`` = the lidar's angular step; ``pi/1536`` for the URG-04LX, k = 3).

Conventions chosen where the paper is silent (docs/paper-reproduction.md):

* Window sizes: each side window gets ``floor(I/k)`` steps, the middle one the rest
  (URG-04LX: right 44..270, middle 271..498, left 499..725).
* A side's beams are split evenly among its mirrors; mirror 1 is the outermost and takes
  any extra beam. The anchor beam of each mirror is its outermost beam (the paper's OZ).
* Targets: with ``k-1`` mirrors a side, the left mirrors fill the right half of the middle
  window and vice versa ("the other side"), mirror ``j`` at offset ``q = j``; with
  ``(k-1)/2`` mirrors a side, each spans the whole window, left offsets ``1..m``, right
  ``m+1..2m``. A slot is ``bearing(g) + q*res/k`` for direct step ``g``. A plane mirror
  reverses the fan, so a mirror's anchor beam goes to the slot at the sub-window's outer
  edge (the paper's M next to the first unreflected beam OP) and its other beams to the
  following slots inwards.
* Standoff: the paper's OA is the perpendicular distance from O to the anchor beam's
  reflected ray (A is the foot of that perpendicular, eq. 1's ZA = OZ cos 2 theta_r).
  Then angle OMZ = arcsin(OA/D) (the paper prints arcsin(OM/OA)) and OZ = OA / sin(OZM)
  (the paper prints OA sin(OZM)).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from scipy.optimize import brentq, minimize_scalar

from .errors import InfeasibleDesignError
from .geometry import (
    MirrorPatch,
    Perturbation,
    arc_point,
    bearing_of,
    reflect_rays,
    unit,
    wrap_angle,
)
from .lidar import LidarModel
from .spec import DesignSpec

__all__ = ["MirrorSolution", "Design", "solve", "window_steps", "EZ"]

EZ = np.array([0.0, 0.0, 1.0])


def _u(theta: np.ndarray | float) -> np.ndarray:
    """Unit horizontal direction(s) at bearing ``theta``: ``(...,) -> (..., 3)``."""
    th = np.asarray(theta, dtype=float)
    return np.stack([np.cos(th), np.sin(th), np.zeros_like(th)], -1)


def window_steps(lidar: LidarModel, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Steps of the right side, middle and left side windows (each ascending)."""
    n_w = lidar.n_steps // k
    n_side = n_w * (k - 1) // 2
    s = lidar.steps
    return s[:n_side], s[n_side: lidar.n_steps - n_side], s[lidar.n_steps - n_side:]


@dataclass(frozen=True, eq=False)
class MirrorSolution:
    """One solved mirror.

    Attributes
    ----------
    name : str
        ``"L1"``, ``"R2"``...; 1 is the outermost mirror of its side.
    side : str
        ``"L"`` (y > 0) or ``"R"``.
    index : int
        1-based position on its side, counted from the outside.
    steps : (n,) int
        The beams this mirror takes, ascending.
    target_bearing : (n,) float
        Where each of them should land on the arc of radius D [rad].
    offset_index : int
        q: the beams sit ``q * res / k`` anticlockwise of a direct beam.
    patch : MirrorPatch
        The mirror as finite geometry (unperturbed, deployed).
    """

    name: str
    side: str
    index: int
    steps: np.ndarray
    target_bearing: np.ndarray
    offset_index: int
    patch: MirrorPatch
    lidar: LidarModel = field(repr=False)

    @property
    def sign(self) -> int:
        """+1 for the left side, -1 for the right (mirror symmetry of every formula)."""
        return 1 if self.side == "L" else -1

    @property
    def anchor_step(self) -> int:
        """The outermost beam (the paper's OZ)."""
        return int(self.steps[-1] if self.side == "L" else self.steps[0])

    @property
    def first_step(self) -> int:
        return int(self.steps[0])

    @property
    def last_step(self) -> int:
        return int(self.steps[-1])

    @cached_property
    def _hits(self) -> tuple[np.ndarray, np.ndarray]:
        th = self.lidar.bearing_from_step(self.steps)
        t, hit, out = reflect_rays(np.zeros((len(th), 3)), _u(th), self.patch.origin_,
                                   self.patch.normal_)
        return t, out

    @property
    def hit_ranges_m(self) -> np.ndarray:
        """Distance from O to the mirror along each of its beams [m], ``(n,)``."""
        return self._hits[0]

    @property
    def oz_m(self) -> float:
        """Range to the mirror along the anchor beam, the paper's OZ [m]."""
        i = -1 if self.side == "L" else 0
        return float(self.hit_ranges_m[i])

    @property
    def incidence_rad(self) -> np.ndarray:
        """Angle of incidence of each beam on the mirror [rad], ``(n,)`` (paper's gamma)."""
        th = self.lidar.bearing_from_step(self.steps)
        return np.arccos(np.clip(np.abs(_u(th) @ self.patch.normal_), 0, 1))

    @property
    def phi_rad(self) -> float:
        """Angle between the anchor beam and the mirror, the paper's phi [rad]."""
        i = -1 if self.side == "L" else 0
        return float(np.pi / 2 - self.incidence_rad[i])

    @property
    def oa_m(self) -> float:
        """Perpendicular distance from O to the anchor beam's reflected ray, the paper's OA [m]."""
        i = -1 if self.side == "L" else 0
        z = _u(self.lidar.bearing_from_step(self.anchor_step)) * self.oz_m
        d = self._hits[1][i]
        return float(np.linalg.norm(np.cross(-z, d)))

    @property
    def standoff_m(self) -> float:
        """Perpendicular distance from O to the mirror plane, the paper's d [m]."""
        return self.patch.standoff

    @property
    def beam_span_m(self) -> float:
        """Distance between the first and last beams' hit points, the paper's QZ [m]."""
        th = self.lidar.bearing_from_step(self.steps[[0, -1]])
        p = _u(th) * self.hit_ranges_m[[0, -1]][:, None]
        return float(np.linalg.norm(p[1] - p[0]))

    @property
    def length_m(self) -> float:
        """Length of the mirror patch, including the beam margins [m]."""
        return self.patch.length


@dataclass(frozen=True, eq=False)
class Design:
    """A solved design: the spec, the lidar, every mirror and the beam-to-mirror map."""

    spec: DesignSpec
    lidar: LidarModel
    mirrors: tuple[MirrorSolution, ...]
    direct_steps: np.ndarray

    @property
    def design_distance_m(self) -> float:
        return self.spec.layout.design_distance_m

    def mirror(self, name: str) -> MirrorSolution:
        for m in self.mirrors:
            if m.name == name:
                return m
        raise KeyError(f"no mirror {name!r}; have {', '.join(m.name for m in self.mirrors)}")

    @cached_property
    def mirror_of_step(self) -> np.ndarray:
        """Index into :attr:`mirrors` of each valid step, -1 for direct beams. ``(n_steps,)``."""
        out = np.full(self.lidar.n_steps, -1, dtype=int)
        for i, m in enumerate(self.mirrors):
            out[m.steps - self.lidar.step_min] = i
        return out

    @cached_property
    def target_bearing(self) -> np.ndarray:
        """Target bearing at D of every valid step (direct: its own bearing). ``(n_steps,)``."""
        out = self.lidar.bearing_from_step(self.lidar.steps)
        for m in self.mirrors:
            out[m.steps - self.lidar.step_min] = m.target_bearing
        return out

    def patches(self, perturbations: dict[str, Perturbation] | None = None) -> list[MirrorPatch]:
        """Mirror patches, optionally perturbed (mirror name -> Perturbation)."""
        perturbations = perturbations or {}
        return [m.patch.perturbed(perturbations[m.name]) if m.name in perturbations else m.patch
                for m in self.mirrors]

    def beam_model(self, perturbations: dict[str, Perturbation] | None = None,
                   mirrors_deployed: bool = True):
        """The runtime :class:`~nodlidar.beams.BeamModel` of this design."""
        from .beams import BeamModel

        return BeamModel.from_design(self, perturbations, mirrors_deployed=mirrors_deployed)


# ---------------------------------------------------------------------------------------
# target assignment


def _assign(spec: DesignSpec, lidar: LidarModel):
    """Yield (side, index, steps, q, target_bearing) for every mirror."""
    k = spec.layout.windows
    m = spec.layout.mirrors_per_side
    right, middle, left = window_steps(lidar, k)
    res = lidar.angular_resolution
    halves = m == k - 1  # each side fills half of the middle window
    n_half = (len(middle) + 1) // 2
    out = []
    for side, side_steps in (("R", right), ("L", left)):
        # split side beams; mirror 1 (outermost) takes the extra ones
        sizes = np.full(m, len(side_steps) // m)
        sizes[: len(side_steps) % m] += 1
        # outermost first: for L the highest steps, for R the lowest
        ordered = side_steps[::-1] if side == "L" else side_steps
        start = 0
        for j in range(1, m + 1):
            chunk = np.sort(ordered[start: start + sizes[j - 1]])
            start += sizes[j - 1]
            if halves:
                q = j
                sub = middle[:n_half] if side == "L" else middle[n_half:]
            else:
                q = j if side == "L" else m + j
                sub = middle
            n = len(chunk)
            if side == "L":
                # anchor (highest step) -> outer edge slot sub[0]; reversed fan
                g = sub[0] + np.arange(n)[::-1]
            else:
                g = sub[-1] - np.arange(n)
            target = lidar.bearing_from_step(g) + q * res / k
            out.append((side, j, chunk, q, target))
    return out


# ---------------------------------------------------------------------------------------
# placement


def _bisector_normal(z: np.ndarray, m: np.ndarray) -> np.ndarray:
    """Unit normal (towards the lidar side) of the mirror at ``z`` sending the ray O->z to m."""
    return unit(unit(-z) + unit(m - z))


def _anchor_oz(theta_z: float, theta_m: float, oa: float, D: float, name: str) -> float:
    """Range OZ of the anchor point from the paper's OA (triangle ZOM, Section III)."""
    moz = abs(float(wrap_angle(theta_z - theta_m)))
    if moz >= np.pi - 1e-6 or abs(wrap_angle(theta_z - theta_m)) < abs(theta_z - theta_m) - 1e-9:
        raise InfeasibleDesignError(
            f"mirror {name}: its anchor beam at {np.degrees(theta_z):.2f} deg would have to turn "
            f"by 180 deg or more to reach its target at {np.degrees(theta_m):.2f} deg; this split "
            f"cannot be built for this lidar's field of view (try more windows)")
    omz = np.arcsin(oa / D)
    ozm = np.pi - moz - omz
    if ozm <= 1e-6:
        raise InfeasibleDesignError(
            f"mirror {name}: no reflection turns its anchor beam onto its target "
            f"(angle OZM = {np.degrees(ozm):.3f} deg <= 0); reduce placement.standoff_m")
    return float(oa / np.sin(ozm))


def _patch_from_line(name: str, z: np.ndarray, normal: np.ndarray, side: str,
                     steps: np.ndarray, lidar: LidarModel, spec: DesignSpec) -> MirrorPatch:
    """A vertical patch through ``z`` with ``normal``, spanning the mirror's beams +- margin."""
    res = lidar.angular_resolution
    mg = spec.placement.margin_steps
    th_lo = lidar.bearing_from_step(steps[0]) - mg * res
    th_hi = lidar.bearing_from_step(steps[-1]) + mg * res
    along = unit(np.cross(EZ, normal))
    t, hit, _ = reflect_rays(np.zeros((2, 3)), _u(np.array([th_lo, th_hi])), z, normal)
    if not np.all(np.isfinite(t)):
        raise InfeasibleDesignError(
            f"mirror {name}: its edge beams run parallel to or away from the mirror plane "
            f"(the fan is too wide for one flat mirror: use more mirrors_per_side)")
    s = (hit - z) @ along
    h = spec.mirror.glass_height_m
    return MirrorPatch(name=name, origin=tuple(z), normal=tuple(normal), along=tuple(along),
                       s_min=float(s.min()), s_max=float(s.max()), z_min=-h / 2, z_max=h / 2,
                       hinge_z=spec.mirror.hinge_z_m)


def _inner_end(patch: MirrorPatch, side: str) -> np.ndarray:
    """The patch end nearer the middle window (smaller |bearing|)."""
    ends = patch.point(np.array([patch.s_min, patch.s_max]))
    b = np.abs(bearing_of(ends))
    return ends[int(np.argmin(b))]


def _chained_anchor(name: str, joint: np.ndarray, theta_z: float, m_pt: np.ndarray) -> np.ndarray:
    """Anchor point on the ray at ``theta_z`` so that the mirror through it passes ``joint``."""
    u = _u(theta_z)

    def f(oz: float) -> float:
        z = oz * u
        return float((joint - z) @ _bisector_normal(z, m_pt))

    r0 = float(np.linalg.norm(joint[:2]))
    grid = r0 * np.geomspace(0.3, 5.0, 200)
    vals = np.array([f(g) for g in grid])
    idx = np.nonzero(np.sign(vals[:-1]) != np.sign(vals[1:]))[0]
    if len(idx) == 0:
        raise InfeasibleDesignError(
            f"mirror {name}: cannot chain it to the previous mirror's end and still turn its "
            f"anchor beam onto its target")
    # the root nearest the joint's range is the physical one
    i = idx[np.argmin(np.abs(grid[idx] - r0))]
    return brentq(f, grid[i], grid[i + 1], xtol=1e-15) * u


def _errors_for_line(normal: np.ndarray, d: float, thetas: np.ndarray, targets: np.ndarray,
                     D: float) -> np.ndarray:
    """Bearing errors at D [rad] of beams ``thetas`` reflected by the plane n.p = d."""
    point = normal * d
    t, hit, out = reflect_rays(np.zeros((len(thetas), 3)), _u(thetas), point, normal)
    return wrap_angle(bearing_of(arc_point(hit, out, D)) - targets)


def _ray_clearance(normal: np.ndarray, d: float, thetas: np.ndarray) -> np.ndarray:
    """Closest approach to the lidar axis [m] of each beam's reflected ray (plane n.p = d)."""
    t, hit, out = reflect_rays(np.zeros((len(thetas), 3)), _u(thetas), normal * d, normal)
    ahead = np.sum(-hit * out, -1) > 0
    perp = np.linalg.norm(np.cross(hit, out)[:, 2:], axis=-1)
    return np.where(ahead, perp, np.linalg.norm(hit[:, :2], axis=-1))


def _optimise_free(name, z0, n0, thetas, targets, D, r_clear, r_head):
    """Mirror with free azimuth and distance: minimise its RMS bearing error at D.

    Constraints: plane at least ``r_clear`` from the axis, every reflected ray at least
    ``r_head`` from it (so it clears the optical head).
    """
    from scipy.optimize import minimize

    if z0 @ n0 > 0:  # parametrise as n.p = -d with n pointing at the lidar
        n0 = -n0
    x0 = np.array([np.arctan2(n0[1], n0[0]), abs(z0 @ n0)])
    scale = np.array([1e-2, 1e-2])

    def unpack(y):
        x = x0 + y * scale
        return _u(x[0]), -x[1]

    def cost(y):
        n, d = unpack(y)
        return float(np.mean(_errors_for_line(n, d, thetas, targets, D) ** 2)) * 1e4

    def cons(y):
        n, d = unpack(y)
        return np.concatenate([[(-d - r_clear) * 1e2], (_ray_clearance(n, d, thetas) - r_head) * 1e2])

    sol = minimize(cost, np.zeros(2), method="SLSQP", constraints=[{"type": "ineq", "fun": cons}],
                   options={"ftol": 1e-15, "maxiter": 500})
    if not sol.success or np.min(cons(sol.x)) < -1e-6:
        raise InfeasibleDesignError(f"mirror {name}: optimal placement failed ({sol.message})")
    n, d = unpack(sol.x)
    return n, d * n


def _optimise_chained(name, joint, thetas, targets, D, n0):
    """Mirror through ``joint`` with free azimuth: 1-D minimisation of RMS error at D."""
    a0 = np.arctan2(n0[1], n0[0])

    def rms(a):
        n = _u(a)
        return float(np.sqrt(np.mean(_errors_for_line(n, joint @ n, thetas, targets, D) ** 2)))

    sol = minimize_scalar(rms, bounds=(a0 - 0.2, a0 + 0.2), method="bounded",
                          options={"xatol": 1e-12})
    return _u(sol.x)


def solve(spec: DesignSpec, *, check: bool = True) -> Design:
    """Place every mirror of ``spec`` and return the :class:`Design`.

    Raises
    ------
    InfeasibleDesignError
        If a mirror cannot be placed, would overlap the lidar housing (plus clearance), or
        the ray trace finds a beam blocked (see :func:`nodlidar.verify.verify`).
    """
    lidar = spec.lidar_model
    D = spec.layout.design_distance_m
    pl = spec.placement
    r_clear = lidar.housing_radius_m + pl.clearance_m
    mirrors: list[MirrorSolution] = []
    prev: dict[str, MirrorPatch] = {}
    for side, j, steps, q, target in _assign(spec, lidar):
        name = f"{side}{j}"
        thetas = lidar.bearing_from_step(steps)
        a = -1 if side == "L" else 0  # anchor index: the outermost beam
        theta_z, theta_m = thetas[a], target[a]
        m_pt = D * _u(theta_m)
        if j == 1 or not pl.chain:
            oa = pl.standoff_m[0 if pl.chain else j - 1]
            z = _anchor_oz(theta_z, theta_m, oa, D, name) * _u(theta_z)
        else:
            z = _chained_anchor(name, _inner_end(prev[side], side), theta_z, m_pt)
        normal = _bisector_normal(z, m_pt)
        if pl.method == "optimal":
            if j == 1 or not pl.chain:
                normal, point = _optimise_free(name, z, normal, thetas, target, D, r_clear,
                                               lidar.head_radius_m + pl.clearance_m / 2)
            else:
                joint = _inner_end(prev[side], side)
                normal = _optimise_chained(name, joint, thetas, target, D, normal)
                point = joint
            # re-anchor on the anchor beam so 'origin' keeps its meaning
            t, hit, _ = reflect_rays(np.zeros((1, 3)), _u(theta_z)[None], point, normal)
            z = hit[0]
            if normal @ (-z) < 0:
                normal = -normal
        patch = _patch_from_line(name, z, normal, side, steps, lidar, spec)
        ends = patch.point(np.array([patch.s_min, patch.s_max]))
        # nearest point of the segment to the lidar axis
        seg = ends[1] - ends[0]
        tt = np.clip(-(ends[0] @ seg) / (seg @ seg), 0, 1)
        closest = float(np.linalg.norm((ends[0] + tt * seg)[:2]))
        if closest < r_clear:
            raise InfeasibleDesignError(
                f"mirror {name} comes within {closest * 1000:.1f} mm of the lidar axis; the "
                f"housing plus clearance needs >= {r_clear * 1000:.1f} mm "
                f"(increase placement.standoff_m or reduce placement.clearance_m)")
        prev[side] = patch
        mirrors.append(MirrorSolution(name=name, side=side, index=j, steps=steps,
                                      target_bearing=target, offset_index=q, patch=patch,
                                      lidar=lidar))
    # order: L1, L2, ..., R1, R2, ...
    mirrors.sort(key=lambda m: (m.side != "L", m.index))
    _, middle, _ = window_steps(lidar, spec.layout.windows)
    design = Design(spec=spec, lidar=lidar, mirrors=tuple(mirrors), direct_steps=middle)
    from .verify import verify

    if not check:
        return design
    report = verify(design)
    if report.n_blocked:
        worst = ", ".join(f"{n}: {c}" for n, c in report.blocked_by_mirror().items() if c)
        raise InfeasibleDesignError(
            f"{report.n_blocked} beams are blocked by another mirror or the housing ({worst}); "
            f"this split cannot be built with these standoffs")
    return design
