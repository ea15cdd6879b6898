"""Scene simulator: the embree ray caster against closed forms and against BeamModel.

Independent references: direct and reflected beam paths to a plane in closed form (mirror
plane reflection, then ray-plane distance), written here from the patch's origin/normal;
the runtime BeamModel (a separate implementation) projecting simulated ranges; the ray-circle
closed form for a moving cylinder; the noise model's sigma.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from nodlidar.errors import ParameterError
from nodlidar.paper import TABLE_I_PERTURBATIONS
from nodlidar.sim.raycast import SceneSimulator, lift_fraction
from nodlidar.sim.scene import (
    HIT_NONE,
    HIT_STATIC,
    BackAndForth,
    ConstantVelocity,
    Cylinder,
    Mover,
    Plane,
    Scene,
    SensorPose,
    Waypoints,
    builtin_scene,
    load_scene,
    wall_scene,
)
from nodlidar.solver import solve
from nodlidar.spec import load_design

PAPER = "design/urg04lx-paper.toml"

# true ranges are recomputed in float64 from the triangle's plane: only rounding error
TRUE_TOL_M = 1e-9
# reported ranges are rounded to the mm: at most half the 1 mm quantisation step off
MM_TOL_M = 0.5e-3 + 1e-9


@pytest.fixture(scope="module")
def design():
    return solve(load_design(PAPER))


def _ry(nod):
    c, s = math.cos(nod), math.sin(nod)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _patch_t(p, o, d):
    """Closed-form distance from o along d to patch p's rectangle (inf if outside/behind)."""
    n, q = np.array(p.normal), np.array(p.origin)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = ((q - o) @ n) / (d @ n)
    h = o + t[:, None] * d
    rel = h - q
    s_, z_ = rel @ np.array(p.along), rel @ np.cross(n, p.along)
    ok = (t > 1e-9) & (s_ > p.s_min) & (s_ < p.s_max) & (z_ > p.z_min) & (z_ < p.z_max)
    return np.where(ok, t, np.inf)


def _analytic(design, perts, steps, nod, plane_pt, plane_n, pose: SensorPose,
              radius_m=math.inf):
    """Closed-form total path to a plane for each step, via its design mirror.

    Returns (path length (n,), determined (n,) bool, direct (n,) bool). A beam is
    determined if it is direct and meets no mirror, or meets its design mirror first and
    its reflection meets no other mirror. Hits farther than ``radius_m`` from ``plane_pt``
    are NaN (the scene's plane is finite: a disc inside its square is surely on it).
    """
    lid = design.lidar
    th = (steps - lid.step_front) * 2 * math.pi / lid.steps_per_rev
    d = np.stack([np.cos(th), np.sin(th), np.zeros_like(th)], 1)
    o = np.zeros_like(d)
    patches = design.patches(perts)
    t_all = np.stack([_patch_t(p, o, d) for p in patches], 1)  # (n, mirrors)
    mos = design.mirror_of_step[steps - lid.step_min]
    direct = mos < 0
    first = np.where(np.isfinite(t_all.min(1)), np.argmin(t_all, 1), -1)
    det = np.where(direct, first < 0, first == mos)
    off = np.zeros(len(steps))
    for i, p in enumerate(patches):
        sel = (mos == i) & det
        n = np.array(p.normal)
        t = t_all[sel, i]
        o[sel] = t[:, None] * d[sel]
        d[sel] = d[sel] - 2 * (d[sel] @ n)[:, None] * n  # mirror-plane reflection
        off[sel] = t
    for j, p in enumerate(patches):  # the reflected rays must not meet a second mirror
        again = np.isfinite(_patch_t(p, o, d)) & (mos != j) & ~direct
        det &= ~again
    # ... nor turn back into the lidar's housing (a vertical cylinder about the z axis):
    # the line's closest approach to the axis, ahead of the mirror, inside the radius
    oxy, dxy = o[:, :2], d[:, :2]
    t_c = -np.sum(oxy * dxy, 1) / np.maximum(np.sum(dxy * dxy, 1), 1e-300)
    closest = np.linalg.norm(oxy + np.maximum(t_c, 0.0)[:, None] * dxy, axis=1)
    det &= direct | (closest > lid.housing_radius_m)
    pivot = np.array(design.spec.nod.pivot_m)
    R = pose.rotation @ _ry(nod)
    ow = (o - pivot) @ R.T + pivot @ pose.rotation.T + np.array(pose.position_m)
    dw = d @ R.T
    t = ((plane_pt - ow) @ plane_n) / (dw @ plane_n)
    on = np.linalg.norm(ow + t[:, None] * dw - plane_pt, axis=1) <= radius_m
    return np.where((t > 0) & on, off + t, np.nan), det, direct


