"""Printable pieces of the mounts: split to fit the printer bed, each in its print orientation.

:func:`print_pieces` takes the printable parts of a :class:`~nodlidar.cad.mounts.MountModel`
(assembly coordinates, mm) and returns :class:`PrintPiece` objects:

* A part that does not fit the bed (``cad.bed_x_mm`` x ``cad.bed_y_mm``, in any rotation
  about the vertical) is cut in two, recursively, across its longest extent. The cut is
  a **half-lap joint**: the piece on one side keeps the lower half of the plate for
  ``cad.lap_mm`` beyond the cut, the other the upper half, so the two overlap by
  ``lap_mm`` and the outside of the part is unchanged. The cut position is chosen where
  the cross-section is smallest (the plain plate, away from pillars and cradles). Each
  lap holds two alignment dowels (``cad.dowel_mm``, holes at the dowel diameter plus
  ``cad.dowel_fit_mm``) and two screws (``cad.joint_screw``, clearance holes) through both
  halves. Cuts are only made through a flat plate of at least ``2 * min_wall_mm``; a part
  whose smallest section is not such a plate is refused with the reason.
* Every piece is turned so that its largest flat face on which it can rest (a planar face
  whose plane has all of the piece on one side) faces down, rotated about the vertical to
  the smallest footprint that fits the bed, and moved to the bed corner (min x = min y =
  min z = 0). :attr:`PrintPiece.to_print` maps assembly to print coordinates.

:func:`bill_of_materials` lists what to buy besides the printed pieces: glass (per
mirror, with the pocket clearance), servos, screws, dowels. It needs no cadquery.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..errors import ParameterError
from ..geometry import matrix_from_axis_angle
from .params import MountParams

__all__ = ["PrintPiece", "print_pieces", "print_orientation", "bill_of_materials",
           "fits_bed"]


@dataclass(frozen=True, eq=False)
class PrintPiece:
    """One printable piece.

    Attributes
    ----------
    name : str
        ``base_1``, ``carrier_L``...: the part name, numbered when the part was split.
    part : str
        The part it was cut from.
    shape : cq.Shape
        The piece in assembly coordinates (head frame, deployed, mm).
    printed : cq.Shape
        The piece in print orientation (on the bed: min x = min y = min z = 0).
    to_print : (4, 4) float
        Rigid transform from assembly to print coordinates (mm).
    size_mm : (3,) float
        Extent of :attr:`printed` along x, y, z.
    joints : list of dict
        The half-lap joints this piece takes part in (with the other piece's name).
    """

    name: str
    part: str
    shape: Any
    printed: Any
    to_print: np.ndarray
    size_mm: np.ndarray
    joints: list[dict[str, Any]] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "part": self.part,
                "print_size_mm": [float(x) for x in self.size_mm],
                "to_print": self.to_print.tolist(), "joints": self.joints}


def fits_bed(w: float, d: float, params: MountParams) -> bool:
    """Whether a ``w`` x ``d`` mm footprint fits the bed in one of its two orientations."""
    bx, by = params.bed_x_mm, params.bed_y_mm
    return (w <= bx and d <= by) or (w <= by and d <= bx)


def _points(shape, tol: float = 0.2) -> np.ndarray:
    """Surface points of a shape (its tessellation's vertices), ``(n, 3)`` mm.

    The vertices of ``shape.tessellate(tol)`` in the same order and bits, read straight
    from each face's triangulation: no cadquery ``Vector`` per vertex (that loop was most
    of ``nodlidar cad``'s print-piece time, issue 16); a face with a location is moved by
    OCCT exactly as ``tessellate`` moves it.
    """
    from OCP.BRep import BRep_Tool
    from OCP.TopLoc import TopLoc_Location

    shape.mesh(tol)  # what tessellate() meshes (angular tolerance 0.1)
    out = []
    for f in shape.Faces():
        loc = TopLoc_Location()
        poly = BRep_Tool.Triangulation_s(f.wrapped, loc)
        if poly is None:
            continue
        nodes = (poly.Node(i) for i in range(1, poly.NbNodes() + 1))
        if not loc.IsIdentity():
            trsf = loc.Transformation()
            nodes = (p.Transformed(trsf) for p in nodes)
        out += [(p.X(), p.Y(), p.Z()) for p in nodes]
    return np.array(out)


def _rot_to(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rotation (3, 3) taking unit vector ``a`` to unit vector ``b``."""
    axis = np.cross(a, b)
    s, c = np.linalg.norm(axis), float(a @ b)
    if s < 1e-12:
        if c > 0:
            return np.eye(3)
        perp = np.cross(a, [1.0, 0, 0]) if abs(a[0]) < 0.9 else np.cross(a, [0, 1.0, 0])
        return matrix_from_axis_angle(perp, np.pi)
    return matrix_from_axis_angle(axis, float(np.arctan2(s, c)))


def _transform(shape, T: np.ndarray):
    """``shape`` moved rigidly by the 4x4 ``T`` (rotation re-orthonormalised for OCCT)."""
    import cadquery as cq  # noqa: TID251 (lazy: CAD only)
    from OCP.BRepBuilderAPI import BRepBuilderAPI_Transform
    from OCP.gp import gp_Trsf

    u, _, vt = np.linalg.svd(T[:3, :3])
    R = u @ vt
    tr = gp_Trsf()
    tr.SetValues(*(float(x) for row in np.c_[R, T[:3, 3]] for x in row))
    return cq.Shape.cast(BRepBuilderAPI_Transform(shape.wrapped, tr, True).Shape())


def _resting_faces(shape, pts: np.ndarray) -> list[tuple[float, np.ndarray, float]]:
    """Planar faces the shape can rest on: ``(area, outward normal, plane offset)``, largest first."""
    out = []
    span = float(np.ptp(pts, axis=0).max())
    for f in shape.Faces():
        if f.geomType() != "PLANE":
            continue
        n = np.array(f.normalAt().toTuple())
        c = np.array(f.Center().toTuple())
        # a supporting plane: every point of the piece on the inner side (tessellation
        # chords may poke out by the deflection only)
        if np.max(pts @ n - c @ n) <= 1e-4 * span + 0.05:
            out.append((float(f.Area()), n, float(c @ n)))
    out.sort(key=lambda x: -x[0])
    return out


def _min_rect_angle(xy: np.ndarray, params: MountParams) -> tuple[float, float, float]:
    """Rotation about z [rad] giving the smallest-area footprint that fits the bed, if any.

    Candidate angles: the directions of the convex hull's edges (a minimum-area rectangle
    has a side along one) and every degree. Returns ``(angle, w, d)``; prefers fitting.

    The choice does not hang on rounding: a footprint turned by 180 deg is the same
    rectangle (opposite hull edges give both), so the angle is taken modulo pi, in
    [-pi/4, 3 pi/4); and areas within 1e-9 (relative) of the smallest are a tie, broken by
    the smaller angle. Before, the two turns of one rectangle differed in area by the
    last bits, and another machine's OCCT (1e-8 noise in the solid) printed the optimal
    design's base turned by 180 deg.
    """
    from scipy.spatial import ConvexHull

    hull = xy[ConvexHull(xy).vertices]
    e = np.diff(np.vstack([hull, hull[:1]]), axis=0)
    cands = np.concatenate([-np.arctan2(e[:, 1], e[:, 0]), np.radians(np.arange(0, 180))])
    rows = []
    for a in cands:
        c, s = np.cos(a), np.sin(a)
        p = hull @ np.array([[c, s], [-s, c]])
        w, d = np.ptp(p[:, 0]), np.ptp(p[:, 1])
        if w < d:  # the long side along the bed's x
            a, w, d = a + np.pi / 2, d, w
        a = (a + np.pi / 4) % np.pi - np.pi / 4
        rows.append((not fits_bed(w, d, params),
                     not (w <= params.bed_x_mm and d <= params.bed_y_mm),
                     float(w * d), float(a), float(w), float(d)))
    first = min(r[:3] for r in rows)
    ties = [r for r in rows if r[:2] == first[:2] and r[2] <= first[2] * (1 + 1e-9)]
    _, _, _, a, w, d = min(ties, key=lambda r: r[3])
    return a, w, d


def print_orientation(shape: Any, params: MountParams) -> tuple[np.ndarray, Any, np.ndarray]:
    """``(T, printed, size)``: the largest resting face down, best z rotation, at the corner."""
    pts = _points(shape)
    faces = _resting_faces(shape, pts)
    if not faces:
        raise ParameterError("cad", "print orientation", "a part with a flat face to rest on")
    _, n, _ = faces[0]
    R = _rot_to(n, np.array([0.0, 0.0, -1.0]))
    q = pts @ R.T
    a, _, _ = _min_rect_angle(q[:, :2], params)
    Rz = matrix_from_axis_angle(np.array([0.0, 0.0, 1.0]), a)
    R = Rz @ R
    q = pts @ R.T
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = -q.min(axis=0)
    printed = _transform(shape, T)
    bb = printed.BoundingBox()
    return T, printed, np.array([bb.xlen, bb.ylen, bb.zlen])


def _section_area(shape, origin: np.ndarray, normal: np.ndarray, big: float) -> float:
    """Area [mm^2] of the shape's cross-section in a plane."""
    import cadquery as cq  # noqa: TID251 (lazy: CAD only)

    face = cq.Face.makePlane(big, big, cq.Vector(*map(float, origin)), cq.Vector(*map(float, normal)))
    sec = shape.intersect(face)
    return float(sum(f.Area() for f in sec.Faces()))


def _split(shape, name: str, params: MountParams
           ) -> list[tuple[Any, list[dict[str, Any]], tuple[np.ndarray, Any, np.ndarray]]]:
    """Cut ``shape`` (assembly coordinates) into pieces that fit the bed (half-lap joints).

    Returns ``(piece, joints, (T, printed, size))`` per piece: the piece in assembly
    coordinates, its joints and its :func:`print_orientation` (computed here anyway to
    decide whether it fits, so :func:`print_pieces` does not orient it a second time).
    """
    import cadquery as cq  # noqa: TID251 (lazy: CAD only)

    T, printed, size = print_orientation(shape, params)
    if fits_bed(size[0], size[1], params):
        return [(shape, [], (T, printed, size))]
    # work in the print frame of this piece: plate bottom at z = 0, long side along x
    P = params
    pts = _points(printed)
    lo, hi = pts.min(0), pts.max(0)
    big = 4 * float(np.ptp(pts, axis=0).max())
    length = hi[0] - lo[0]
    # the plate: the cross-section must be a slab from z = 0 to the plate top
    t_plate = _plate_thickness(printed)
    lap = P.lap_mm
    spans: dict[float, tuple[float, float]] = {}   # each section computed once per x
    excesses: dict[float, float] = {}

    def span(x: float) -> tuple[float, float]:
        if x not in spans:
            spans[x] = _section_span(printed, x, big, t_plate)
        return spans[x]

    def excess_at(x: float) -> float:
        """Section area [mm^2] beyond a plain slab of the plate (pillars, cradles...)."""
        if x not in excesses:
            area = _section_area(printed, np.array([x, 0, 0]), np.array([1.0, 0, 0]), big)
            y0, y1 = span(x)
            excesses[x] = area - (y1 - y0) * t_plate
        return excesses[x]

    cands = []
    for frac in np.linspace(0.3, 0.7, 9):
        c = lo[0] + frac * length
        # halves that fit the bed first, then a plain plate, then the middle (balanced)
        both_fit = (fits_bed(c - lo[0] + lap, size[1], P)
                    and fits_bed(hi[0] - c, size[1], P))
        cands.append((float(c), both_fit, float(frac)))
    c, excess = _choose_cut(cands, excess_at, lap)
    # only a plain slab of the plate may be cut: a lap through a pillar would not hold
    if t_plate < 2 * P.min_wall_mm or excess > 0.02 * length * t_plate + 1.0:
        raise ParameterError(
            "cad.bed_x_mm/bed_y_mm", (P.bed_x_mm, P.bed_y_mm),
            f"a bed that holds part {name} ({size[0]:.0f} x {size[1]:.0f} mm): it has no flat "
            f"plate of >= {2 * P.min_wall_mm:g} mm to cut with a lap joint")
    half = t_plate / 2
    keep = (cq.Solid.makeBox(big, big, big, cq.Vector(c - big, -big / 2, -big / 2))
            .fuse(cq.Solid.makeBox(lap, big, big / 2 + half, cq.Vector(c, -big / 2, -big / 2))))
    a = printed.intersect(keep).clean()
    b = printed.cut(keep).clean()
    # dowels and screws through the lap, spread along the cut where the plate is
    y0, y1 = span(c + lap / 2)
    xm = c + lap / 2
    holes = []
    kinds = ("dowel", "screw", "screw", "dowel")
    for f, kind in zip((0.15, 0.38, 0.62, 0.85), kinds, strict=True):
        y = y0 + f * (y1 - y0)
        if not (printed.isInside(cq.Vector(xm, y, half / 2))
                and printed.isInside(cq.Vector(xm, y, 1.5 * half))):
            continue
        dia = (P.dowel_mm + P.dowel_fit_mm) if kind == "dowel" else P.clearance_dia_mm(P.joint_screw)
        holes.append((kind, xm, y, dia))
    if len([h for h in holes if h[0] == "screw"]) < 1 or len([h for h in holes if h[0] == "dowel"]) < 1:
        raise ParameterError("cad.lap_mm", P.lap_mm, f"a lap across part {name} with room for "
                             "a dowel and a screw (the cut found no plate there)")
    cyl = [cq.Solid.makeCylinder(d / 2, t_plate + 2, cq.Vector(x, y, -1), cq.Vector(0, 0, 1))
           for _, x, y, d in holes]
    a = a.cut(*cyl).clean()
    b = b.cut(*cyl).clean()
    Tinv = np.linalg.inv(T)

    def to_asm(p):
        return (Tinv @ np.array([*p, 1.0]))[:3]

    # probe points in the lap's material beside each hole, one per half: a piece that
    # holds one of them takes part in the joint
    probes = [to_asm((x + sx * (d / 2 + 1.0), y, z)) for _, x, y, d in holes
              for sx in (-1, 1) for z in (half / 2, 1.5 * half)]
    joint = {"lap_mm": lap, "plate_mm": float(t_plate),
             "dowels": sum(h[0] == "dowel" for h in holes),
             "screws": sum(h[0] == "screw" for h in holes),
             "holes_mm": [[*to_asm((x, y, 0.0)).tolist(), d] for _, x, y, d in holes],
             "probes_mm": [p.tolist() for p in probes]}
    out = []
    for piece in (a, b):
        for solid in piece.Solids():
            out += [(s, j + [joint], o) for s, j, o in _split(_transform(solid, Tinv), name, params)]
    return out


def _choose_cut(cands: list[tuple[float, bool, float]], excess_at: Callable[[float], float],
                lap: float) -> tuple[float, float]:
    """The lap joint's cut ``(c, excess)`` among candidates ``(c [mm], both_fit, frac)``.

    Each candidate is judged by the sections at ``c``, ``c + lap/2`` and ``c + lap``
    (``excess_at(x)``: section area beyond a plain slab of the plate [mm^2]); the choice is
    the smallest key ``(round(max(excess, 0), 1) > 0, not both_fit, |frac - 0.5|)`` with
    ``excess`` the largest of the three, the first candidate on ties. The last two parts
    of the key need no geometry, so the candidates are visited in their order and the
    first one whose three sections are all plain slab wins: every candidate after it has a
    larger key. A candidate is out at its first section with excess (``round(max(., 0),
    1)`` is monotone, so it is > 0 for the maximum iff for one of the three). This takes
    3 sections instead of 27 when the middle is plain plate (issue 16: the sections were
    ~30 % of the paper build's export); ``excess`` is the chosen candidate's, as before.
    """
    order = sorted(((not fit, abs(frac - 0.5)), i, c) for i, (c, fit, frac) in enumerate(cands))
    chosen = None
    for _, _, cand in order:
        if all(round(max(excess_at(x), 0.0), 1) <= 0 for x in (cand, cand + lap / 2, cand + lap)):
            chosen = cand
            break
    if chosen is None:   # no plain cut: the smallest key is the first in that order
        chosen = order[0][2]
    return chosen, max(excess_at(x) for x in (chosen, chosen + lap / 2, chosen + lap))


def _plate_thickness(printed) -> float:
    """Height [mm] of the horizontal face nearest above the bed that covers most of it."""
    faces = []
    for f in printed.Faces():
        if f.geomType() != "PLANE":
            continue
        n = np.array(f.normalAt().toTuple())
        if n[2] > 1 - 1e-9:
            faces.append((f.Area(), f.Center().z))
    if not faces:
        return 0.0
    return float(max(faces)[1])


def _section_span(printed, x: float, big: float, t: float) -> tuple[float, float]:
    """y range [mm] of the plate's section at ``x`` (at half its thickness)."""
    import cadquery as cq  # noqa: TID251 (lazy: CAD only)

    edge = cq.Edge.makeLine(cq.Vector(x, -big, t / 2), cq.Vector(x, big, t / 2))
    sec = printed.intersect(edge)
    ys = [v.Y for v in sec.Vertices()]
    return (min(ys), max(ys)) if ys else (0.0, 0.0)


def print_pieces(model: Any, params: MountParams | None = None, *,
                 refused: list[dict[str, str]] | None = None) -> list[PrintPiece]:
    """Every printable part of ``model``, split to fit the bed, in print orientation.

    A part that cannot be split to fit raises :class:`ParameterError`, unless a list is
    given as ``refused``: then ``{"part", "reason"}`` is appended and the rest printed.
    """
    P = params or model.params
    out: list[PrintPiece] = []
    for part in model.parts:
        if part.kind != "printable":
            continue
        try:
            pieces = _split(part.shape, part.name, P)
        except ParameterError as exc:
            if refused is None:
                raise
            refused.append({"part": part.name, "reason": str(exc)})
            continue
        for i, (shape, joints, (T, printed, size)) in enumerate(pieces, start=1):
            name = part.name if len(pieces) == 1 else f"{part.name}_{i}"
            if not fits_bed(size[0], size[1], P):  # pragma: no cover - _split guarantees it
                raise ParameterError("cad.bed_x_mm/bed_y_mm", (P.bed_x_mm, P.bed_y_mm),
                                     f"a bed that holds {name} ({size[0]:.0f} x {size[1]:.0f} mm)")
            out.append(PrintPiece(name=name, part=part.name, shape=shape, printed=printed,
                                  to_print=T, size_mm=size, joints=joints))
    # a piece takes part in the joints whose lap material it holds
    import cadquery as cq  # noqa: TID251 (lazy: CAD only)

    for p in out:
        p.joints[:] = [j for j in p.joints
                       if any(p.shape.isInside(cq.Vector(*q)) for q in j["probes_mm"])]
    for p in out:
        for j in p.joints:
            j["pieces"] = sorted(q.name for q in out if any(k is j for k in q.joints))
    return out


def bill_of_materials(design: Any, params: MountParams, pieces: list[PrintPiece] | None = None
                      ) -> list[dict[str, Any]]:
    """What to buy: rows ``{item, spec, qty, note}`` (no cadquery needed without ``pieces``).

    Glass: one pane per mirror, the solved patch length plus the pocket clearance minus a
    cutting allowance is left to the supplier (we give the exact nominal size), height
    and thickness from ``[mirror]``. Servos: one per side carrier. Screws: base to the
    platform (4), lidar to the base (4), one hinge pin per side, horn screws (4 per side),
    servo screws (2 per side), joint screws and dowels of the split pieces.
    """
    P = params
    spec = design.spec
    rows: list[dict[str, Any]] = []
    h = spec.mirror.glass_height_m * 1000
    t = spec.mirror.glass_thickness_m * 1000
    for m in design.mirrors:
        rows.append({"item": f"glass {m.name}", "spec": f"front-surface mirror {m.length_m * 1000:.1f} "
                     f"x {h:.1f} x {t:.1f} mm", "qty": 1,
                     "note": f"pocket {m.length_m * 1000 + P.pocket_clearance_mm:.1f} mm long "
                             f"(glass slides {P.pocket_clearance_mm:g} mm)"})
    sides = sorted({m.side for m in design.mirrors})
    n = len(sides)
    rows.append({"item": "lift servo", "spec": f"Dynamixel XL430-W250 size ({P.servo_length_mm:g} x "
                 f"{P.servo_width_mm:g} x {P.servo_depth_mm:g} mm)", "qty": n,
                 "note": "one per side carrier"})
    rows.append({"item": "base screw", "spec": f"{P.base_screw} x {P.base_thickness_mm + 6:g} mm",
                 "qty": 4, "note": "base to the nodding platform"})
    rows.append({"item": "lidar screw", "spec": f"{P.lidar_screw} x {P.base_thickness_mm + 5:g} mm",
                 "qty": 4, "note": f"{spec.lidar} to the base"})
    pin_len = 2 * P.pillar_thickness_mm + 10
    rows.append({"item": "hinge pin", "spec": f"{P.hinge_pin} screw, >= {pin_len:g} mm + nut",
                 "qty": n, "note": "through the front pillar into the carrier tube"})
    rows.append({"item": "horn screw", "spec": f"{P.horn_screw} x {P.flange_thickness_mm + 4:g} mm",
                 "qty": 4 * n, "note": "carrier flange to the servo horn"})
    rows.append({"item": "servo screw", "spec": f"{P.servo_screw} x 6 mm", "qty": 2 * n,
                 "note": "servo to its cradle"})
    if pieces:
        joints = {id(j): j for p in pieces for j in p.joints}.values()
        n_s = sum(j["screws"] for j in joints)
        n_d = sum(j["dowels"] for j in joints)
        if n_s:
            plate = max(j["plate_mm"] for j in joints)
            rows.append({"item": "joint screw", "spec": f"{P.joint_screw} x {plate + 4:g} mm + nut",
                         "qty": n_s, "note": "through the half-lap joints of the split base"})
        if n_d:
            rows.append({"item": "dowel pin", "spec": f"{P.dowel_mm:g} mm x "
                         f"{max(j['plate_mm'] for j in joints):g} mm", "qty": n_d,
                         "note": "aligns the half-lap joints"})
    return rows
