"""The one hinge/lift model (nodlidar.hinge, issue 18 "Two hinge axes").

A side's mirrors sit on one carrier turned by one servo, so they turn about one axis. The
CAD (cad.mounts, numpy layout) and the simulator (sim.raycast) must lift each glass to
the same pose: checked on the glass corners and normals in both states, and on the
simulator's actual ray cast part way through a lift, for the paper build and a k = 5
build. Plus the axis rule from first principles, the lifted state's beams, and the
lifted glass's clearance from the lidar and from the other side.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from numpy.testing import assert_allclose

from nodlidar.errors import ParameterError
from nodlidar.geometry import directions_from_bearings, matrix_from_axis_angle, reflect
from nodlidar.hinge import (
    LiftAxis,
    face_ends,
    lift_fraction,
    lifted_patch,
    lifted_points,
    side_lift_axes,
)
from nodlidar.solver import solve
from nodlidar.spec import load_design

_DESIGNS = Path(__file__).resolve().parents[1] / "design"
# the chained reading of the paper (equal windows, mirrors edge to edge): the k = 5 build
# is made from it by changing the window count
PAPER = _DESIGNS / "urg04lx-paper-chained.toml"
# the paper read to its four printed numbers (the default file): unchained mirrors, L2's
# tip in front of L1
EXACT = _DESIGNS / "urg04lx-paper.toml"
# the tolerances: same glass pose to 0.01 mm / 0.01 deg
POS_TOL_MM = 0.01
ANG_TOL_DEG = 0.01


@pytest.fixture(scope="module")
def builds():
    spec = load_design(PAPER)
    return {"paper": solve(spec),
            "k5": solve(spec.replace(**{"layout.windows": 5, "layout.mirrors_per_side": 4})),
            "exact": solve(load_design(EXACT))}


@pytest.fixture(scope="module", params=["paper", "k5", "exact"])
def design(request, builds):
    return builds[request.param]


def test_exact_build_is_the_unchained_one(builds):
    """The "exact" build has unchained sides with a stop cut back in front of the
    neighbour glass (else the lift checks below prove nothing more for it)."""
    from nodlidar.cad.mounts import side_layouts
    from nodlidar.cad.params import MountParams

    lay = side_layouts(builds["exact"], MountParams())
    assert not any(lo.chained for lo in lay.values())
    assert all(any(lo.stop_beside) for lo in lay.values())


def _angle_deg(a, b):
    return math.degrees(math.acos(float(np.clip(np.dot(a, b), -1.0, 1.0))))


def test_k5_build_has_more_than_one_mirror_a_side(builds):
    """The k = 5 build really chains 4 mirrors a side (else it proves nothing more)."""
    d = builds["k5"]
    assert [m.name for m in d.mirrors] == ["L1", "L2", "L3", "L4", "R1", "R2", "R3", "R4"]


def test_cad_and_simulator_lift_each_glass_to_the_same_pose(design):
    """Each mirror lifted through the CAD's hinge (cad.mounts.mirror_face_poses, the
    carrier's pose in mm) and through the simulator's (the glass SceneSimulator casts
    against at a lift fraction): same corners to 0.01 mm and same normal to 0.01 deg,
    deployed and lifted."""
    from nodlidar.cad.mounts import mirror_face_poses
    from nodlidar.sim.raycast import SceneSimulator

    cad = mirror_face_poses(design)
    sim = SceneSimulator(design, "wall")
    for state, f in (("deployed", 0.0), ("lifted", 1.0)):
        glass = sim.mirror_patches_at(f, f)
        for m, g in zip(design.mirrors, glass, strict=True):
            pose = cad[m.name][state]
            assert_allclose(g.corners() * 1000, pose["corners_mm"], rtol=0, atol=POS_TOL_MM,
                            err_msg=f"{m.name} {state}")
            assert _angle_deg(g.normal_, pose["normal"]) < ANG_TOL_DEG, (m.name, state)
        if state == "lifted":
            # a real motion, not two copies of the deployed pose
            moved = [np.abs(g.corners() - m.patch.corners()).max()
                     for m, g in zip(design.mirrors, glass, strict=True)]
            assert min(moved) > 5e-3


def test_simulator_casts_against_the_cad_hinge_part_way_up(design):
    """The ray cast itself (not just the pose accessor): part way through a lift, every
    beam the simulator reflects starts again on the glass the CAD's hinge axis (HingeAxis,
    mm) turns by ``f * lift_rad``, inside its rectangle, and leaves with the exact
    reflection about that glass's normal. A mirror turned about its own hinge line (the
    old model, up to 16 mm off) would put the hits millimetres off that plane."""
    from nodlidar.cad.mounts import hinge_axes, mirror_face_poses
    from nodlidar.sim.raycast import SceneSimulator

    f = 0.3  # 27 deg: the glass still crosses the scan plane
    axes = hinge_axes(design)
    dep = mirror_face_poses(design)
    sim = SceneSimulator(design, "wall")
    steps = design.lidar.steps
    o, d, _, first, bounces, alive = sim.head_rays(steps, f, f)
    d0 = directions_from_bearings(design.lidar.bearing_from_step(steps))
    one = (first >= 0) & (bounces == 1) & alive
    assert one.sum() > 100
    for i, m in enumerate(design.mirrors):
        sel = one & (first == i)
        if not sel.any():
            continue
        ax = axes[m.side]
        R = matrix_from_axis_angle(np.asarray(ax.direction), f * ax.lift_rad)
        p0 = np.asarray(ax.point_mm)
        c = (np.asarray(dep[m.name]["deployed"]["corners_mm"]) - p0) @ R.T + p0
        n = R @ np.asarray(dep[m.name]["deployed"]["normal"])
        hit_mm = o[sel] * 1000
        # float64 plane distance of a float64 hit: ~1e-12 mm; 1e-6 mm is far below any
        # model difference and far above rounding
        assert_allclose((hit_mm - c[0]) @ n, 0.0, atol=1e-6, err_msg=m.name)
        u, v = c[1] - c[0], c[3] - c[0]
        su = (hit_mm - c[0]) @ u / (u @ u)
        sv = (hit_mm - c[0]) @ v / (v @ v)
        assert np.all((su > -1e-9) & (su < 1 + 1e-9) & (sv > -1e-9) & (sv < 1 + 1e-9)), m.name
        assert_allclose(d[sel], reflect(d0[sel], n), atol=1e-12, err_msg=m.name)


def test_axis_rule_from_the_faces(design):
    """The rule of docs/conventions.md, checked without nodlidar.hinge's arithmetic:
    horizontal at hinge_z, along the chord (outermost outer end -> innermost inner end),
    every face point on or behind it with one face end on it, glass swinging away from
    the lidar by the design's lift angle."""
    ms = design.spec.mirror
    axes = side_lift_axes(design)
    assert set(axes) == {m.side for m in design.mirrors}
    for side, ax in axes.items():
        sols = sorted((m for m in design.mirrors if m.side == side), key=lambda m: m.index)
        assert ax.point_m[2] == pytest.approx(ms.hinge_z_m, abs=1e-15)
        assert ax.direction[2] == 0.0 and ax.outward[2] == 0.0
        # the chord's ends by bearings: the outer end has the larger |bearing|
        ends = [m.patch.corners()[:2] * [1, 1, 0] for m in (sols[0], sols[-1])]  # z = 0 edge
        b = [np.abs(np.arctan2(q[:, 1], q[:, 0])) for q in ends]
        chord = ends[1][np.argmin(b[1])] - ends[0][np.argmax(b[0])]
        assert_allclose(face_ends(sols[0].patch)[0], ends[0][np.argmax(b[0])], atol=1e-15)
        assert abs(ax.direction[0] * chord[1] - ax.direction[1] * chord[0]) < 1e-12
        assert ax.direction_ @ chord > 0
        pts = np.vstack([m.patch.corners() for m in sols])
        e = (pts - ax.point_) @ ax.outward_
        assert e.min() > -1e-12 and e.min() < 1e-12  # on or behind, touching
        # outward is away from the lidar: the lidar origin is in front of the axis
        assert (np.zeros(3) - ax.point_) @ ax.outward_ < 0
        assert abs(ax.lift_rad) == pytest.approx(ms.lift_angle_rad, abs=1e-15)
        # top of the glass away from the lidar (hinge below): the lifted up vector
        for m in sols:
            up = lifted_patch(m.patch, ax, 1.0).up_
            assert up @ ax.outward_ > 0 and up @ m.patch.normal_ < 0