def _side_gap(design):
    """Side-window steps no mirror takes (the exact paper reading leaves 612..615 and
    153..156 unreflected): they leave sideways, direct. ``(k,) int``."""
    lid = design.lidar
    free = lid.steps[design.mirror_of_step < 0]
    return np.setdiff1d(free, design.direct_steps)


@pytest.mark.parametrize("perturbed", [False, True])
@pytest.mark.parametrize("nod", [0.0, 0.2, -0.3])
def test_plane_ranges_match_closed_form(design, perturbed, nod):
    perts = dict(TABLE_I_PERTURBATIONS) if perturbed else {}
    n = np.array([-1.0, -0.25, 0.12])
    n /= np.linalg.norm(n)
    c = np.array([2.3, 0.4, 0.6])
    pose = SensorPose((0.1, -0.2, 0.5), math.radians(8.0))
    scene = Scene("plane", (Plane(tuple(c), tuple(n), (30.0, 30.0)),), sensor=pose)
    sim = SceneSimulator(design, scene, perts)
    s = sim.scan(0.0, nod, noise=False)
    # the plane is 30 m square: hits within 15 m of its centre are surely on it
    want, det, direct = _analytic(design, perts, s.steps, nod, c, n, pose, radius_m=15.0)
    use = det & np.isfinite(want)
    # nearly all beams are checked: all but the ones the design gives up (shadowed: the
    # reflection meets another mirror) and the unreflected side-window beams, which leave
    # sideways, past the plane
    lost = len(design.shadowed_steps) + len(_side_gap(design))
    assert use.sum() > (500 if perturbed else 670) - lost
    if not perturbed:
        # the closed form's second-mirror test finds exactly the design's shadowed beams
        assert np.array_equal(s.steps[~det], design.shadowed_steps)
    assert direct[use].sum() >= 200 and (~direct[use]).sum() >= 300  # both kinds
    assert np.all(s.object_id[use] == HIT_STATIC)
    assert_allclose(s.true_range_m[use], want[use], rtol=0, atol=TRUE_TOL_M)  # float64 closed forms
    assert np.max(np.abs(s.range_m[use] - want[use])) <= MM_TOL_M
    # the beams it reflected are exactly the ones the closed form says hit their mirror
    assert np.array_equal(s.mirror[use] >= 0, ~direct[use])
    # hit points lie on the plane
    assert_allclose((s.point_world[use] - c) @ n, 0.0, atol=TRUE_TOL_M)


@pytest.mark.parametrize("perturbed", [False, True])
def test_beam_model_projects_simulated_ranges_onto_the_plane(design, perturbed):
    """BeamModel (runtime, precomputed paths) vs the embree caster: independent code."""
    perts = dict(TABLE_I_PERTURBATIONS) if perturbed else {}
    dist, yaw = 1.8, 0.15
    sim = SceneSimulator(design, wall_scene(dist, yaw), perts)
    nod = np.linspace(-0.3, 0.3, design.lidar.n_steps)  # a ramp within one scan
    s = sim.scan(0.0, nod, noise=False)
    bm = design.beam_model(perts)
    same = (s.mirror == bm.mirror_of_step) & np.isfinite(s.true_range_m)
    # all but the design's shadowed beams (no return in the simulator) and the unreflected
    # side-window beams (they leave sideways, past the wall)
    lost = len(design.shadowed_steps) + len(_side_gap(design))
    assert same.sum() > (550 if perturbed else 680) - lost
    if not perturbed:
        # the simulator re-traces blocking: shadowed beams return nothing
        assert not np.isfinite(s.true_range_m[design.shadowed_steps - design.lidar.step_min]).any()
    p = bm.points(s.steps[same], s.true_range_m[same], s.nod_rad[same])
    n = np.array([math.cos(yaw), math.sin(yaw), 0.0])
    # both are float64 closed forms of the same geometry: agreement to rounding
    assert_allclose(p @ n, dist, atol=1e-9)
    assert_allclose(p, s.point_world[same], atol=1e-9)
    # with the reported (mm) ranges the points are within the quantisation of the wall
    q = bm.points(s.steps[same], s.range_m[same], s.nod_rad[same])
    assert np.max(np.abs(q @ n - dist)) <= MM_TOL_M


