"""Parametric mirror mounts: pure functions from a solved design + :class:`MountParams`.

Everything is built in the head frame (x forward, y left, z up, scan plane z = 0,
lidar optical axis = z axis) in **millimetres**; metres from the solver are converted
once, in :func:`side_layouts`. cadquery is imported inside the build functions only, so
the numpy layout (:func:`hinge_axes`, :func:`mirror_face_poses`) works without it.

Parts
-----
``base`` (printable)
    Plate under the lidar (its top is the lidar's housing base, ``scan_plane_height``
    below the scan plane) with 4 lidar holes and 4 base holes, and per side a front hinge
    pillar (bore for the hinge pin) and a servo cradle (pocket for the lift servo, screw
    holes). The plate never reaches past ``clearance_mm`` of the lifted carriers.
``carrier_L`` / ``carrier_R`` (printable)
    One per side, holding all of that side's glass: a back plate whose front face is the
    glass datum (exactly ``glass_thickness`` behind the solved reflecting face), a skirt
    whose top is the glass seat (``z_min`` of the patch), a hinge tube with a bore on the
    side's hinge axis, and a horn flange (4 holes) at the outer end for the servo horn.
    Each glass's pocket is closed at both ends, ``pocket_clearance_mm`` longer than the
    solved mirror (half of it at each end), so the printed part locates the glass along
    its length: at a free end (the outer end of the side's outermost mirror, the inner
    end of its innermost one, both ends of an unchained mirror) by an end stop, a block
    square to the mirror beyond the patch's ``s`` range, standing ``end_stop_depth_mm``
    (less than the glass thickness) in front of the datum and ``end_stop_height_mm`` above
    the seat, so it stays behind the face plane and below the beam band; at a chained
    joint by the back plate's joint face, which closes the wedge between the two glass
    ends behind their faces (a face at half the joint angle to each datum that meets the
    glass's back edge; the wedge is too thin for a square stop of ``min_wall_mm``). The
    pocket is open in front (the glass goes in from the lidar side) and no wall stands
    in a beam path; the glass is bonded to the datum faces.

    Close unchained neighbours (``placement.chain = false``, e.g. the paper read to its
    printed numbers, ``design/urg04lx-paper.toml``, where L2's outer end stands
    4.9 mm in front of L1's glass near L1's inner end): a free end stop that would run
    into the neighbour's glass is cut back to clear it by ``pocket_clearance_mm / 2`` -
    at the neighbour's glass end when the two ends face each other across a short gap
    (one web between the two pockets then holds both ends), else at the neighbour's face
    plane, where the stop stands in front of the lower part of that glass, below the beam
    band, as a lip that also keeps its bottom in the pocket (that glass goes in from
    above). The cut stop must still meet its glass end over ``end_stop_depth_mm`` and be
    ``min_wall_mm`` wide, else the build is refused naming both mirrors. Where a lidar
    beam passes beyond an unchained glass's end through its back plate (the paper-exact
    build's steps 612..615 between L1 and L2), the plate is cut to the glass's shadow (the
    ray from the optical centre tangent to the glass end) and the acute wedge this leaves
    is blunted to ``min_wall_mm``: the datum then stops ``min_wall / tan(a)`` short of
    that glass end (0.65 mm there), which overhangs its bonded face. The glass's own end
    face (its thickness, which the solver's faces do not have) still meets such beams.
    Chained sides are built exactly as before.
``glass_<mirror>`` (reference)
    The mirror glass: its front face *is* the solved :class:`~nodlidar.geometry.MirrorPatch`.
``servo_<side>``, ``lidar`` (reference)
    Envelopes used for interference checks (servo body + horn; lidar housing + head).

Hinge axis (one per side carrier)
---------------------------------
A side's mirrors sit on one carrier turned by one servo horn, so they all turn about one
line: the side's lift axis of :func:`nodlidar.hinge.side_lift_axes` (the one hinge model
of the code base, which the simulator and the ROS outputs use too; :class:`HingeAxis` is
its view in mm). It is horizontal at ``z = hinge_z``, parallel to the chord from the
outer end of the outermost mirror face to the inner end of the innermost one, through
the most lidar-ward point of the side's faces. The carrier conforms to the axis: its
plan polygons (back plate, end stops, skirt) are clipped to the half-plane behind it
(away from the lidar), so every part of the carrier lies on or behind it. Lifting turns
the carrier by ``lift_angle`` about this axis with the top swinging away from the lidar,
so all carrier material ends up below ``hinge_z + hinge_boss_radius``: out of the beams.
In the deployed state the faces are exactly the solver's patches.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import NodlidarError, ParameterError
from ..geometry import matrix_from_axis_angle, unit
from ..hinge import LiftAxis, face_ends, side_lift_axes
from .params import MountParams

if TYPE_CHECKING:  # pragma: no cover
    import cadquery as cq  # noqa: TID251 (typing only)

    from ..solver import Design

__all__ = [
    "CadBuildError",
    "STATES",
    "HingeAxis",
    "SideLayout",
    "Part",
    "MountModel",
    "side_layouts",
    "hinge_axes",
    "lift_transform",
    "mirror_face_poses",
    "build_mounts",
    "part_shapes",
    "build_assembly",
]

STATES = ("deployed", "lifted")
MM_PER_M = 1000.0
EZ = np.array([0.0, 0.0, 1.0])


class CadBuildError(NodlidarError):
    """The mounts cannot be built from this design and these parameters (message says why)."""


def mm_from_m(x: Any) -> np.ndarray:
    """Metres -> millimetres (the only unit conversion of the CAD layer)."""
    return np.asarray(x, dtype=float) * MM_PER_M




# ---------------------------------------------------------------------------------------
# layout (numpy only)


@dataclass(frozen=True)
class HingeAxis:
    """A side carrier's hinge axis (head frame, mm).

    Attributes
    ----------
    side : str
        ``"L"`` or ``"R"``.
    point_mm : (3,) float
        A point of the axis (level with ``hinge_z``, at the outer end of the mirrors).
    direction : (3,) float
        Unit direction, from the outer end towards the inner end of the side's mirrors.
    outward : (3,) float
        Unit horizontal direction perpendicular to the axis, away from the lidar.
    lift_rad : float
        Signed rotation about ``direction`` [rad] that lifts the carrier (top away).
    """

    side: str
    point_mm: tuple[float, float, float]
    direction: tuple[float, float, float]
    outward: tuple[float, float, float]
    lift_rad: float

    @classmethod
    def from_lift_axis(cls, axis: LiftAxis) -> HingeAxis:
        """The CAD's view (mm) of the side's lift axis (:func:`nodlidar.hinge.side_lift_axes`)."""
        x, y, z = (float(v) for v in mm_from_m(axis.point_m))
        return cls(side=axis.side, point_mm=(x, y, z),
                   direction=axis.direction, outward=axis.outward, lift_rad=axis.lift_rad)

    def to_dict(self) -> dict[str, Any]:
        return {"side": self.side, "point_mm": list(self.point_mm),
                "direction": list(self.direction), "outward": list(self.outward),
                "lift_deg": float(np.degrees(self.lift_rad))}


@dataclass(frozen=True, eq=False)
class SideLayout:
    """Plan-view geometry of one side carrier (mm), derived from the solved patches."""

    side: str
    mirror_names: tuple[str, ...]
    axis: HingeAxis
    back_polygons: tuple[np.ndarray, ...]   # (k, 2) xy polygons of the back plate
    skirt_polygon: np.ndarray               # (k, 2) convex hull
    u_lo: float                             # carrier body extent along the axis [mm]
    u_hi: float
    chained: bool
    stop_polygons: tuple[np.ndarray, ...] = ()   # (4, 2) xy polygons of the end stops
    stop_ends: tuple[tuple[str, str], ...] = ()  # (mirror name, "outer"/"inner") per stop
    # per stop: the neighbour glass it was cut back to clear (None: a plain stop); empty
    # when no stop of the side was cut (every chained design)
    stop_beside: tuple[str | None, ...] = ()


def _clip_halfplane(poly: np.ndarray, p0: np.ndarray, w: np.ndarray) -> np.ndarray | None:
    """The part of the convex-or-simple plan polygon ``poly (k, 2)`` [mm] where
    ``(p - p0) . w >= 0``, or None if nothing is left (Sutherland-Hodgman against one
    half-plane: exact for any simple polygon that crosses the line at most twice)."""
    e = (poly - p0) @ w
    if np.all(e >= 0):
        return poly
    out = []
    k = len(poly)
    for i in range(k):
        j = (i + 1) % k
        if e[i] >= 0:
            out.append(poly[i])
        if (e[i] >= 0) != (e[j] >= 0):
            f = e[i] / (e[i] - e[j])
            out.append(poly[i] + f * (poly[j] - poly[i]))
    # a vertex on the line is entered once, not again as a crossing
    q = np.array([p for i, p in enumerate(out) if np.linalg.norm(p - out[i - 1]) > 1e-9])
    if len(q) < 3:
        return None
    area = 0.5 * abs(float(np.sum(q[:, 0] * np.roll(q[:, 1], -1) - np.roll(q[:, 0], -1) * q[:, 1])))
    return q if area > 1e-9 else None


def _clip_behind(poly: np.ndarray, axis: HingeAxis) -> np.ndarray | None:
    """The part of the plan polygon ``poly (k, 2)`` [mm] on or behind the hinge axis (on
    its ``outward`` side), or None if nothing is left (the carrier's polygons each cross
    the axis line at most once, so the part kept is one piece)."""
    return _clip_halfplane(poly, np.asarray(axis.point_mm)[:2], np.asarray(axis.outward)[:2])


def _convex_overlap(a: np.ndarray, b: np.ndarray, tol: float = 1e-9) -> bool:
    """Whether two convex plan polygons ``(k, 2)`` [mm] share area (separating axis test;
    polygons that only touch, within ``tol`` mm, do not overlap)."""
    for poly in (a, b):
        edges = np.roll(poly, -1, axis=0) - poly
        normals = np.c_[-edges[:, 1], edges[:, 0]]
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        pa, pb = a @ normals.T, b @ normals.T          # (ka, k), (kb, k) projections
        if np.any((pa.max(0) <= pb.min(0) + tol) | (pb.max(0) <= pa.min(0) + tol)):
            return False
    return True


def _min_width(poly: np.ndarray) -> float:
    """Smallest width [mm] of a convex plan polygon ``(k, 2)`` (over its edge directions,
    where the minimum of a convex polygon's width is always attained)."""
    edges = np.roll(poly, -1, axis=0) - poly
    normals = np.c_[-edges[:, 1], edges[:, 0]]
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    proj = poly @ normals.T
    return float((proj.max(0) - proj.min(0)).min())


def _inside(poly: np.ndarray, pts: np.ndarray, tol: float = 1e-6) -> bool:
    """Whether the points ``(m, 2)`` lie in the convex polygon ``(k, 2)`` (or within
    ``tol`` mm of it), whichever its orientation."""
    edges = np.roll(poly, -1, axis=0) - poly
    cross = edges[:, 0][None, :] * (pts[:, None, 1] - poly[None, :, 1]) \
        - edges[:, 1][None, :] * (pts[:, None, 0] - poly[None, :, 0])
    cross /= np.linalg.norm(edges, axis=1)[None, :]
    return bool(np.all(cross >= -tol) or np.all(cross <= tol))


def _check_vertical(design: Design) -> None:
    for m in design.mirrors:
        p = m.patch
        if abs(p.normal_[2]) > 1e-9 or abs(p.up_[2] - 1.0) > 1e-9:
            raise CadBuildError(f"mirror {m.name} is not vertical; the mounts support "
                                "vertical mirrors (unperturbed solved designs) only")


def _stop_polygon(end: np.ndarray, away: np.ndarray, n: np.ndarray, gap: float,
                  params: MountParams, t: float) -> np.ndarray:
    """Plan polygon (4, 2) of an end stop beyond the face end ``end`` (mm).

    ``away`` points along the mirror away from the glass, ``n`` is the face normal. The
    stop runs from ``gap`` to ``gap + end_stop_length_mm`` beyond the end and from
    ``end_stop_depth_mm`` in front of the glass datum back to the back plate's rear face.
    """
    a0, a1 = end + gap * away, end + (gap + params.end_stop_length_mm) * away
    front, back = t - params.end_stop_depth_mm, t + params.wall_mm
    return np.array([a0 - front * n, a1 - front * n, a1 - back * n, a0 - back * n])[:, :2]


def _blunt(poly: np.ndarray, min_wall: float) -> np.ndarray | None:
    """The convex plan polygon ``poly (k, 2)`` [mm] with every acute corner cut off, so
    that no printed wedge is thinner than ``min_wall`` mm: at a corner of interior angle
    ``a < 90 deg``, a cut square to the longer of its two edges, ``min_wall / tan(a)``
    from the corner, leaves a right-angled corner ``min_wall`` thick (and an obtuse one).
    None if nothing is left (the polygon is thinner than ``min_wall`` everywhere)."""
    q = poly
    for _ in range(2 * len(poly)):              # each cut removes one acute corner
        k = len(q)
        for i in range(k):
            e1, e2 = q[i - 1] - q[i], q[(i + 1) % k] - q[i]
            l1, l2 = np.linalg.norm(e1), np.linalg.norm(e2)
            cos_a = float(e1 @ e2) / (l1 * l2)
            if cos_a > 1e-9:                    # acute
                e = e1 / l1 if l1 >= l2 else e2 / l2
                x = min_wall * cos_a / np.sqrt(1.0 - cos_a ** 2)   # min_wall / tan(a)
                cut = _clip_halfplane(q, q[i] + x * e, e)
                if cut is None:
                    return None
                q = cut
                break
        else:
            return q
    return q  # pragma: no cover - the loop above ends by its else clause


def _angle_from(mid: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Signed angle [rad] of the plan directions ``v (..., 2)`` from the direction ``mid``."""
    return np.arctan2(mid[0] * v[..., 1] - mid[1] * v[..., 0], v @ mid)


def _in_shadow(poly: np.ndarray, glass: np.ndarray, bearings: np.ndarray,
               min_wall: float, name: str) -> np.ndarray:
    """The plan polygon ``poly (k, 2)`` [mm] (a back plate) cut to the angular shadow of
    its ``glass (4, 2)`` (face ends, then back corners) as seen from the lidar's optical
    centre (the head frame's origin), where a beam would otherwise meet it.

    At each end the tangent to the glass is the ray from the origin through the end's
    corner (front or back) farthest round from the glass's middle. If one of the lidar's
    ``bearings`` [rad] passes beyond that tangent through the plate (a beam between two
    unchained glasses), the plate is cut along the tangent and the acute wedge this leaves
    at the datum is blunted (:func:`_blunt`): the datum then stops ``min_wall / tan(a)``
    short of that glass end (``a``: the angle between the datum and the tangent), where
    the glass overhangs its bonded face. Otherwise the plate is returned unchanged."""
    mid = glass.mean(axis=0)
    beam = _angle_from(mid, np.c_[np.cos(bearings), np.sin(bearings)])
    plate = _angle_from(mid, poly)
    q = poly
    for pair in ((0, 3), (1, 2)):                     # (face, back) corner of each end
        c = glass[list(pair)]
        ang = _angle_from(mid, c)
        p = c[int(np.argmax(np.abs(ang)))]
        tangent = ang[int(np.argmax(np.abs(ang)))]
        sgn = np.sign(tangent)
        beyond = sgn * plate > sgn * tangent
        if not beyond.any():
            continue
        far = np.max(sgn * plate[beyond])
        if not np.any((sgn * beam > sgn * tangent) & (sgn * beam < far)):
            continue
        w = np.array([-p[1], p[0]])
        w = w if w @ mid >= 0 else -w
        cut = _clip_halfplane(q, np.zeros(2), w)
        blunt = None if cut is None else _blunt(cut, min_wall)
        if blunt is None:  # pragma: no cover - the plate is as long as its glass
            raise CadBuildError(f"the back plate of {name} cut to the glass's shadow (beams "
                                f"pass beside its ends) is thinner than cad.min_wall_mm")
        q = blunt
    return q


def _stop_fails(stop: np.ndarray, j: int, which: str, ends: list[np.ndarray],
                dirs: list[np.ndarray], normals: list[np.ndarray], gap: float,
                params: MountParams, t: float) -> str:
    """Why the plan polygon ``stop (k, 2)`` [mm] no longer works as the ``which`` end stop
    of mirror ``j`` ("" if it does): it must still meet the glass end over the whole
    designed contact (from ``end_stop_depth_mm`` in front of the datum back to the datum,
    at the pocket's end ``gap`` beyond the glass) and be at least ``min_wall_mm`` wide."""
    o, i = ends[j]
    end, away = (o, -dirs[j]) if which == "outer" else (i, dirs[j])
    n = normals[j]
    contact = np.array([end + gap * away - (t - params.end_stop_depth_mm) * n,
                        end + gap * away - t * n])[:, :2]
    if not _inside(stop, contact):
        return (f"no longer meets the glass end over cad.end_stop_depth_mm = "
                f"{params.end_stop_depth_mm:g} mm")
    width = _min_width(stop)
    if width < params.min_wall_mm:
        return f"is {width:.2f} mm thin (< cad.min_wall_mm = {params.min_wall_mm:g} mm)"
    return ""


def _stop_beside(stop: np.ndarray, j: int, which: str, k: int, ms: list[Any],
                 ends: list[np.ndarray], dirs: list[np.ndarray], normals: list[np.ndarray],
                 gap: float, params: MountParams, t: float) -> np.ndarray:
    """The ``which`` end stop of mirror ``j`` (plan polygon ``stop (4, 2)``, mm) cut back so
    that it clears the glass of mirror ``k`` by the pocket play ``gap``.

    Two cuts are tried, the first that leaves a working stop (:func:`_stop_fails`) wins:

    1. at ``k``'s nearer glass end (``gap`` beyond it): the ends face each other across a
       gap too short for two free stops, and what is left is one web between the two
       pockets that holds both glass ends (``k``'s own stop, cut the same way, is the
       same web);
    2. at ``k``'s face plane (``gap`` in front of it): the end of ``j`` overhangs ``k``'s
       glass in plan (unchained mirrors whose ends overlap as seen from the lidar, e.g.
       the paper's L2 tip in front of L1's inner end). The stop then stands in front of
       the lower part of ``k``'s glass, below the beam band (it is no taller than any
       stop), a lip that also keeps that glass's bottom in its pocket, which it enters
       from above.

    Raises :class:`CadBuildError` naming both mirrors if neither cut leaves a stop.
    """
    ok, ik = ends[k]
    nk = normals[k]
    cands = []
    for end_k, out_k in ((ok, -dirs[k]), (ik, dirs[k])):
        cands.append(((end_k + gap * out_k)[:2], out_k[:2]))    # beyond k's end
    cands.append(((ok + gap * nk)[:2], nk[:2]))                  # in front of k's face
    reasons = []
    for p0, w in cands:
        q = _clip_halfplane(stop, p0, w)
        if q is None:
            reasons.append("nothing is left")
            continue
        q = _blunt(q, params.min_wall_mm)
        if q is None:
            reasons.append(f"is thinner than cad.min_wall_mm = {params.min_wall_mm:g} mm")
            continue
        why = _stop_fails(q, j, which, ends, dirs, normals, gap, params, t)
        if not why:
            return q
        reasons.append(why)
    raise CadBuildError(
        f"the end stop at the {which} end of {ms[j].name} runs into glass_{ms[k].name} and "
        f"cannot be cut back to clear it (beyond its ends: {reasons[0]} / {reasons[1]}; in "
        f"front of its face: {reasons[2]}): the mirrors are too close; use a smaller "
        f"cad.end_stop_length_mm ({params.end_stop_length_mm:g} mm) or "
        "cad.pocket_clearance_mm, or move the mirrors apart")


def side_layouts(design: Design, params: MountParams) -> dict[str, SideLayout]:
    """Plan-view layout of each side carrier (see the module docstring for the axis rule)."""
    from scipy.spatial import ConvexHull

    _check_vertical(design)
    t = float(mm_from_m(design.spec.mirror.glass_thickness_m))
    w = params.wall_mm
    gap = params.pocket_clearance_mm / 2          # length play at each end of a pocket
    half_h = float(mm_from_m(design.spec.mirror.glass_height_m)) / 2
    if params.end_stop_height_mm > half_h - params.beam_band_mm:
        raise ParameterError("cad.end_stop_height_mm", params.end_stop_height_mm,
                             f"<= mirror.glass_height/2 - cad.beam_band_mm = "
                             f"{half_h - params.beam_band_mm:g} mm (the stops stay below the beams)")
    if params.end_stop_depth_mm >= t:
        raise ParameterError("cad.end_stop_depth_mm", params.end_stop_depth_mm,
                             f"< mirror.glass_thickness = {t:g} mm (the stops stay behind the "
                             "mirror's face plane; a flush stop would be a second face in it)")
    axes = {sd: HingeAxis.from_lift_axis(ax) for sd, ax in side_lift_axes(design).items()}
    out: dict[str, SideLayout] = {}
    for side in ("L", "R"):
        ms = sorted((m for m in design.mirrors if m.side == side), key=lambda m: m.index)
        if not ms:
            continue
        ends = [mm_from_m(face_ends(m.patch)) for m in ms]
        normals = [np.asarray(m.patch.normal_, float) for m in ms]
        dirs = [unit(i - o) for o, i in ends]
        chained = all(np.linalg.norm(ends[j][1] - ends[j + 1][0]) < 1e-6
                      for j in range(len(ms) - 1))
        # concave joints only (the back offsets of a convex joint would overlap)
        for j in range(len(ms) - 1):
            turn = np.cross(dirs[j], dirs[j + 1])[2]
            towards_lidar = np.cross(dirs[j], normals[j])[2]
            if turn * towards_lidar < -1e-12:
                chained = False
        # every pocket: the glass plus `gap` at each end, at the datum (depth t)
        los = [o - gap * d for (o, _), d in zip(ends, dirs, strict=True)]
        his = [i + gap * d for (_, i), d in zip(ends, dirs, strict=True)]
        fronts = [p for o, i in ends for p in (o, i)] + los + his
        stops: list[np.ndarray] = []
        stop_ends: list[tuple[str, str]] = []
        trimmed: dict[int, str] = {}     # stop index -> the neighbour glass it was cut to
        glass_plans = [np.array([o, i, i - t * n, o - t * n])[:, :2]
                       for (o, i), n in zip(ends, normals, strict=True)]
        if chained:
            for j in range(len(ms) - 1):
                # the joint face (datum end of j to datum start of j + 1) must still run
                # inwards: the wedge between the glass ends holds gap < t tan(angle / 2)
                ang = float(np.arccos(np.clip(dirs[j] @ dirs[j + 1], -1.0, 1.0)))
                p1, p2 = his[j] - t * normals[j], los[j + 1] - t * normals[j + 1]
                if (p2 - p1) @ (dirs[j] + dirs[j + 1]) <= 1e-9:
                    raise ParameterError(
                        "cad.pocket_clearance_mm", params.pocket_clearance_mm,
                        f"< {2 * t * np.tan(ang / 2):.3g} mm at the {ms[j].name}/{ms[j + 1].name} "
                        "joint (2 x glass thickness x tan(joint angle / 2))")
            inner, outer = [], []
            for j in range(len(ms)):
                n = normals[j]
                inner += [los[j] - t * n, his[j] - t * n]
                outer += [los[j] - (t + w) * n, his[j] - (t + w) * n]
            polys: tuple[np.ndarray, ...] = (np.array(inner + outer[::-1])[:, :2],)
            free = [(0, "outer"), (len(ms) - 1, "inner")]
        else:
            # each back plate is cut at both ends to its glass's shadow as seen from
            # the lidar: unchained glass leaves beams through the gaps between them,
            # which must not graze a plate standing out beyond the glass end
            bearings = design.lidar.bearing_from_step(design.lidar.steps)
            polys = tuple(_in_shadow(np.array([lo - t * n, hi - t * n, hi - (t + w) * n,
                                               lo - (t + w) * n])[:, :2], gp, bearings,
                                     params.min_wall_mm, m.name)
                          for lo, hi, n, gp, m in zip(los, his, normals, glass_plans, ms,
                                                      strict=True))
            free = [(j, e) for j in range(len(ms)) for e in ("outer", "inner")]
        for j, which in free:
            o, i = ends[j]
            end, away = (o, -dirs[j]) if which == "outer" else (i, dirs[j])
            stop = _stop_polygon(end, away, normals[j], gap, params, t)
            # close unchained neighbours: a stop that would run into another glass of
            # the side is cut back to that glass (see _stop_beside)
            for k in range(len(ms)):
                if k != j and _convex_overlap(stop, glass_plans[k]):
                    stop = _stop_beside(stop, j, which, k, ms, ends, dirs, normals,
                                        gap, params, t)
                    trimmed[len(stops)] = ms[k].name
            stops.append(stop)
            stop_ends.append((ms[j].name, which))
        # the hinge axis is the side's lift axis (nodlidar.hinge, from the faces alone);
        # the carrier conforms to it: material lidar-ward of it (the end stops' front
        # corners beyond an end of a mirror that is not parallel to the chord) is cut
        # away, so that the whole carrier lies behind the axis and stays below it lifted
        axis = axes[side]
        a0, c, wdir = (np.asarray(axis.point_mm), np.asarray(axis.direction),
                       np.asarray(axis.outward))
        polys = tuple(q for q in (_clip_behind(poly, axis) for poly in polys) if q is not None)
        kept = [(q, se, trimmed.get(n)) for n, (q, se) in enumerate(
                    (_clip_behind(sp, axis), se) for sp, se in zip(stops, stop_ends, strict=True))
                if q is not None]
        stops, stop_ends = [q for q, _, _ in kept], [se for _, se, _ in kept]
        stop_beside = tuple(b for _, _, b in kept)
        for q, (mname, which), beside in kept:
            if beside is not None:
                # the axis clip must not have cut away what the trimmed stop holds
                j = [m.name for m in ms].index(mname)
                why = _stop_fails(q, j, which, ends, dirs, normals, gap, params, t)
                if why:
                    raise CadBuildError(
                        f"the end stop at the {which} end of {mname}, cut back to clear "
                        f"glass_{beside}, {why} behind the hinge axis")
        fronts = [f for f in fronts if (f[:2] - a0[:2]) @ wdir[:2] >= -1e-9]
        pts = np.vstack([*polys, *stops, np.array(fronts)[:, :2]])
        u = (pts - a0[:2]) @ c[:2]
        ax_pts = np.array([a0[:2] + u.min() * c[:2], a0[:2] + u.max() * c[:2]])
        allp = np.vstack([pts, ax_pts])
        hull = allp[ConvexHull(allp).vertices]
        out[side] = SideLayout(side=side, mirror_names=tuple(m.name for m in ms), axis=axis,
                               back_polygons=polys, skirt_polygon=hull, u_lo=float(u.min()),
                               u_hi=float(u.max()), chained=chained, stop_polygons=tuple(stops),
                               stop_ends=tuple(stop_ends),
                               stop_beside=stop_beside if any(stop_beside) else ())
    return out


def hinge_axes(design: Design, params: MountParams | None = None) -> dict[str, HingeAxis]:
    """The hinge axis of each side carrier (mm), keyed by side."""
    params = params or MountParams()
    return {s: lay.axis for s, lay in side_layouts(design, params).items()}


def lift_transform(axis: HingeAxis, state: str) -> tuple[np.ndarray, np.ndarray]:
    """Rigid motion ``p -> R p + t`` (mm) of a side's carrier in ``state``."""
    if state not in STATES:
        raise ParameterError("state", state, " or ".join(STATES))
    if state == "deployed":
        return np.eye(3), np.zeros(3)
    R = matrix_from_axis_angle(np.asarray(axis.direction), axis.lift_rad)
    p = np.asarray(axis.point_mm)
    return R, p - R @ p


def mirror_face_poses(design: Design, params: MountParams | None = None
                      ) -> dict[str, dict[str, dict[str, Any]]]:
    """Pose of every mirror face in both states: ``{name: {state: {...}}}``.

    Each pose has ``origin_mm`` (the patch origin), ``normal`` (unit, towards the lidar
    when deployed), ``along``, ``up`` and ``corners_mm`` (4 x 3, order of
    :meth:`~nodlidar.geometry.MirrorPatch.corners`).
    """
    params = params or MountParams()
    axes = hinge_axes(design, params)
    out: dict[str, dict[str, dict[str, Any]]] = {}
    for m in design.mirrors:
        p = m.patch
        out[m.name] = {}
        for state in STATES:
            R, tr = lift_transform(axes[m.side], state)
            out[m.name][state] = {
                "origin_mm": (R @ mm_from_m(p.origin_) + tr).tolist(),
                "normal": (R @ p.normal_).tolist(),
                "along": (R @ p.along_).tolist(),
                "up": (R @ p.up_).tolist(),
                "corners_mm": (mm_from_m(p.corners()) @ R.T + tr).tolist(),
            }
    return out


# ---------------------------------------------------------------------------------------
# solids (cadquery)


@dataclass(frozen=True, eq=False)
class Part:
    """One part of the mount assembly (shape in the deployed state, head frame, mm)."""

    name: str
    kind: str                  # "printable" or "reference"
    shape: Any                 # cq.Shape
    side: str | None = None    # moves with that side's carrier
    color: tuple[float, float, float, float] = (0.7, 0.7, 0.7, 1.0)
    description: str = ""


@dataclass(frozen=True, eq=False)
class MountModel:
    """All parts of one design's mounts plus the layout they came from."""

    design: Any
    params: MountParams
    layouts: dict[str, SideLayout]
    parts: tuple[Part, ...]
    extras: dict[str, Any] = field(default_factory=dict)

    def part(self, name: str) -> Part:
        for p in self.parts:
            if p.name == name:
                return p
        raise KeyError(name)

    @property
    def axes(self) -> dict[str, HingeAxis]:
        return {s: lay.axis for s, lay in self.layouts.items()}


def _cq():
    try:
        import cadquery as cq  # noqa: TID251 (lazy: the one place mounts import it)
    except ImportError as exc:  # pragma: no cover - cadquery is a dependency
        raise CadBuildError(f"CAD export needs cadquery ({exc})") from None
    return cq


def _prism(cq, poly_xy: np.ndarray, z0: float, z1: float):
    """Vertical prism over a plan polygon ``(n, 2)`` from ``z0`` to ``z1`` (mm).

    The steps of ``cq.Workplane("XY", origin=(0, 0, z0)).polyline(pts).close()
    .extrude(z1 - z0).val()`` made directly on the shapes (the same OCCT calls with the
    same arguments, so the same solid), without the Workplane objects whose Python
    bookkeeping was half of the part build's time outside the booleans (issue 16).
    """
    plane = cq.Plane.named("XY", origin=(0, 0, float(z0)))
    pts = [plane.toWorldCoords(tuple(map(float, p))) for p in poly_xy]
    edges = [cq.Edge.makeLine(a, b) for a, b in zip(pts[:-1], pts[1:], strict=True)]
    # close(): from the last edge's end to the first edge's start, through plane coordinates
    end = plane.toLocalCoords(edges[-1].endPoint())
    start = plane.toLocalCoords(edges[0].startPoint())
    if end.sub(start).Length > 1e-6:
        edges.append(cq.Edge.makeLine(plane.toWorldCoords(end), plane.toWorldCoords(start)))
    face = cq.Face.makeFromWires(cq.Wire.assembleEdges(edges), []).Faces()[0]
    solid = cq.Solid.extrudeLinear(face, plane.zDir.multiply(float(z1 - z0)), taper=0.0)
    # extrude(): the solid fused with no base (a one-solid compound gives the solid back), cleaned
    return cq.Compound.makeCompound([solid]).fuse().clean()


def _axis_box(cq, ax: HingeAxis, u: tuple[float, float], e: tuple[float, float],
              z: tuple[float, float]):
    """Box in the axis frame (u along the axis, e outward, z up; z absolute, mm)."""
    a0 = np.asarray(ax.point_mm)
    c, w = np.asarray(ax.direction), np.asarray(ax.outward)
    corners = [a0[:2] + uu * c[:2] + ee * w[:2] for uu, ee in
               ((u[0], e[0]), (u[1], e[0]), (u[1], e[1]), (u[0], e[1]))]
    return _prism(cq, np.array(corners), z[0], z[1])


def _axis_cyl(cq, ax: HingeAxis, radius: float, u0: float, u1: float,
              offset_e: float = 0.0, offset_z: float = 0.0):
    """Cylinder coaxial (or parallel, offset in e/z) to the hinge axis from u0 to u1 (mm)."""
    a0 = np.asarray(ax.point_mm)
    c, w = np.asarray(ax.direction), np.asarray(ax.outward)
    base = a0 + u0 * c + offset_e * w + offset_z * EZ
    return cq.Solid.makeCylinder(float(radius), float(u1 - u0), cq.Vector(*map(float, base)),
                                 cq.Vector(*map(float, c)))


def _vcyl(cq, xy, radius: float, z0: float, z1: float):
    return cq.Solid.makeCylinder(float(radius), float(z1 - z0),
                                 cq.Vector(float(xy[0]), float(xy[1]), float(z0)),
                                 cq.Vector(0, 0, 1))


def _fuse(shapes):
    first, *rest = shapes
    return first.fuse(*rest).clean() if rest else first


def _single_solid(cq, shape, name: str):
    solids = shape.Solids()
    if len(solids) != 1:
        raise CadBuildError(f"part {name} came out as {len(solids)} solids; the parameters "
                            "leave pieces unconnected")
    s = solids[0]
    if not s.isValid():
        raise CadBuildError(f"part {name} is not a valid solid (OCCT check failed)")
    return s


def build_mounts(design: Design, params: MountParams | None = None) -> MountModel:
    """Build every part of the mounts for ``design`` (deployed state, head frame, mm).

    Raises
    ------
    ParameterError
        A fabrication parameter does not fit this design (the message names it).
    CadBuildError
        The geometry cannot be built (e.g. the servo does not fit under the hinge).
    """
    cq = _cq()
    params = params or MountParams()
    P = params
    spec = design.spec
    lidar = design.lidar
    layouts = side_layouts(design, P)
    hinge_z = float(mm_from_m(spec.mirror.hinge_z_m))
    z_min = float(mm_from_m(-spec.mirror.glass_height_m / 2))
    z_max = -z_min
    t_glass = float(mm_from_m(spec.mirror.glass_thickness_m))
    hw = float(mm_from_m(lidar.housing_half_width_m))
    sph = float(mm_from_m(lidar.scan_plane_height_m))
    z_base = -sph                       # top of the base plate = lidar housing base
    z_plate = z_base - P.base_thickness_mm
    r_boss = P.hinge_boss_radius_mm
    r_pin = P.hinge_bore_mm / 2
    z_bot = hinge_z - r_boss            # carrier bottom
    if hinge_z + r_boss > -P.beam_band_mm:
        raise ParameterError("cad.hinge_boss_radius_mm", P.hinge_boss_radius_mm,
                             f"< |mirror.hinge_z| - beam_band_mm = {-hinge_z - P.beam_band_mm:g} "
                             "(the lifted carrier must stay below the beams)")
    if z_bot - z_base < P.clearance_mm:
        raise CadBuildError(f"the hinge tube (bottom at {z_bot:.1f} mm) does not clear the base "
                            f"plate (top at {z_base:.1f} mm): lower mirror.hinge_z_m less or use a "
                            "smaller cad.hinge_boss_radius_mm")
    s_lidar = P.lidar_hole_spacing_mm
    need = s_lidar / 2 + P.clearance_dia_mm(P.lidar_screw) / 2 + P.min_wall_mm
    if need > hw:
        raise ParameterError("cad.lidar_hole_spacing_mm", s_lidar,
                             f"<= {2 * (hw - P.clearance_dia_mm(P.lidar_screw) / 2 - P.min_wall_mm):.3g} "
                             f"mm (holes under the {lidar.name} housing)")

    parts: list[Part] = []
    extras: dict[str, Any] = {"z_base_mm": z_base, "z_plate_mm": z_plate, "hinge_z_mm": hinge_z}

    # -- glass (reference) ---------------------------------------------------------
    for m in design.mirrors:
        c4 = mm_from_m(m.patch.corners())
        n = np.asarray(m.patch.normal_)
        a, b = c4[0], c4[1]                      # (s_min, z_min), (s_max, z_min)
        poly = np.array([a, b, b - t_glass * n, a - t_glass * n])[:, :2]
        g = _prism(cq, poly, c4[0, 2], c4[2, 2])
        parts.append(Part(f"glass_{m.name}", "reference", _single_solid(cq, g, m.name),
                          side=m.side, color=(0.55, 0.8, 0.95, 0.6),
                          description=f"mirror glass {m.name}: front face = solved patch"))

    glass_parts = list(parts)

    # -- carriers ------------------------------------------------------------------
    neck = P.clearance_mm + 3.0                  # room for the horn screws behind the flange
    base_extra: list[Any] = []
    base_cuts: list[Any] = []
    hull_pts: list[np.ndarray] = []
    for side, lay in layouts.items():
        ax = lay.axis
        solids = [_prism(cq, lay.skirt_polygon, z_bot, z_min)]
        solids += [_prism(cq, poly, z_bot, z_max) for poly in lay.back_polygons]
        stops = [_prism(cq, poly, z_bot, z_min + P.end_stop_height_mm)
                 for poly in lay.stop_polygons]
        for stop, (mname, which) in zip(stops, lay.stop_ends, strict=True):
            for g in (g for g in glass_parts if g.side == side):
                if stop.intersect(g.shape).Volume() > 1e-6:
                    raise CadBuildError(
                        f"the end stop at the {which} end of {mname} runs into {g.name}: the "
                        f"mirrors are too close; use a smaller cad.end_stop_length_mm "
                        f"({P.end_stop_length_mm:g} mm) or cad.pocket_clearance_mm")
        solids += stops
        u_fl0 = lay.u_lo - neck - P.flange_thickness_mm
        solids.append(_axis_cyl(cq, ax, r_boss, u_fl0, lay.u_hi))
        solids.append(_axis_cyl(cq, ax, P.horn_radius_mm, u_fl0, u_fl0 + P.flange_thickness_mm))
        body = _fuse(solids)
        cuts = [_axis_cyl(cq, ax, r_pin, u_fl0 - 1.0, lay.u_hi + 1.0)]
        r_h = P.clearance_dia_mm(P.horn_screw) / 2
        for k in range(4):
            ang = np.pi / 4 + k * np.pi / 2
            cuts.append(_axis_cyl(cq, ax, r_h, u_fl0 - 1.0, u_fl0 + P.flange_thickness_mm + 1.0,
                                  offset_e=P.horn_bolt_circle_mm / 2 * np.cos(ang),
                                  offset_z=P.horn_bolt_circle_mm / 2 * np.sin(ang)))
        body = body.cut(*cuts).clean()
        parts.append(Part(f"carrier_{side}", "printable", _single_solid(cq, body, f"carrier_{side}"),
                          side=side, color=(0.95, 0.55, 0.2, 1.0),
                          description=f"{side} mirror carrier ({', '.join(lay.mirror_names)}), "
                                      "turns about its hinge axis"))

        # -- servo (reference) and its cradle / the front pillar (base) -------------
        hb1 = u_fl0 - P.horn_thickness_mm        # servo body face at the horn side
        hb0 = hb1 - P.servo_depth_mm
        off, L, W, sc = P.servo_shaft_offset_mm, P.servo_length_mm, P.servo_width_mm, P.servo_clearance_mm
        servo = _fuse([_axis_box(cq, ax, (hb0, hb1), (-off, L - off), (hinge_z - W / 2, hinge_z + W / 2)),
                       _axis_cyl(cq, ax, P.horn_radius_mm, hb1, u_fl0)])
        parts.append(Part(f"servo_{side}", "reference", _single_solid(cq, servo, f"servo_{side}"),
                          color=(0.2, 0.2, 0.2, 1.0),
                          description="lift servo envelope (body + horn), XL430-size by default"))
        wl = P.wall_mm
        pocket_bot = hinge_z - W / 2 - sc
        if pocket_bot - z_plate < P.min_wall_mm:
            raise CadBuildError(
                f"the {side} servo does not fit between the base plate and the hinge axis "
                f"(cradle floor {pocket_bot - z_plate:.2f} mm < min wall {P.min_wall_mm} mm); "
                "raise mirror.hinge_z_m or use a smaller servo")
        cu = (hb0 - sc - wl, hb1)
        ce = (-off - sc - wl, L - off + sc + wl)
        cradle = _axis_box(cq, ax, cu, ce, (z_plate, max(hinge_z, pocket_bot + P.min_wall_mm)))
        base_extra.append(cradle)
        base_cuts.append(_axis_box(cq, ax, (hb0 - sc, hb1 + 1.0), (-off - sc, L - off + sc),
                                   (pocket_bot, hinge_z + 100.0)))
        a0, c, wv = (np.asarray(ax.point_mm), np.asarray(ax.direction), np.asarray(ax.outward))
        for frac in (0.3, 0.7):
            ee = ce[0] + frac * (ce[1] - ce[0])
            xy = a0[:2] + (hb0 + hb1) / 2 * c[:2] + ee * wv[:2]
            base_cuts.append(_vcyl(cq, xy, P.clearance_dia_mm(P.servo_screw) / 2, z_plate - 1,
                                   pocket_bot + 1))
        pu = (lay.u_hi + P.clearance_mm, lay.u_hi + P.clearance_mm + P.pillar_thickness_mm)
        base_extra.append(_axis_box(cq, ax, pu, (-r_boss, r_boss), (z_plate, hinge_z)))
        base_extra.append(_axis_cyl(cq, ax, r_boss, pu[0], pu[1]))
        base_extra.append(_axis_box(cq, ax, pu, (-(r_boss + P.clearance_mm + wl), r_boss),
                                    (z_plate, z_base)))
        base_cuts.append(_axis_cyl(cq, ax, r_pin, pu[0] - 1.0, pu[1] + 1.0))
        e_in = -(r_boss + P.clearance_mm)
        for uu in (cu[0], pu[1]):
            hull_pts.append(a0[:2] + uu * c[:2] + e_in * wv[:2])
        extras[f"pillar_{side}_u_mm"] = pu
        extras[f"cradle_{side}_u_mm"] = cu

    # -- base (printable) ------------------------------------------------------------
    from scipy.spatial import ConvexHull

    h = hw + P.base_margin_mm
    sq = np.array([[h, h], [-h, h], [-h, -h], [h, -h]])
    allp = np.vstack([sq, *hull_pts]) if hull_pts else sq
    plate_poly = allp[ConvexHull(allp).vertices]
    base = _fuse([_prism(cq, plate_poly, z_plate, z_base), *base_extra])
    r_l = P.clearance_dia_mm(P.lidar_screw) / 2
    r_b = P.clearance_dia_mm(P.base_screw) / 2
    for sx in (-1, 1):
        for sy in (-1, 1):
            base_cuts.append(_vcyl(cq, (sx * s_lidar / 2, sy * s_lidar / 2), r_l, z_plate - 1, z_base + 1))
            hb = hw + P.base_margin_mm / 2
            base_cuts.append(_vcyl(cq, (sx * hb, sy * hb), r_b, z_plate - 1, z_base + 1))
    base = base.cut(*base_cuts).clean()
    parts.insert(0, Part("base", "printable", _single_solid(cq, base, "base"),
                         color=(0.3, 0.45, 0.85, 1.0),
                         description="base: lidar seat, hinge pillars, servo cradles"))

    # -- lidar envelope (reference) ----------------------------------------------------
    top = float(mm_from_m(lidar.housing_height_m)) - sph
    body_top = -P.beam_band_mm - 2.0
    lid = _fuse([_prism(cq, sq * hw / h, z_base, body_top),
                 _vcyl(cq, (0, 0), float(mm_from_m(lidar.head_radius_m)), body_top, top)])
    parts.append(Part("lidar", "reference", _single_solid(cq, lid, "lidar"),
                      color=(0.1, 0.1, 0.1, 1.0),
                      description=f"{lidar.name} envelope (square body, round optical head)"))
    return MountModel(design=design, params=P, layouts=layouts, parts=tuple(parts), extras=extras)


def part_shapes(model: MountModel, state: str) -> dict[str, Any]:
    """Every part's shape in ``state`` (carriers, their glass: rotated about the hinge)."""
    if state not in STATES:
        raise ParameterError("state", state, " or ".join(STATES))
    out = {}
    for p in model.parts:
        if state == "lifted" and p.side is not None:
            ax = model.layouts[p.side].axis
            a0 = np.asarray(ax.point_mm)
            a1 = a0 + np.asarray(ax.direction)
            out[p.name] = p.shape.rotate(tuple(map(float, a0)), tuple(map(float, a1)),
                                         float(np.degrees(ax.lift_rad)))
        else:
            out[p.name] = p.shape
    return out


def build_assembly(model: MountModel, state: str) -> cq.Assembly:
    """A named, coloured :class:`cadquery.Assembly` of all parts in ``state``."""
    cq = _cq()
    shapes = part_shapes(model, state)
    assy = cq.Assembly(name=f"{model.design.spec.name}_{state}")
    for p in model.parts:
        assy.add(shapes[p.name], name=p.name, color=cq.Color(*p.color))
    return assy