def test_lifted_beams_go_direct(builds):
    """Lifted, no beam of the lidar's field meets a glass of the paper build (traced by
    the simulator), and the lifted glass is entirely below the scan plane (turned by 90
    deg about an axis 25 mm below the plane, a point at distance e >= 0 behind the axis
    and h above it ends at height -25 mm - e)."""
    from nodlidar.sim.raycast import SceneSimulator

    design = builds["paper"]
    sim = SceneSimulator(design, "wall")
    _, _, _, first, bounces, alive = sim.head_rays(design.lidar.steps, 1.0, 1.0)
    assert np.all(first == -1) and np.all(bounces == 0) and np.all(alive)
    # and deployed, the windows are reflected (the check can fail)
    _, _, _, first0, _, _ = sim.head_rays(design.lidar.steps, 0.0, 0.0)
    assert np.sum(first0 >= 0) > 400
    top = max(np.max(g.corners()[:, 2]) for g in sim.mirror_patches_at(1.0, 1.0))
    assert top < 0.0


def _glass_corners(patch, thickness):
    """(8, 3) corners of a glass pane: the face and the face moved back by the thickness."""
    c = patch.corners()
    return np.vstack([c, c - thickness * patch.normal_])


def test_lifted_glass_clears_the_lidar_and_the_other_side(design):
    """The glass (with its thickness), deployed, half way and lifted, stays out of the
    lidar housing and away from the other side: the vertical plane through the side's lift
    axis separates the glass (behind it, all the way up) from the housing's square body
    (in front of it), and y = 0 separates the two sides' glass. (The printed carriers,
    hinge tubes and servos against the lidar envelope: test_cad.py test_no_interference,
    in both states.)"""
    lidar = design.lidar
    hw = lidar.housing_half_width_m
    t = design.spec.mirror.glass_thickness_m
    sq = np.array([[hw, hw], [-hw, hw], [-hw, -hw], [hw, -hw]])
    axes = side_lift_axes(design)
    ys = {}
    for side, ax in axes.items():
        glass = [lifted_points(_glass_corners(m.patch, t), ax, f)
                 for m in design.mirrors if m.side == side for f in (0.0, 0.5, 1.0)]
        e = (np.vstack(glass) - ax.point_) @ ax.outward_
        assert e.min() > -1e-12, side
        e_housing = (sq - ax.point_[:2]) @ ax.outward_[:2]
        assert e_housing.max() < 0, (side, e_housing.max())
        ys[side] = np.vstack(glass)[:, 1]
    assert ys["L"].min() > 0 and ys["R"].max() < 0