def test_perturbed_beams_that_miss_their_mirror_go_elsewhere(design):
    """Table I moves mirrors enough that some beams miss (or meet another mirror): the
    simulator follows the physics, BeamModel keeps the design assignment."""
    sim = SceneSimulator(design, wall_scene(2.0), dict(TABLE_I_PERTURBATIONS))
    s = sim.scan(0.0, 0.0, noise=False)
    changed = s.mirror != design.mirror_of_step
    assert 0 < changed.sum() < 150


def test_lifted_mirrors_send_reflected_window_beams_direct(design):
    # a closed box of walls around the sensor: every direct beam hits something
    scene = Scene("room", (load_scene("room").statics[0],), sensor=SensorPose((0, 0, 1.2)))
    sim = SceneSimulator(design, scene)
    dep = sim.scan(0.0, 0.0, 0.0, 0.0, noise=False)
    lif = sim.scan(0.0, 0.0, 1.0, 1.0, noise=False)
    win = design.mirror_of_step >= 0
    assert np.all(dep.mirror[win] >= 0) and np.all(dep.mirror[~win] == -1)
    assert np.all(lif.mirror == -1) and np.all(lif.bounces == 0)
    # direct beams to the room walls in closed form (sensor 1.2 m up, head level)
    lx, ly, _ = scene.statics[0].size_m
    cx, cy = scene.statics[0].center_m
    th = design.lidar.bearing_from_step(design.lidar.steps)
    with np.errstate(divide="ignore"):
        tx = np.where(np.cos(th) > 0, (cx + lx / 2) / np.cos(th), (cx - lx / 2) / np.cos(th))
        ty = np.where(np.sin(th) > 0, (cy + ly / 2) / np.sin(th), (cy - ly / 2) / np.sin(th))
    want = np.minimum(np.abs(tx), np.abs(ty))
    assert_allclose(lif.true_range_m, want, atol=TRUE_TOL_M)
    # the middle window does not care about the mirrors
    assert_allclose(lif.true_range_m[~win], dep.true_range_m[~win], atol=1e-12)
    # only the left side lifted: left window direct, right window still reflected
    half = sim.scan(0.0, 0.0, 1.0, 0.0, noise=False)
    left = np.isin(design.mirror_of_step, [i for i, m in enumerate(design.mirrors) if m.side == "L"])
    assert np.all(half.mirror[left] == -1)
    assert np.all(half.mirror[win & ~left] >= 0)


def test_per_beam_lift_state_equals_scans_at_each_state(design):
    """A lift in progress: each beam sees the mirror where it is at that beam's time. The
    per-beam path must give, beam by beam, what a scan at that constant state gives."""
    sim = SceneSimulator(design, "room")
    levels = np.array([0.0, 0.3, 0.5, 0.6, 1.0])
    idx = np.arange(design.lidar.n_steps) % len(levels)
    fl, fr = levels[idx], levels[::-1][idx]
    s = sim.scan(0.0, 0.1, fl, fr, noise=False)
    for i, (a, b) in enumerate(zip(levels, levels[::-1])):
        ref = sim.scan(0.0, 0.1, a, b, noise=False)
        sel = idx == i
        assert np.array_equal(s.mirror[sel], ref.mirror[sel])
        assert_allclose(s.true_range_m[sel], ref.true_range_m[sel], atol=1e-12)
    assert len(np.unique(s.mirror[design.mirror_of_step >= 0])) > 2


