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

import math
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from .design import Design, MirrorSolution  # the solved-design types (re-exported here)
from .errors import InfeasibleDesignError, ParameterError
from .geometry import (
    EZ,
    TOL,
    MirrorPatch,
    arc_point,
    bearing_of,
    directions_from_bearings,
    reflect_rays,
    unit,
    wrap_angle,
)
from .lidar import LidarModel
from .spec import DesignSpec
from .verify import verify

__all__ = ["MirrorSolution", "Design", "solve", "window_steps", "front_window", "EZ"]


def window_steps(lidar: LidarModel, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Steps of the right side, middle and left side windows (each ascending)."""
    n_w = lidar.n_steps // k
    n_side = n_w * (k - 1) // 2
    s = lidar.steps
    return s[:n_side], s[n_side: lidar.n_steps - n_side], s[lidar.n_steps - n_side:]


# ---------------------------------------------------------------------------------------
# target assignment


@dataclass(frozen=True)
class _Plan:
    """What one mirror must do: its beams, its anchor and target slot, how it is placed."""

    name: str
    side: str
    index: int
    steps: np.ndarray
    anchor: int
    target_step: int          # g0: the anchor beam lands q/slots of a step beside it
    q: int                    # 0 <= q < slots
    standoff_m: float | None  # OA, None when chained
    chain: bool

    def targets(self, lidar: LidarModel, slots: int) -> np.ndarray:
        """Target bearing at D of each of :attr:`steps` (reversed fan about the anchor)."""
        g = self.target_step - (self.steps - self.anchor)
        return lidar.bearing_from_step(g) + self.q * lidar.angular_resolution / slots


def _steps_of(lidar: LidarModel, steps: tuple, deg: tuple, name: str) -> np.ndarray:
    """Valid steps of a window given by edge steps or edge bearings [deg]."""
    if steps:
        lo, hi = steps
        lidar.check_step(np.array([lo, hi]), name + ".steps")
        return np.arange(lo, hi + 1)
    b = np.degrees(lidar.bearing_from_step(lidar.steps))
    sel = lidar.steps[(b >= deg[0] - TOL.angle_deg) & (b <= deg[1] + TOL.angle_deg)]
    if not len(sel):
        raise ParameterError(name + ".deg", list(deg), f"a range holding at least one step of "
                             f"{lidar.name} ({b[0]:.2f} .. {b[-1]:.2f} deg)")
    return sel


def front_window(spec: DesignSpec, lidar: LidarModel) -> np.ndarray:
    """Steps of the unreflected front window, ascending ``(n,) int``."""
    lay = spec.layout
    if lay.front_window_steps or lay.front_window_deg:
        return _steps_of(lidar, lay.front_window_steps, lay.front_window_deg,
                         "layout.front_window")
    if spec.placement.mirrors and not lay.side_windows:
        # explicit mirrors: the run of steps no mirror takes around the front step
        free = np.ones(lidar.n_steps, bool)
        for mp in spec.placement.mirrors:
            free[max(mp.steps[0], lidar.step_min) - lidar.step_min:
                 min(mp.steps[1], lidar.step_max) - lidar.step_min + 1] = False
        i = lidar.step_front - lidar.step_min
        lo, hi = i, i
        while lo > 0 and free[lo - 1]:
            lo -= 1
        while hi < lidar.n_steps - 1 and free[hi + 1]:
            hi += 1
        return lidar.steps[lo: hi + 1]
    if lay.side_windows:
        raise ParameterError("layout.front_window_steps", [], "[first, last] (or "
                             "front_window_deg) when side_windows are given")
    return window_steps(lidar, lay.windows)[1]


def _side_windows(spec: DesignSpec, lidar: LidarModel, front: np.ndarray):
    """(side, steps, offsets) of every reflected window, outermost window of a side first."""
    lay = spec.layout
    if not lay.side_windows:
        right, _, left = window_steps(lidar, lay.windows)
        m = lay.mirrors_per_side
        halves = m == lay.windows - 1  # each side fills half of the middle window
        q_r = tuple(range(1, m + 1)) if halves else tuple(range(m + 1, 2 * m + 1))
        return [("R", right, m, q_r), ("L", left, m, tuple(range(1, m + 1)))]
    out = []
    for i, w in enumerate(lay.side_windows):
        st = _steps_of(lidar, w.steps, w.deg, f"layout.side_windows[{i}]")
        if st[0] > front[-1]:
            side = "L"
        elif st[-1] < front[0]:
            side = "R"
        else:
            raise ParameterError(f"layout.side_windows[{i}]", [int(st[0]), int(st[-1])],
                                 f"steps wholly below or above the front window "
                                 f"{int(front[0])}..{int(front[-1])}")
        if len(st) < w.mirrors:
            raise ParameterError(f"layout.side_windows[{i}].mirrors", w.mirrors,
                                 f"<= its {len(st)} beams")
        out.append((side, st, w.mirrors, w.offsets))
    taken = np.concatenate([o[1] for o in out])
    if len(np.unique(taken)) != len(taken):
        raise ParameterError("layout.side_windows", [[int(o[1][0]), int(o[1][-1])] for o in out],
                             "windows that do not overlap")
    # outermost window of a side first, so mirror numbers count from the outside
    out.sort(key=lambda o: (o[0], -o[1][-1] if o[0] == "L" else o[1][0]))
    return out


def _plans(spec: DesignSpec, lidar: LidarModel) -> tuple[list[_Plan], np.ndarray]:
    """Every mirror's plan and the front window's steps."""
    pl = spec.placement
    k = spec.layout.slots
    front = front_window(spec, lidar)
    plans: list[_Plan] = []
    if pl.mirrors:
        for mp in pl.mirrors:
            lidar.check_step(np.array(mp.steps), f"placement.mirrors[{mp.name}].steps")
            g0 = mp.target_step + mp.target_offset // k
            plans.append(_Plan(mp.name, mp.side, mp.index, np.arange(mp.steps[0], mp.steps[1] + 1),
                               int(mp.anchor), int(g0), int(mp.target_offset % k),
                               None if mp.chain else mp.standoff_m, mp.chain))
        return plans, front
    # fill the front window's slots: per offset q, left-side beams from its first step up
    # and right-side beams from its last step down (a plane mirror reverses the fan, so a
    # side's outermost beam lands at the far edge)
    next_g: dict[tuple[str, int], int] = {}
    count = {"L": 0, "R": 0}
    for side, st, m, offsets in _side_windows(spec, lidar, front):
        sizes = np.full(m, len(st) // m)
        sizes[: len(st) % m] += 1
        ordered = st[::-1] if side == "L" else st  # outermost first
        start = 0
        for j in range(m):
            chunk = np.sort(ordered[start: start + sizes[j]])
            start += sizes[j]
            count[side] += 1
            idx = count[side]
            q = offsets[j]
            key = (side, q)
            g0 = next_g.get(key, int(front[0]) if side == "L" else int(front[-1]))
            n = len(chunk)
            next_g[key] = g0 + n if side == "L" else g0 - n
            anchor = int(chunk[-1] if side == "L" else chunk[0])
            # chaining joins the mirrors of one window (another window may lie apart)
            chained = pl.chain and j > 0
            oa = None
            if not chained:
                oa = pl.standoff_m[0] if pl.chain else pl.standoff_m[min(idx, len(pl.standoff_m)) - 1]
            plans.append(_Plan(f"{side}{idx}", side, idx, chunk, anchor, g0 + q // k, q % k, oa,
                               chained))
    _check_slots(plans, front, lidar, k)
    return plans, front


def _check_slots(plans: list[_Plan], front: np.ndarray, lidar: LidarModel, k: int) -> None:
    """Refuse splits whose targets leave the front window or share a slot."""
    owner: dict[tuple[int, int], str] = {}
    for p in plans:
        g = p.target_step - (p.steps - p.anchor)
        out = g[(g < front[0]) | (g > front[-1])]
        if len(out):
            raise InfeasibleDesignError(
                f"mirror {p.name} ({len(p.steps)} beams, steps {p.steps[0]}..{p.steps[-1]}) "
                f"would land beside steps {g.min()}..{g.max()} but the front window is "
                f"{front[0]}..{front[-1]} ({len(out)} beams outside): give it fewer beams, "
                f"another offset, or a wider front window")
        for gi in g:
            key = (int(gi), p.q)
            if key in owner:
                raise InfeasibleDesignError(
                    f"mirrors {owner[key]} and {p.name} both send a beam to the slot "
                    f"{p.q}/{k} of a step beside step {gi}: give them different "
                    f"layout.side_windows.offsets")
            owner[key] = p.name


# ---------------------------------------------------------------------------------------
# scalar solvers: dependency-free, so solving a design does not import scipy.optimize
# (~0.5 s of a fresh ``nodlidar design``, issue 16). Written here from the textbook
# methods (regula falsi with the Illinois modification; golden section with parabolic
# steps), not ported from scipy; tests/test_solver_regression.py checks them against
# scipy's ``brentq`` and ``minimize_scalar(method="bounded")`` within their tolerances.

_RTOL_ROOT = 4 * 2.220446049250313e-16  # relative part of the root's tolerance
_GOLDEN = (3.0 - math.sqrt(5.0)) / 2    # golden-section fraction of a bracket, ~0.382
_SQRT_EPS = math.sqrt(2.220446049250313e-16)


def _brent_root(f: Callable[[float], float], xa: float, xb: float, xtol: float,
                rtol: float = _RTOL_ROOT, maxiter: int = 200) -> float:
    """A root of ``f`` in the bracket ``[xa, xb]`` (``f`` changes sign across it).

    Regula falsi with the Illinois modification (the end that stays put has its value
    halved, so the bracket shrinks from both sides), and a bisection whenever a step
    left more than half the bracket. Returns the end of the final bracket with the
    smaller ``|f|`` once the bracket is narrower than ``xtol + rtol*|x|``.
    """
    a, b = float(xa), float(xb)
    fa, fb = f(a), f(b)
    if fa == 0:
        return a
    if fb == 0:
        return b
    if math.copysign(1.0, fa) == math.copysign(1.0, fb):
        raise ValueError("f(xa) and f(xb) must have different signs")
    side = 0  # which end was kept by the last step: -1 a, +1 b
    for _ in range(maxiter):
        x_best = a if abs(fa) < abs(fb) else b
        width = abs(b - a)
        if width <= xtol + rtol * abs(x_best):
            return x_best
        x = (a * fb - b * fa) / (fb - fa)
        if not (min(a, b) < x < max(a, b)):
            x = 0.5 * (a + b)
        fx = f(x)
        if fx == 0:
            return x
        if math.copysign(1.0, fx) == math.copysign(1.0, fa):
            a, fa = x, fx
            if side == 1:
                fb *= 0.5  # b kept twice running: Illinois step
            side = 1
        else:
            b, fb = x, fx
            if side == -1:
                fa *= 0.5
            side = -1
        if abs(b - a) > 0.5 * width:  # a slow falsi step: bisect as well
            m = 0.5 * (a + b)
            fm = f(m)
            if fm == 0:
                return m
            if math.copysign(1.0, fm) == math.copysign(1.0, fa):
                a, fa = m, fm
            else:
                b, fb = m, fm
            side = 0
    raise ValueError(f"no convergence in {maxiter} iterations")


def _bounded_min(func: Callable[[float], float], lo: float, hi: float, xatol: float,
                 maxfun: int = 500) -> float:
    """Minimiser of ``func`` on ``[lo, hi]`` (a unimodal function: the bracket keeps the
    minimum of the points seen).

    Golden-section steps, replaced by the vertex of the parabola through the three best
    points whenever that vertex lies inside the bracket and moves less than half the step
    before last (so it converges superlinearly on smooth minima and never worse than
    golden section). Stops when the bracket is within ``2*tol`` of the best point on both
    sides, ``tol = sqrt(eps)*|x| + xatol/3`` (``sqrt(eps)|x|``: a smooth minimum is flat
    to rounding within that), or after ``maxfun`` evaluations.
    """
    a, b = float(lo), float(hi)
    x = a + _GOLDEN * (b - a)
    fx = func(x)
    w, fw, v, fv = x, fx, x, fx  # second and third best points
    step = prev = 0.0             # the last step and the one before it
    for _ in range(maxfun - 1):
        mid = 0.5 * (a + b)
        tol = _SQRT_EPS * abs(x) + xatol / 3.0
        if abs(x - mid) <= 2.0 * tol - 0.5 * (b - a):
            break
        parabolic = False
        if abs(prev) > tol:
            # vertex of the parabola through (x, fx), (w, fw), (v, fv), as x + num/den
            t1 = (x - w) * (fx - fv)
            t2 = (x - v) * (fx - fw)
            num = (x - v) * t2 - (x - w) * t1
            den = 2.0 * (t2 - t1)
            if den > 0.0:
                num = -num
            den = abs(den)
            if abs(num) < abs(0.5 * den * prev) and den * (a - x) < num < den * (b - x):
                parabolic = True
                prev, step = step, num / den
                if x + step - a < 2.0 * tol or b - (x + step) < 2.0 * tol:
                    step = tol if mid >= x else -tol  # too near an end: tol toward the middle
        if not parabolic:
            prev = (a - x) if x >= mid else (b - x)
            step = _GOLDEN * prev
        if abs(step) < tol:  # never evaluate closer than tol to the best point
            step = tol if (step > 0.0 or (step == 0.0 and mid >= x)) else -tol
        u = x + step
        fu = func(u)
        if fu <= fx:  # u is the new best: the bracket shrinks to u's side of x
            if u >= x:
                a = x
            else:
                b = x
            v, fv, w, fw, x, fx = w, fw, x, fx, u, fu
        else:         # x stays best: the bracket shrinks to x's side of u
            if u < x:
                a = u
            else:
                b = u
            if fu <= fw or w == x:
                v, fv, w, fw = w, fw, u, fu
            elif fu <= fv or v == x or v == w:
                v, fv = u, fu
    return x


# ---------------------------------------------------------------------------------------
# placement


def _bisector_normal(z: np.ndarray, m: np.ndarray) -> np.ndarray:
    """Unit normal (towards the lidar side) of the mirror at ``z`` sending the ray O->z to m."""
    return unit(unit(-z) + unit(m - z))


def _anchor_oz(theta_z: float, theta_m: float, oa: float, D: float, name: str) -> float:
    """Range OZ of the anchor point from the paper's OA (triangle ZOM, Section III)."""
    moz = abs(float(wrap_angle(theta_z - theta_m)))
    wrapped = abs(wrap_angle(theta_z - theta_m)) < abs(theta_z - theta_m) - TOL.angle_rad
    if moz >= np.pi - TOL.degenerate_rad or wrapped:
        raise InfeasibleDesignError(
            f"mirror {name}: its anchor beam at {np.degrees(theta_z):.2f} deg would have to turn "
            f"by {abs(np.degrees(theta_z - theta_m)):.1f} deg to reach its target at "
            f"{np.degrees(theta_m):.2f} deg, and a flat mirror turns a beam by less than "
            f"180 deg; this split cannot be built for this lidar's field of view (try more "
            f"windows, or a front window nearer this side)")
    omz = np.arcsin(oa / D)
    ozm = np.pi - moz - omz
    if ozm <= TOL.degenerate_rad:
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
    t, hit, _ = reflect_rays(np.zeros((2, 3)), directions_from_bearings(np.array([th_lo, th_hi])), z, normal)
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
    u = directions_from_bearings(theta_z)

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
    return _brent_root(f, grid[i], grid[i + 1], xtol=1e-15) * u


def _errors_for_line(normal: np.ndarray, d: float, thetas: np.ndarray, targets: np.ndarray,
                     D: float) -> np.ndarray:
    """Bearing errors at D [rad] of beams ``thetas`` reflected by the plane n.p = d."""
    point = normal * d
    t, hit, out = reflect_rays(np.zeros((len(thetas), 3)), directions_from_bearings(thetas), point, normal)
    return wrap_angle(bearing_of(arc_point(hit, out, D)) - targets)


def _ray_clearance(normal: np.ndarray, d: float, thetas: np.ndarray) -> np.ndarray:
    """Closest approach to the lidar axis [m] of each beam's reflected ray (plane n.p = d)."""
    t, hit, out = reflect_rays(np.zeros((len(thetas), 3)), directions_from_bearings(thetas),
                               normal * d, normal)
    ahead = np.sum(-hit * out, -1) > 0
    perp = np.linalg.norm(np.cross(hit, out)[:, 2:], axis=-1)
    return np.where(ahead, perp, np.linalg.norm(hit[:, :2], axis=-1))


def _optimise_free(name: str, z0: np.ndarray, n0: np.ndarray, thetas: np.ndarray,
                   targets: np.ndarray, D: float, r_clear: float, r_head: float
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Mirror with free azimuth and distance: minimise its RMS bearing error at D.

    Constraints: plane at least ``r_clear`` from the axis, every reflected ray at least
    ``r_head`` from it (so it clears the optical head). Returns the unit normal (3,) and
    a point of the plane (3,) [m].

    The plane is n.p = -d with n = (cos a, sin a, 0) facing the lidar. Both constraints are
    lower bounds on d for a given a (:func:`_standoff_floor`: a reflected ray's clearance
    is d times a function of its incidence angle), so the 2-variable problem is a nested
    pair of 1-variable ones: for each a the best d >= that floor (:func:`_best_standoff`),
    then the best a within 0.2 rad of the anchor placement's azimuth (the search is local,
    as the SLSQP it replaced was: the anchor placement is the start).
    """
    if z0 @ n0 > 0:  # parametrise as n.p = -d with n pointing at the lidar
        n0 = -n0
    a0 = float(np.arctan2(n0[1], n0[0]))
    u = directions_from_bearings(thetas)
    half = 0.2

    def cost(a: float, d: float) -> float:
        n = directions_from_bearings(a)
        return float(np.mean(_errors_for_line(n, -d, thetas, targets, D) ** 2))

    def best(x: float) -> tuple[float, float]:
        a = a0 + x
        return _best_standoff(lambda d: cost(a, d),
                              _standoff_floor(u, directions_from_bearings(a), r_clear, r_head))

    # the offset from a0 is the variable: the minimiser's stopping tolerance is relative to
    # |x| (~1e-8 |x|), so near 0 it resolves the azimuth to ~1e-10 rad, where the cost's
    # own rounding (a quadratic minimum flat to 1e-16 relative) sets the limit
    x = _bounded_min(lambda x: best(x)[0], -half, half, xatol=1e-12)
    f, d = best(x)
    if not math.isfinite(f) or abs(x) > half - 1e-6:
        raise InfeasibleDesignError(
            f"mirror {name}: optimal placement failed (no minimum of the RMS error within "
            f"{np.degrees(half):.1f} deg of the anchor placement's azimuth)")
    n = directions_from_bearings(a0 + x)
    clear = _ray_clearance(n, -d, thetas)
    if d < r_clear - 1e-12 or clear.min() < r_head - 1e-12:  # the floor is exact: a bug guard
        raise InfeasibleDesignError(f"mirror {name}: optimal placement failed (constraints)")
    return n, -d * n


def _standoff_floor(u: np.ndarray, n: np.ndarray, r_clear: float, r_head: float) -> float:
    """Least plane distance d [m] for which the mirror n.p = -d keeps ``r_clear`` from the
    axis and every reflected beam ``r_head`` from it (inf if a beam misses the plane).

    u : (m, 3) beam directions; n : (3,) unit normal facing the lidar. A beam meeting the
    plane at incidence g (cos g = -u.n) hits it at range d/cos g; its reflected ray's
    closest approach to O is 2 d sin g when that point lies ahead of the hit (g < 45 deg),
    else the hit itself, d/cos g (:func:`_ray_clearance` computes the same by vectors).
    Both are d times a function of g, so each beam bounds d from below.
    """
    c = -(u @ n)
    if np.any(c <= TOL.parallel):
        return math.inf
    sin_g = np.abs(u[:, 0] * n[1] - u[:, 1] * n[0])  # |u x n| (horizontal): exact near g = 0
    per_m = np.where(c > math.sqrt(0.5), 2 * sin_g, 1 / c)
    with np.errstate(divide="ignore"):  # normal incidence: reflected back through O, inf
        return max(r_clear, float(np.max(r_head / per_m)))


def _best_standoff(cost: Callable[[float], float], floor: float) -> tuple[float, float]:
    """(least cost, its d) of ``cost(d)`` over ``d >= floor`` [m].

    For d much smaller than D the reflected beams' bearing errors at D are affine in d (the
    virtual origin moves by 2d along the normal) to O((d/D)^2), so the squared error is a
    convex quadratic in d: the floor is the minimum when the cost rises from it (the usual
    case, found in every design in design/), else the minimum lies above it.
    """
    if not math.isfinite(floor):
        return math.inf, floor
    f0 = cost(floor)
    if cost(floor + 1e-6) >= f0:
        return f0, floor
    d = _bounded_min(cost, floor, floor + 0.5, xatol=1e-12)
    fd = cost(d)
    return (fd, d) if fd < f0 else (f0, floor)


def _optimise_chained(name: str, joint: np.ndarray, thetas: np.ndarray, targets: np.ndarray,
                      D: float, n0: np.ndarray) -> np.ndarray:
    """Mirror through ``joint`` with free azimuth: 1-D minimisation of RMS error at D.

    The variable is the offset from the anchor placement's azimuth (within 0.2 rad): the
    search stops within ~1.5e-8 |x| of the minimum, ~1e-10 rad near x = 0 (as the
    azimuth itself, ~0.9 rad, it stopped only within ~1.3e-8 rad).
    """
    a0 = float(np.arctan2(n0[1], n0[0]))

    def rms(x: float) -> float:
        n = directions_from_bearings(a0 + x)
        return float(np.sqrt(np.mean(_errors_for_line(n, joint @ n, thetas, targets, D) ** 2)))

    return directions_from_bearings(a0 + _bounded_min(rms, -0.2, 0.2, xatol=1e-12))


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
    plans, front = _plans(spec, lidar)
    k = spec.layout.slots
    for plan in plans:
        name, side, j, steps, q = plan.name, plan.side, plan.index, plan.steps, plan.q
        target = plan.targets(lidar, k)
        thetas = lidar.bearing_from_step(steps)
        theta_z = float(lidar.bearing_from_step(plan.anchor))
        theta_m = float(lidar.bearing_from_step(plan.target_step) + q * lidar.angular_resolution / k)
        if np.sign(theta_z) != (1 if side == "L" else -1):
            raise ParameterError(f"placement.mirrors[{name}]", [int(steps[0]), int(steps[-1])],
                                 f"steps on the {'left (above' if side == 'L' else 'right (below'}"
                                 f" step {lidar.step_front})")
        m_pt = D * directions_from_bearings(theta_m)
        if not plan.chain:
            assert plan.standoff_m is not None  # an unchained plan always has its OA
            z = _anchor_oz(theta_z, theta_m, plan.standoff_m, D, name) * directions_from_bearings(theta_z)
        else:
            if side not in prev:
                raise ParameterError(f"placement.mirrors[{name}].chain", True,
                                     "false for the first mirror of its side")
            z = _chained_anchor(name, _inner_end(prev[side], side), theta_z, m_pt)
        normal = _bisector_normal(z, m_pt)
        if pl.method == "optimal":
            if not plan.chain:
                normal, point = _optimise_free(name, z, normal, thetas, target, D, r_clear,
                                               lidar.head_radius_m + pl.clearance_m / 2)
            else:
                joint = _inner_end(prev[side], side)
                normal = _optimise_chained(name, joint, thetas, target, D, normal)
                point = joint
            # re-anchor on the anchor beam so 'origin' keeps its meaning
            t, hit, _ = reflect_rays(np.zeros((1, 3)), directions_from_bearings(theta_z)[None], point, normal)
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
                                      lidar=lidar, anchor=plan.anchor,
                                      target_step=plan.target_step))
    # order: L1, L2, ..., R1, R2, ...
    mirrors.sort(key=lambda m: (m.side != "L", m.index))
    design = Design(spec=spec, lidar=lidar, mirrors=tuple(mirrors), direct_steps=front)
    if not check and not spec.placement.shadowed_steps:
        return design
    report = verify(design)
    if spec.placement.shadowed_steps:
        # the given-up steps the trace finds blocked: the runtime must not project them
        design = replace(design, shadowed_steps=report.steps[report.bad & ~report.unexpected_blocked()])
    if not check:
        return design
    bad = report.unexpected_blocked()
    if bad.any():
        raise InfeasibleDesignError(
            f"{int(bad.sum())} beams are blocked by another mirror or the housing "
            f"({report.describe_blocked(bad)}); this split cannot be built with these standoffs")
    return design