def test_hinge_above_lifts_the_glass_away_and_above():
    """A hinge above the glass (the spec allows it; the CAD builds hinges below only):
    the glass still swings away from the lidar and ends above the scan plane."""
    spec = load_design(PAPER)
    d = solve(spec.replace(**{"mirror.hinge_z_m": 0.025}))
    for side, ax in side_lift_axes(d).items():
        for m in (m for m in d.mirrors if m.side == side):
            lifted = lifted_patch(m.patch, ax, 1.0)
            assert lifted.corners()[:, 2].min() > 0
            e0 = (m.patch.corners() - ax.point_) @ ax.outward_
            e1 = (lifted.corners() - ax.point_) @ ax.outward_
            assert e1.mean() > e0.mean() + 0.01


def test_partial_lift_is_the_fraction_of_the_rotation(builds):
    """lifted_patch(f) turns by f * lift_rad: composing two halves is the whole lift
    (round trip through MirrorPatch.transformed), and lift_fraction maps servo angles."""
    design = builds["paper"]
    ax = side_lift_axes(design)["L"]
    m = design.mirrors[0]
    half = lifted_patch(lifted_patch(m.patch, ax, 0.5), ax, 0.5)
    assert_allclose(half.corners(), lifted_patch(m.patch, ax, 1.0).corners(), atol=1e-15)
    assert_allclose(lifted_patch(m.patch, ax, 0.0).corners(), m.patch.corners(), atol=1e-15)
    assert_allclose(lift_fraction([-0.1, 0.0, math.pi / 4, math.pi / 2, 2.0], 0.0, math.pi / 2),
                    [0.0, 0.0, 0.5, 1.0, 1.0], atol=1e-15)
    with pytest.raises(ParameterError, match="lifted_rad"):
        lift_fraction(0.3, deployed_rad=1.0, lifted_rad=1.0)   # no travel: no fraction
    from nodlidar.sim.raycast import lift_fraction as old_home

    assert old_home is lift_fraction