def test_nod_ramp_scans_and_moving_sensor(design):
    """scans(): the design's nod ramp per beam; points projected with BeamModel at the
    ramp's closed-form pitch land on the wall. A sensor driving at 1 m/s towards a wall sees
    it nearer by 1 m/s times each beam's time."""
    sim = SceneSimulator(design, wall_scene(2.0))
    scans = sim.scans(12, noise=False)
    nod_spec = design.spec.nod
    bm = design.beam_model()
    for s in scans:
        ramp = nod_spec.pitch_min_rad + nod_spec.rate_rad_s * s.t_s  # first rising ramp (2 s)
        assert_allclose(s.nod_rad, ramp, atol=1e-12)
        same = (s.mirror == bm.mirror_of_step) & np.isfinite(s.range_m)
        p = bm.points(s.steps[same], s.range_m[same], ramp[same])
        assert same.sum() > 600 and np.max(np.abs(p[:, 0] - 2.0)) <= MM_TOL_M
    moving = Scene("drive", wall_scene(2.0).statics, sensor=SensorPose((0, 0, 0), 0.0, (1.0, 0, 0)))
    s = SceneSimulator(design, moving).scan(0.5, 0.0, 1.0, 1.0, noise=False)
    front = s.steps == design.lidar.step_front
    assert_allclose(s.true_range_m[front], 2.0 - 1.0 * s.t_s[front], atol=1e-9)
    assert s.t_s[front][0] > 0.5 + 0.03  # step 384 is 37.5 ms after the timestamp


def test_lift_fraction_maps_servo_angle():
    assert_allclose(lift_fraction([-0.1, 0.0, math.pi / 4, math.pi / 2, 2.0], 0.0, math.pi / 2),
                    [0.0, 0.0, 0.5, 1.0, 1.0], atol=1e-15)
    assert_allclose(lift_fraction(1.0, deployed_rad=2.0, lifted_rad=0.0), 0.5)


def test_partly_lifted_mirror_leaves_the_scan_plane_at_the_closed_form_angle(design):
    """A side turns about its lift axis (nodlidar.hinge: |hinge_z| below the scan plane).
    A top corner of a glass, e behind the axis and h above it, is at height
    hinge_z + h cos a - e sin a = hinge_z + R cos(a + phi) (R = hypot(e, h),
    phi = atan2(e, h)) after turning by a: it drops below the scan plane at
    a = acos(|hinge_z| / R) - phi. The glass leaves the scan plane when its last top
    corner does; just before, every mirror still reflects beams, just after none."""
    from nodlidar.hinge import side_lift_axes

    ms = design.spec.mirror
    hz = ms.hinge_z_m
    axes = side_lift_axes(design)
    f_star = []
    for m in design.mirrors:
        ax = axes[m.side]
        top = m.patch.corners()[2:]
        e, h = (top - ax.point_) @ ax.outward_, top[:, 2] - hz
        a = np.max(np.arccos(abs(hz) / np.hypot(e, h)) - np.arctan2(e, h))
        f_star.append(a / ms.lift_angle_rad)  # 0.57 of the lift for the paper
    sim = SceneSimulator(design, wall_scene(2.0))
    below = sim.scan(0.0, 0.0, min(f_star) - 0.01, min(f_star) - 0.01, noise=False)
    above = sim.scan(0.0, 0.0, max(f_star) + 0.01, max(f_star) + 0.01, noise=False)
    # the glass still crosses the scan plane near its top corner on the axis (turned
    # outwards, so the beams towards the rest of it now miss it)
    assert all(np.any(below.mirror == i) for i in range(len(design.mirrors)))
    assert np.all(above.mirror == -1)


def test_moving_cylinder_is_seen_where_it_is_at_each_beam_time(design):
    """Two cylinders moving fast; each beam's range matches the ray-circle closed form
    with the cylinder at that beam's own time, not at the scan's start."""
    v = np.array([0.0, 6.0, 0.0])  # m/s: 0.4 m in a 66 ms scan
    r = 0.25
    t0 = 0.3
    a = BackAndForth((1.5, -1.6, 0.0), tuple(np.array([1.5, -1.6, 0]) + 10 * v / 6), 6.0, t0)
    b = BackAndForth((-0.8, 1.0, 0.0), tuple(np.array([-0.8, 1.0, 0]) + 10 * v / 6), 6.0, t0)
    scene = Scene("movers", (), (Mover(Cylinder(r, 2.0, -1.0), a, "early"),
                                 Mover(Cylinder(r, 2.0, -1.0), b, "late")), SensorPose((0, 0, 0)))
    sim = SceneSimulator(design, scene)
    s = sim.scan(t0, 0.0, 1.0, 1.0, noise=False)  # mirrors lifted: direct beams
    th = design.lidar.bearing_from_step(s.steps)
    d = np.stack([np.cos(th), np.sin(th)], 1)

    def circle_range(centres, hit, rad=r):  # nearest root of |t d - c| = rad
        bq = np.sum(d[hit] * centres[:, :2], 1)
        disc = bq**2 - (np.sum(centres[:, :2] ** 2, 1) - rad * rad)
        return np.where(disc >= 0, bq - np.sqrt(np.maximum(disc, 0)), np.nan)

    for k, traj in enumerate((a, b)):
        hit = s.object_id == 1 + k
        assert hit.sum() >= 5
        c = traj.position(s.t_s[hit])
        # the 128-facet mesh lies between its incircle (r cos(pi/128)) and r: each range
        # lies between the closed-form ranges to the two circles (rounding: 1e-9 m)
        outer, inner = circle_range(c, hit, r), circle_range(c, hit, r * math.cos(math.pi / 128))
        assert np.all(s.true_range_m[hit] >= outer - 1e-9)
        assert np.all(s.true_range_m[hit] <= np.where(np.isnan(inner), np.inf, inner) + 1e-9)
        face_on = np.isfinite(inner)
        assert face_on.sum() >= 5
        assert np.max(s.true_range_m[hit][face_on] - outer[face_on]) < 0.002
        naive = circle_range(np.broadcast_to(traj.position(t0), (hit.sum(), 3)), hit)
        late = s.t_s[hit] - t0
        if k == 1:  # seen at the end of the scan: ~55 ms later, moved ~0.33 m
            assert late.min() > 0.045
            assert np.nanmax(np.abs(naive - s.true_range_m[hit])) > 0.05 or np.isnan(naive).any()
        else:  # seen early (~15 ms after the start): still moved but far less
            assert late.max() < 0.03
    # ground-truth points lie on the cylinder mesh at the beam time
    for k, traj in enumerate((a, b)):
        hit = s.object_id == 1 + k
        rad = np.linalg.norm(s.point_world[hit, :2] - traj.position(s.t_s[hit])[:, :2], axis=1)
        assert np.all((rad <= r + 1e-9) & (rad >= r * math.cos(math.pi / 128) - 1e-9))


def test_back_and_forth_is_a_triangle_wave():
    tr = BackAndForth((0.0, 0.0, 0.0), (1.0, 0.0, 0.0), 0.5, t0_s=1.0)
    t = np.array([1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 0.0])
    assert_allclose(tr.position(t)[:, 0], [0.0, 0.5, 1.0, 0.5, 0.0, 0.5, 0.5], atol=1e-12)
    assert_allclose(tr.velocity(np.array([1.5, 3.5]))[:, 0], [0.5, -0.5])
    h = BackAndForth.from_heading((0, 0, 0), math.radians(89.4), 0.13, 1.0)
    u = np.subtract(h.end_m, h.start_m)
    assert_allclose(math.degrees(math.atan2(u[1], u[0])), 89.4, atol=1e-12)