def test_lift_axis_refuses_bad_values():
    good = dict(side="L", point_m=(0.0, 0.05, -0.025), direction=(1.0, 0.0, 0.0),
                outward=(0.0, 1.0, 0.0), lift_rad=-math.pi / 2)
    LiftAxis(**good)
    for key, bad, name in (("side", "X", "side"), ("direction", (1.0, 0.0, 0.1), "direction"),
                           ("direction", (0.6, 0.6, 0.0), "direction"),
                           ("outward", (1.0, 0.0, 0.0), "outward"),
                           ("lift_rad", 0.0, "lift_rad"), ("point_m", (0.0, np.nan, 0.0), "point_m")):
        with pytest.raises(ParameterError, match=name):
            LiftAxis(**{**good, key: bad})


def test_cad_carrier_conforms_to_the_lift_axis(design):
    """The CAD's hinge is the lift axis (HingeAxis = LiftAxis in mm), every plan polygon of
    the carrier (back plate, end stops, skirt) lies on or behind it - the end stops' front
    corners that stood up to 0.35 mm lidar-ward of it on the paper build are clipped - and
    the lifted carrier (each polygon's prism from the hinge tube's bottom to its top)
    stays below the beam band."""
    from nodlidar.cad.mounts import HingeAxis, lift_transform, side_layouts
    from nodlidar.cad.params import MountParams

    P = MountParams()
    ms = design.spec.mirror
    hz = ms.hinge_z_m * 1000
    z_bot, z_min, z_max = hz - P.hinge_boss_radius_mm, -ms.glass_height_m * 500, ms.glass_height_m * 500
    axes = side_lift_axes(design)
    clipped = 0
    for side, lay in side_layouts(design, P).items():
        assert lay.axis == HingeAxis.from_lift_axis(axes[side])
        a0, w = np.asarray(lay.axis.point_mm)[:2], np.asarray(lay.axis.outward)[:2]
        prisms = ([(q, z_max) for q in lay.back_polygons]
                  + [(q, z_min + P.end_stop_height_mm) for q in lay.stop_polygons]
                  + [(lay.skirt_polygon, z_min)])
        R, t = lift_transform(lay.axis, "lifted")
        for q, top in prisms:
            assert ((q - a0) @ w).min() > -1e-9, side
            pts = np.vstack([np.c_[q, np.full(len(q), z)] for z in (z_bot, top)])
            assert (pts @ R.T + t)[:, 2].max() < -P.beam_band_mm, side
        clipped += sum(len(q) > 4 for q in lay.stop_polygons)
    assert clipped > 0  # the clip did something on these builds (else it is untested)