def test_noise_statistics_match_the_model(design):
    """Std of (reported - true) range at 0.5 m and 3 m vs sigma(r) of the model.

    With n samples the sample std has relative standard error 1/sqrt(2n); we allow 4 of
    them. The mm rounding adds 1/12 mm^2 of variance, included in the expectation.
    """
    for dist in (0.5, 3.0):
        sim = SceneSimulator(design, wall_scene(dist))
        errs, sig = [], []
        for k in range(30):
            s = sim.scan(0.0, 0.0, 1.0, 1.0, noise=True, seed=k)
            # beams within +-15 deg of the wall normal: range within 3.5 % of dist
            sel = np.abs(design.lidar.bearing_from_step(s.steps)) < math.radians(15)
            errs.append(s.range_m[sel] - s.true_range_m[sel])
            sig.append(design.lidar.range_sigma_m(s.true_range_m[sel]))
        e, sg = np.concatenate(errs), np.concatenate(sig)
        n = e.size
        assert n > 1500
        z = e / np.sqrt(sg**2 + 1e-6 / 12)
        assert abs(np.std(z) - 1.0) < 4 / math.sqrt(2 * n)
        assert abs(np.mean(z)) < 4 / math.sqrt(n)
        want_sigma = 0.010 if dist <= 1.0 else 0.01 * dist  # data sheet / 3 (lidar.py)
        assert abs(np.std(e) / want_sigma - 1.0) < 0.05


def test_noise_is_seeded_and_switchable(design):
    sim = SceneSimulator(design, wall_scene(1.0))
    a = sim.scan(0.0, 0.0, seed=3)
    b = sim.scan(0.0, 0.0, seed=3)
    c = sim.scan(0.0, 0.0, seed=4)
    off = sim.scan(0.0, 0.0, noise=False)
    assert np.array_equal(a.range_m, b.range_m, equal_nan=True)
    assert not np.array_equal(a.range_m, c.range_m, equal_nan=True)
    ok = np.isfinite(off.true_range_m)
    assert_allclose(off.range_m[ok], np.round(off.true_range_m[ok] * 1000) / 1000, atol=1e-12)
    assert_allclose(a.range_m * 1000, np.round(a.range_m * 1000), atol=1e-9)  # whole mm


def test_no_return_and_limits(design):
    """Beams into empty space are NaN; measured_m() also blanks what the device would send
    as an error code (beyond DMAX 5.6 m, below DMIN 20 mm)."""
    far = SceneSimulator(design, wall_scene(7.0)).scan(0.0, 0.0, 1.0, 1.0, noise=False)
    front = np.abs(design.lidar.bearing_from_step(far.steps)) < 0.3
    assert np.all(far.range_m[front] > 5.6) and np.all(np.isnan(far.measured_m()[front]))
    back = np.abs(design.lidar.bearing_from_step(far.steps)) > math.pi / 2
    assert np.all(np.isnan(far.range_m[back])) and np.all(far.object_id[back] == HIT_NONE)


def test_waypoints_walk_the_legs_at_their_speeds_and_wait_at_each_waypoint():
    """Times worked by hand: legs of 1 m at 0.5 m/s (2 s) and 2 m at 1 m/s (2 s), a 1 s
    wait at the middle waypoint; before t0 at the first waypoint, after the end at the
    last. The velocity is the derivative of the position away from the corners."""
    tr = Waypoints([[0, 0, 0], [1, 0, 0], [1, 2, 0]], [0.5, 1.0], pause_s=1.0, t0_s=1.0)
    assert tr.duration_s == pytest.approx(5.0)
    t = np.array([0.0, 1.0, 2.0, 3.0, 3.5, 4.0, 5.0, 6.0, 9.0])
    assert_allclose(tr.position(t)[:, :2], [[0, 0], [0, 0], [0.5, 0], [1, 0], [1, 0], [1, 0],
                                            [1, 1], [1, 2], [1, 2]], atol=1e-12)
    assert_allclose(tr.velocity(t)[:, :2], [[0, 0], [0.5, 0], [0.5, 0], [0, 0], [0, 0],
                                            [0, 1], [0, 1], [0, 0], [0, 0]], atol=1e-12)
    # round and round: periodic, and waiting at the first waypoint on each return too
    lp = Waypoints([[0, 0, 0], [1, 0, 0], [1, 1, 0]], 0.5, pause_s=0.5, loop=True)
    per = 2 + 2 + 2 * math.sqrt(2) + 3 * 0.5
    assert lp.duration_s == pytest.approx(per)
    ts = np.linspace(0.013, 3 * per, 997)
    assert_allclose(lp.position(ts + per), lp.position(ts), atol=1e-12)
    h = 1e-7
    fd = (lp.position(ts + h) - lp.position(ts - h)) / (2 * h)
    corner = np.any(np.abs(np.mod(ts, per)[:, None] - np.array(
        [0, 2, 2.5, 4.5, 5, 5 + 2 * math.sqrt(2), per])) < 1e-6, axis=1)
    assert_allclose(fd[~corner], lp.velocity(ts)[~corner], atol=1e-6)
    assert_allclose(lp.position(per - 0.25), [0, 0, 0], atol=1e-12)  # waiting at the first


def test_a_waypoints_mover_is_seen_as_the_same_motion_by_the_kernel_law(design):
    """The simulator casts a waypoints mover through its own ``position(t)`` per beam,
    the built-in kinds through the compiled law: on a leg the two must give the same
    ranges, to rounding (the same rays, the same mesh)."""
    v = np.array([0.0, 6.0, 0.0])  # m/s: fast, so each beam's own time matters
    start = np.array([1.5, -1.6, 0.0])
    wp = Waypoints([tuple(start), tuple(start + 2 * v)], 6.0)
    cv = ConstantVelocity(tuple(start), tuple(v))
    scans = []
    for traj in (wp, cv):
        scene = Scene("m", (), (Mover(Cylinder(0.25, 2.0, -1.0), traj, "p"),), SensorPose((0, 0, 0)))
        scans.append(SceneSimulator(design, scene).scan(0.3, 0.0, 1.0, 1.0, noise=False))
    hit = scans[1].object_id == 1
    assert hit.sum() >= 5
    assert_array_equal(scans[0].object_id, scans[1].object_id)
    assert_allclose(scans[0].true_range_m[hit], scans[1].true_range_m[hit], atol=1e-9)


@pytest.mark.parametrize("kw, match", [
    ({"points_m": [[0, 0, 0]]}, "at least 2 waypoints"),
    ({"points_m": [[0, 0, 0], [0, 0, 0]]}, "points_m.1.*different"),
    ({"points_m": [[0, 0], [1, 0, 0]]}, "points_m.0.*3 finite"),
    ({"speed_m_s": [1.0, 2.0]}, "one per leg .1."),
    ({"speed_m_s": -1.0}, "speed_m_s"),
    ({"speed_m_s": "fast"}, "speed_m_s"),
    ({"pause_s": -1.0}, "pause_s.*>= 0"),
    ({"loop": "false"}, "loop.*true or false"),  # a string would read as true
    ({"t0_s": "soon"}, "t0_s"),
])
def test_waypoints_reject_bad_input_by_name(kw, match):
    args = {"points_m": [[0, 0, 0], [1, 0, 0]], "speed_m_s": 1.0, **kw}
    with pytest.raises(ParameterError, match=match):
        Waypoints(**args)


def test_scene_toml_round_trip_and_errors(tmp_path):
    p = tmp_path / "s.toml"
    p.write_text("""
name = "lab"
[sensor]
position_m = [0.5, 0.0, 0.3]
yaw_deg = 90.0
[room]
size_m = [4.0, 3.0, 2.0]
center_m = [1.0, 0.0]
ceiling = false
[[box]]
size_m = [0.5, 0.5, 1.0]
center_m = [2.0, 1.0, 0.5]
[[plane]]
center_m = [1.0, 0.0, 0.0]
normal = [-1.0, 0.0, 0.0]
size_m = [2.0, 1.0]
[[mover]]
radius_m = 0.2
height_m = 1.0
trajectory = "back_and_forth"
start_m = [2.0, -0.5, 0.0]
heading_deg = 90.0
length_m = 1.0
speed_m_s = 0.25
[[mover]]
shape = "box"
size_m = [0.3, 0.3, 0.6]
trajectory = "constant_velocity"
start_m = [0.0, 0.0, 0.0]
velocity_m_s = [0.1, 0.0, 0.0]
[[mover]]
trajectory = "waypoints"
points_m = [[1.0, -1.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]]
speed_m_s = 0.5
pause_s = 2.0
""")
    s = Scene.from_toml(p)
    assert s.name == "lab" and len(s.statics) == 3 and len(s.movers) == 3
    assert_allclose(s.movers[2].position(np.array([1.0, 3.0, 5.0])),
                    [[1.0, -0.5, 0.0], [1.0, 0.0, 0.0], [1.5, 0.0, 0.0]], atol=1e-12)
    assert_allclose(s.sensor.yaw_rad, math.pi / 2)
    assert len(s.static_parts()) == 5 + 1 + 1  # 4 walls + floor, box, plane
    assert_allclose(s.movers[0].position(4.0), [2.0, 0.5, 0.0], atol=1e-12)
    assert_allclose(s.movers[1].position(np.array([2.0]))[0], [0.2, 0.0, 0.0])
    assert load_scene(str(p)) == s
    bad = tmp_path / "bad.toml"
    bad.write_text("[[mover]]\ntrajectory = 'zigzag'\n")
    with pytest.raises(ParameterError, match="trajectory"):
        Scene.from_toml(bad)
    bad.write_text("[[mover]]\ntrajectory = 'waypoints'\nspeed_m_s = 1.0\n")
    with pytest.raises(ParameterError, match="points_m.*required for trajectory 'waypoints'"):
        Scene.from_toml(bad)
    bad.write_text("walls = 3\n")
    with pytest.raises(ParameterError, match="walls"):
        Scene.from_toml(bad)
    with pytest.raises(ParameterError, match="room, paper-tracking, wall"):
        load_scene("nowhere")


def test_scene_files_load(design):
    from pathlib import Path

    files = sorted((Path(__file__).resolve().parents[1] / "design" / "scenes").glob("*.toml"))
    assert len(files) >= 2
    for f in files:
        sc = Scene.from_toml(f)
        assert SceneSimulator(design, sc).scan(0.0, 0.0).range_m.shape == (design.lidar.n_steps,)
    # the file form of the paper's scene is the built-in, number for number
    assert Scene.from_toml(files[[f.stem for f in files].index("paper-tracking")]) == \
        builtin_scene("paper-tracking")


def test_builtin_scenes(design):
    tr = builtin_scene("paper-tracking")
    traj = tr.movers[0].trajectory
    assert traj.speed_m_s == 0.13
    u = np.subtract(traj.end_m, traj.start_m)
    assert_allclose(math.degrees(math.atan2(u[1], u[0])), 89.4, atol=1e-9)
    assert 0.15 <= tr.movers[0].shape.radius_m <= 0.2
    # the cylinder stays 1.5..2.5 m in front of the sensor over a back-and-forth cycle
    pos = traj.position(np.linspace(0, 2 * traj.leg_s, 200))
    rng_ = np.linalg.norm(pos[:, :2] - np.array(tr.sensor.position_m[:2]), axis=1)
    assert rng_.min() >= 1.5 and rng_.max() <= 2.5
    # the sensor sees it through the mirrors: some reflected beams hit the cylinder
    s = SceneSimulator(design, tr).scan(0.0, 0.0, noise=False)
    assert np.sum((s.object_id == 1) & (s.mirror >= 0)) > 10
    assert np.sum((s.object_id == 1) & (s.mirror < 0)) > 5
    room_sim = SceneSimulator(design, "room")
    room = room_sim.scan(0.0, 0.0, 1.0, 1.0)
    assert np.all(np.isfinite(room.range_m))  # closed room: every beam returns
    ahead = room.steps == design.lidar.step_front
    # straight ahead (0.4 m up) is box2 (top at 0.5 m, yawed -30 deg around (4, -0.2))
    box = room_sim.scene.statics[3]
    assert room_sim.part_names[room.part[ahead][0]] == box.name == "box2"
    c, s_ = math.cos(box.yaw_rad), math.sin(box.yaw_rad)
    q = room.point_world[ahead][0] - np.array(box.center_m)
    local = np.array([c * q[0] + s_ * q[1], -s_ * q[0] + c * q[1], q[2]])
    # the hit lies on the box surface: inside its extents, on one face
    assert np.all(np.abs(local) <= np.array(box.size_m) / 2 + 1e-9)
    assert np.isclose(np.abs(local) - np.array(box.size_m) / 2, 0.0, atol=1e-9).any()
    assert len(load_scene(None).statics) == len(builtin_scene("room").statics)
