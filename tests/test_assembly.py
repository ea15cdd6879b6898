"""3D assembly against independent references: the simulator's ray-traced ground truth hit
points, a wall at a known pose, a hand-written beam-time formula and a linear nod ramp."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from nodlidar.errors import ParameterError
from nodlidar.geometry import rot_y
from nodlidar.paper import TABLE_I_PERTURBATIONS
from nodlidar.runtime.actuators import MirrorLiftProfile, NodProfile
from nodlidar.runtime.assembly import (
    AngleSamples,
    AssemblyModel,
    PoseTrack,
    ScanBatch,
    assemble,
    mirror_state,
)
from nodlidar.sim.raycast import SceneSimulator
from nodlidar.sim.scene import SensorPose, builtin_scene, wall_scene
from nodlidar.solver import solve
from nodlidar.spec import load_design

ROOT = Path(__file__).resolve().parents[1]
DESIGN = solve(load_design(ROOT / "design" / "urg04lx-paper.toml"))
LIDAR = DESIGN.lidar
T_SCAN = LIDAR.scan_period_s
PROFILE = NodProfile(-0.3, 0.3, 0.5)  # ramp up for 1.2 s from t = 0


def nod_samples(t_end: float = 1.2, dt: float = 0.02):
    """Samples of the rising ramp every ``dt`` (linear between them: interpolation exact)."""
    t = np.arange(0.0, t_end + 1e-9, dt)
    return t, PROFILE.angle_at(t)


def simulate(sim: SceneSimulator, n: int, t0: float = 0.1, lift_left=0.0, lift_right=0.0,
             true_ranges: bool = True):
    """``n`` scans with the ramp evaluated at every beam's own time (the sim's truth)."""
    truths = []
    for k in range(n):
        ts = t0 + k * T_SCAN
        tb = sim.beam_times(ts)
        truths.append(sim.scan(ts, PROFILE.angle_at(tb), lift_left, lift_right, noise=False))
    key = "true_range_m" if true_ranges else "range_m"
    batch = ScanBatch.from_arrays(LIDAR.steps, np.stack([getattr(t, key) for t in truths]),
                                  t0 + np.arange(n) * T_SCAN)
    return batch, truths


def test_matches_simulator_truth_world_frame_moving_robot():
    """Room scene, Table I mirrors (calibration = the truth), the robot driving at 0.4 m/s
    with a yawed sensor mount: every assembled point equals the simulator's hit point."""
    yaw, v = 0.3, (0.4, 0.1, 0.0)
    scene = dataclasses.replace(builtin_scene("room"),
                                sensor=SensorPose((0.2, -0.1, 0.4), yaw, v, 0.0))
    sim = SceneSimulator(DESIGN, scene, TABLE_I_PERTURBATIONS)
    batch, truths = simulate(sim, 6)
    # robot_from_sensor: sensor 0.25 m ahead of and 0.3 m above the robot origin, yawed
    robot_from_sensor = np.eye(4)
    robot_from_sensor[:3, :3] = SensorPose((0, 0, 0), yaw).rotation
    robot_from_sensor[:3, 3] = (0.25, 0.0, 0.3)
    # world_from_robot(t) = world_from_sensor(t) @ inv(robot_from_sensor), every 0.1 s
    tp = np.arange(0.0, 1.01, 0.1)
    world_from_sensor = np.zeros((len(tp), 4, 4))
    world_from_sensor[:, :3, :3] = scene.sensor.rotation
    world_from_sensor[:, :3, 3] = np.array(scene.sensor.position_m) + np.outer(tp, v)
    world_from_sensor[:, 3, 3] = 1
    poses = PoseTrack(tp, world_from_sensor @ np.linalg.inv(robot_from_sensor))
    model = AssemblyModel.from_design(DESIGN, TABLE_I_PERTURBATIONS, "table-1")
    pc = assemble(model, batch, nod_samples(), frame="world",
                  robot_from_sensor=robot_from_sensor, world_from_robot=poses)
    truth = np.concatenate([t.point_world for t in truths])
    steps = np.concatenate([t.steps for t in truths])
    clear = model.clear[steps - DESIGN.lidar.step_min]
    # the simulator does not model the lidar housing; assembly drops beams whose (perturbed)
    # reflection crosses it, as blocked (Table I turns L1 so that step 722's does): those
    # are the only simulated hits assembly may drop
    from nodlidar.verify import HOUSING, verify
    blocker = verify(DESIGN, dict(TABLE_I_PERTURBATIONS)).blocker[steps - DESIGN.lidar.step_min]
    assert np.all(blocker[np.isfinite(truth[:, 0]) & ~clear] == HOUSING)
    hit = np.isfinite(truth[:, 0]) & clear
    assert len(pc) == hit.sum() > 3000
    assert pc.meta["blocked"] >= (np.isfinite(truth[:, 0]) & ~clear).sum()
    # exact ranges, a linear ramp and a constant velocity are all reproduced exactly by the
    # linear interpolations; what is left is float rounding (~1e-15 m)
    assert_allclose(pc.xyz, truth[hit], atol=1e-9, rtol=0)
    assert_array_equal(pc.mirror, np.concatenate([t.mirror for t in truths])[hit])
    assert set(np.unique(pc.mirror)) == {-1, 0, 1, 2, 3}
    assert_allclose(pc.t, np.concatenate([t.t_s for t in truths])[hit], atol=1e-12, rtol=0)
    assert pc.calibration_id == "table-1" and pc.frame == "world"


def test_shadowed_beams_are_dropped_as_blocked():
    """The design's shadowed steps (their reflection meets another mirror) are exactly the
    steps the runtime's model calls not clear, the simulator returns nothing for them, and
    assembly counts them as blocked instead of projecting them on one reflection."""
    model = AssemblyModel.from_design(DESIGN)
    lid = DESIGN.lidar
    assert len(DESIGN.shadowed_steps) == 20   # 616..625 and 143..152 (design file)
    assert_array_equal(lid.steps[~model.clear], DESIGN.shadowed_steps)
    sim = SceneSimulator(DESIGN, wall_scene(2.0))
    batch, truths = simulate(sim, 2)
    sh = DESIGN.shadowed_steps - lid.step_min
    assert all(not np.isfinite(t.range_m[sh]).any() for t in truths)
    pc = assemble(model, batch, nod_samples())
    assert not np.isin(pc.step, DESIGN.shadowed_steps).any()
    # a real sensor may see the back of the shadowing glass: a range on those beams is
    # dropped and counted as blocked, not projected
    r = np.stack([t.true_range_m for t in truths])
    r[:, sh] = 0.07
    pc2 = assemble(model, ScanBatch.from_arrays(lid.steps, r, batch.scan_time_s), nod_samples())
    assert pc2.meta["blocked"] == 2 * len(sh) and len(pc2) == len(pc)


def test_beam_times_and_per_beam_nod_vs_linear_ramp():
    """Beam time = scan stamp + step x 97.65625 us (URG-04LX, written out by hand here), and
    each beam gets the ramp's angle at its own time, not its scan's."""
    sim = SceneSimulator(DESIGN, wall_scene(2.0))
    batch, truths = simulate(sim, 3)
    model = AssemblyModel.from_design(DESIGN)
    pc = assemble(model, batch, nod_samples(dt=0.05))
    t_hand = 0.1 + pc.scan * 0.1 + pc.step * (0.1 / 1024)
    assert_allclose(pc.t, t_hand, atol=1e-12, rtol=0)  # float rounding only
    expected = model.deployed.points(pc.step, pc.range_m, PROFILE.angle_at(t_hand))
    assert_allclose(pc.xyz, expected, atol=1e-12, rtol=0)
    # the cloud keeps each beam's nod angle: the ramp's at the hand-written time
    assert_allclose(pc.nod_rad, PROFILE.angle_at(t_hand), atol=1e-12, rtol=0)
    # the nod turns by 0.5 rad/s x 0.0666 s = 33 mrad across one scan's valid steps: using
    # the scan's time for every beam would misplace far beams by centimetres
    coarse = model.deployed.points(pc.step, pc.range_m, PROFILE.angle_at(0.1 + pc.scan * 0.1))
    assert np.abs(coarse - pc.xyz).max() > 0.03


@pytest.mark.parametrize("calibrated", [True, False])
def test_wall_at_known_pose_direct_and_reflected(calibrated):
    """Ranges rounded to mm like the device (noise off): all points, direct and through
    every mirror, lie on the wall plane within 0.5 mm - when the calibration (here the true
    Table I errors) is applied; the nominal model puts some mirrors' points off the wall."""
    d, yaw = 1.5, 0.15
    sim = SceneSimulator(DESIGN, wall_scene(d, yaw, size_m=(20.0, 8.0)), TABLE_I_PERTURBATIONS)
    batch, _ = simulate(sim, 8, true_ranges=False)
    model = AssemblyModel.from_design(DESIGN, TABLE_I_PERTURBATIONS if calibrated else None)
    pc = assemble(model, batch, nod_samples())
    n = np.array([math.cos(yaw), math.sin(yaw), 0.0])
    resid = pc.xyz @ n - d
    for m in range(-1, 4):
        sel = pc.mirror == m
        assert sel.sum() > 100
        worst = np.abs(resid[sel]).max()
        if calibrated:
            # mm rounding moves a point <= 0.5 mm along its ray, so <= 0.5 mm off the plane
            assert worst <= 0.5e-3 + 1e-9, (m, worst)
        else:
            # Table I errors are cm-level at 1.5 m; the nominal model also calls some beams
            # direct that the turned mirrors actually catch (so m = -1 is off too)
            assert worst > 5e-3, (m, worst)


def test_mirror_lift_states_per_side():
    """Left side lifted (its beams go straight, mirror id -1), right side deployed; then the
    left side lifting during the scans: beams while it moves are dropped and counted."""
    sim = SceneSimulator(DESIGN, wall_scene(1.5, size_m=(20.0, 8.0)))
    model = AssemblyModel.from_design(DESIGN)
    left_ids = [i for i, m in enumerate(DESIGN.mirrors) if m.side == "L"]
    batch, truths = simulate(sim, 3, lift_left=1.0)
    up = model.lift_left.lifted_rad  # the design's lifted servo angle of the left side
    lifted = (np.array([0.0, 5.0]), np.full(2, up))
    pc = assemble(model, batch, nod_samples(), mirror_left=lifted)
    truth = np.concatenate([t.point_world for t in truths])
    hit = np.isfinite(truth[:, 0])
    assert_allclose(pc.xyz, truth[hit], atol=1e-9, rtol=0)
    assert not np.isin(pc.mirror, left_ids).any() and np.isin(pc.mirror, [2, 3]).any()
    # lifted = exactly the beams of the left window's steps (the design's map, independently)
    left_steps = np.isin(DESIGN.mirror_of_step[pc.step - LIDAR.step_min], left_ids)
    assert_array_equal(pc.lifted, left_steps)

    # the left servo moves from deployed to lifted between t1 and t2 (inside scan 1)
    t1, t2 = 0.22, 0.25
    moving = (np.array([0.0, t1, t2, 5.0]), np.array([0.0, 0.0, up, up]))
    batch, _ = simulate(sim, 3)
    pc = assemble(model, batch, nod_samples(), mirror_left=moving)
    # independently: beams of left mirrors whose interpolated servo angle is more than the
    # tolerance (3 ticks) away from both ends
    tb = LIDAR.beam_time_s(batch.scan_time_s[batch.scan], batch.steps)
    ang = np.clip((tb - t1) / (t2 - t1), 0, 1) * up
    tol = 3 * 2 * math.pi / 4096
    on_left = np.isin(DESIGN.mirror_of_step[batch.steps - LIDAR.step_min], left_ids)
    between = on_left & (np.abs(ang) > tol) & (np.abs(ang - up) > tol) & np.isfinite(batch.ranges_m)
    assert pc.meta["mirror_moving"] == between.sum() > 10
    assert np.isin(pc.mirror[pc.t < t1], left_ids).any()
    assert not np.isin(pc.mirror[pc.t > t2], left_ids).any()


def test_error_codes_and_uncovered_beams_dropped():
    sim = SceneSimulator(DESIGN, wall_scene(1.5))
    batch, _ = simulate(sim, 4)
    r = batch.ranges_m.copy()
    r[::7] = np.nan  # error codes arrive as NaN from the driver
    batch = dataclasses.replace(batch, ranges_m=r)
    model = AssemblyModel.from_design(DESIGN)
    t_nod, a_nod = nod_samples()
    keep = t_nod <= 0.35  # samples end inside scan 2: later beams have no nod angle
    pc = assemble(model, batch, (t_nod[keep], a_nod[keep]))
    tb = LIDAR.beam_time_s(batch.scan_time_s[batch.scan], batch.steps)
    valid = np.isfinite(r)
    assert pc.meta["error_codes"] == (~valid).sum()
    assert pc.meta["no_nod"] == (valid & (tb > t_nod[keep][-1])).sum() > 0
    assert len(pc) == (valid & (tb <= t_nod[keep][-1])).sum()
    assert np.isfinite(pc.xyz).all()


def test_robot_frame_is_robot_from_sensor_applied():
    sim = SceneSimulator(DESIGN, wall_scene(1.5))
    batch, _ = simulate(sim, 2)
    model = AssemblyModel.from_design(DESIGN)
    T = np.eye(4)
    T[:3, :3] = rot_y(0.2)
    T[:3, 3] = (0.1, -0.2, 0.5)
    s = assemble(model, batch, 0.05)
    r = assemble(model, batch, 0.05, frame="robot", robot_from_sensor=T)
    assert_allclose(r.xyz, s.xyz @ T[:3, :3].T + T[:3, 3], atol=1e-12, rtol=0)
    w = assemble(model, batch, 0.05, frame="world", robot_from_sensor=T,
                 world_from_robot=np.eye(4))
    assert_allclose(w.xyz, r.xyz, atol=1e-12, rtol=0)


def test_mirror_state_thresholds():
    p = MirrorLiftProfile(0.0, math.pi / 2)
    tol = 3 * 2 * math.pi / 4096
    got = mirror_state(np.array([0.0, 0.9 * tol, 1.1 * tol, 1.0, math.pi / 2 - 0.9 * tol, np.nan]), p)
    assert_array_equal(got, [0, 0, 2, 2, 1, 2])


def test_bad_input():
    sim = SceneSimulator(DESIGN, wall_scene(1.5))
    batch, _ = simulate(sim, 1)
    model = AssemblyModel.from_design(DESIGN)
    with pytest.raises(ParameterError, match="frame"):
        assemble(model, batch, 0.0, frame="map")
    with pytest.raises(ParameterError, match="robot_from_sensor"):
        assemble(model, batch, 0.0, frame="robot")
    with pytest.raises(ParameterError, match="robot_from_sensor"):
        assemble(model, batch, 0.0, frame="robot", robot_from_sensor=2 * np.eye(4))
    with pytest.raises(ParameterError, match="world_from_robot"):
        assemble(model, batch, 0.0, frame="world", robot_from_sensor=np.eye(4))
    flip = np.diag([1.0, 1.0, -1.0, 1.0])  # a reflection: orthonormal, det -1
    with pytest.raises(ParameterError, match=r"det\(world_from_robot\(t\)\[1\]"):
        assemble(model, batch, 0.0, frame="world", robot_from_sensor=np.eye(4),
                 world_from_robot=lambda t: np.where(np.arange(len(t))[:, None, None] == 1,
                                                     flip, np.eye(4)))
    with pytest.raises(ParameterError, match="mirror state"):
        assemble(model, batch, 0.0, mirror_left="half")


def test_old_transform_keywords_refused_with_hint():
    """robot2sensor/world2robot were renamed: the old keywords answer with the new name
    and its meaning, never silently ignored or mapped (they read the wrong way round)."""
    sim = SceneSimulator(DESIGN, wall_scene(1.5))
    batch, _ = simulate(sim, 1)
    model = AssemblyModel.from_design(DESIGN)
    with pytest.raises(TypeError, match="robot2sensor was renamed robot_from_sensor "
                                        r"\(it maps sensor coordinates into the robot frame\)"):
        assemble(model, batch, 0.0, frame="robot", robot2sensor=np.eye(4))
    with pytest.raises(TypeError, match="world2robot was renamed world_from_robot"):
        assemble(model, batch, 0.0, frame="world", robot_from_sensor=np.eye(4),
                 world2robot=np.eye(4))
    with pytest.raises(TypeError, match="unexpected keyword argument 'robot_frm_sensor'"):
        assemble(model, batch, 0.0, robot_frm_sensor=np.eye(4))
    with pytest.raises(TypeError, match="world2robot was renamed world_from_robot"):
        PoseTrack([0.0], world2robot=np.eye(4)[None])
    track = PoseTrack(t_s=[0.0], world_from_robot=np.eye(4)[None])
    assert_allclose(track.apply([0.0], np.ones((1, 3))), np.ones((1, 3)), atol=0, rtol=0)
    with pytest.raises(TypeError, match="world_from_robot"):
        PoseTrack([0.0])
    # the old attribute answers too, and any other missing one as Python would
    with pytest.raises(AttributeError, match="world2robot was renamed world_from_robot"):
        track.world2robot  # noqa: B018
    with pytest.raises(AttributeError, match="no attribute 'world_frm_robot'"):
        track.world_frm_robot  # noqa: B018
    import copy
    import pickle

    assert_allclose(pickle.loads(pickle.dumps(track)).t_s, track.t_s)  # __getattr__ safe
    assert_allclose(copy.deepcopy(track).world_from_robot, track.world_from_robot)


def test_pose_track_checks_every_pose():
    """Each keyframe goes through frames.check_transform: a reflection or a scaled
    rotation anywhere in the track is refused, naming its index."""
    T = np.tile(np.eye(4), (3, 1, 1))
    T[2, :3, :3] = np.diag([1.0, -1.0, 1.0])
    with pytest.raises(ParameterError, match=r"det\(world_from_robot\[2\]"):
        PoseTrack([0.0, 1.0, 2.0], T)
    T[2, :3, :3] = 1.01 * np.eye(3)
    with pytest.raises(ParameterError, match=r"world_from_robot\[2\]\[:3, :3\]"):
        PoseTrack([0.0, 1.0, 2.0], T)
    with pytest.raises(ParameterError, match="poses.shape"):
        PoseTrack([0.0, 1.0], np.tile(np.eye(4), (3, 1, 1)))


def test_pose_track_matches_scipy_slerp():
    """The written-out slerp against scipy's Slerp (an independent implementation); the
    translation is linear; queries outside the poses clamp."""
    from scipy.spatial.transform import Rotation, Slerp

    rng = np.random.default_rng(3)
    ts = np.sort(rng.uniform(0, 10, 8))
    rots = Rotation.random(8, random_state=4)
    T = np.tile(np.eye(4), (8, 1, 1))
    T[:, :3, :3] = rots.as_matrix()
    T[:, :3, 3] = rng.normal(size=(8, 3))
    q = np.concatenate([rng.uniform(-1, 11, 1000), ts])
    got = PoseTrack(ts, T).at(q)
    qc = np.clip(q, ts[0], ts[-1])
    # both are exact slerps: agreement to float rounding
    assert_allclose(got[:, :3, :3], Slerp(ts, rots)(qc).as_matrix(), atol=1e-12, rtol=0)
    for j in range(3):
        assert_allclose(got[:, j, 3], np.interp(qc, ts, T[:, j, 3]), atol=1e-12, rtol=0)
    assert_allclose(got[-8:], T, atol=1e-12, rtol=0)  # at the keyframes: the poses
    # apply(): the same poses on points without the (n, 4, 4) matrices
    pts = rng.normal(0, 3, (q.size, 3))
    want = np.einsum("nij,nj->ni", got[:, :3, :3], pts) + got[:, :3, 3]
    assert_allclose(PoseTrack(ts, T).apply(q, pts), want, atol=1e-12, rtol=0)
    one = PoseTrack(ts[:1], T[:1])
    assert_allclose(one.apply(q, pts), pts @ T[0, :3, :3].T + T[0, :3, 3], atol=1e-12, rtol=0)


def test_calibrated_range_model_puts_points_back_on_the_truth():
    """A lidar that reads ``(1 + s) r + o`` (the calibration file's range model, as the
    intrinsics fit and calibration.synthetic.with_range_error define it): assembled with a
    calibration carrying (o, s), every point is the simulator's true hit again; without it,
    points sit centimetres off."""
    from nodlidar.calibration.calfile import CalibratedPerturbations

    offset, scale = 0.02, 0.01
    sim = SceneSimulator(DESIGN, builtin_scene("room"), TABLE_I_PERTURBATIONS)
    batch, truths = simulate(sim, 3)
    measured = dataclasses.replace(batch, ranges_m=(1 + scale) * batch.ranges_m + offset)
    cal = CalibratedPerturbations(TABLE_I_PERTURBATIONS, (), offset, scale)
    model = AssemblyModel.from_design(DESIGN, cal, "cal-range")
    pc = assemble(model, measured, nod_samples())
    truth = np.concatenate([t.point_world for t in truths])
    hit = np.isfinite(truth[:, 0])
    assert len(pc) == hit.sum() > 1000
    # exact arithmetic up to float rounding of the inversion (~1e-15 relative)
    assert_allclose(sim.scene.sensor.to_world(pc.xyz, pc.t), truth[hit], atol=1e-9, rtol=0)
    assert_allclose(pc.range_m, batch.ranges_m[np.isfinite(batch.ranges_m)], atol=1e-12, rtol=0)
    plain = assemble(AssemblyModel.from_design(DESIGN, TABLE_I_PERTURBATIONS), measured,
                     nod_samples())
    off = np.linalg.norm(sim.scene.sensor.to_world(plain.xyz, plain.t) - truth[hit], axis=1)
    assert off.min() > 0.019  # at least the 2 cm offset


# --- the compiled per-point kernel (nodlidar/runtime/_assembly_kernel.py) ---


def test_kernel_rotation_is_geometry_rotate_columns():
    """The kernel's scalar Rodrigues and half-angle cos/sin against
    geometry.rotate_columns and beams.cos_sin (the numpy forms the kernel must repeat):
    random unit axes, angles over +-pi, vectors up to ~20 m. The same formula in the same
    order agrees to rounding; 1e-12 m on 20 m vectors leaves ~200 ulp for a compiler's
    different rounding and nothing for another formula (a sign or a term wrong is ~1 m)."""
    from nodlidar.beams import cos_sin
    from nodlidar.geometry import rotate_columns
    from nodlidar.runtime import _assembly_kernel as K

    rng = np.random.default_rng(11)
    n = 400
    v = rng.normal(0.0, 5.0, (n, 3))
    k = rng.normal(size=(n, 3))
    k /= np.linalg.norm(k, axis=1)[:, None]
    a = rng.uniform(-np.pi, np.pi, n)
    c, s = cos_sin(a)
    cs = np.array([K.cos_sin(x) for x in a])
    assert_allclose(cs[:, 0], c, atol=1e-15, rtol=0)  # the same three operations
    assert_allclose(cs[:, 1], s, atol=1e-15, rtol=0)
    want = np.stack(rotate_columns(v[:, 0], v[:, 1], v[:, 2], k[:, 0], k[:, 1], k[:, 2], c, s),
                    axis=-1)
    got = np.array([K.rodrigues(*v[i], *k[i], c[i], s[i]) for i in range(n)])
    assert_allclose(got, want, atol=1e-12, rtol=0)
    # and an independent form: the rotation matrix of scipy
    from scipy.spatial.transform import Rotation

    R = Rotation.from_rotvec(k * a[:, None]).as_matrix()
    assert_allclose(got, np.einsum("nij,nj->ni", R, v), atol=1e-12, rtol=0)


def test_assembly_does_not_depend_on_beam_order():
    """The kernel looks up each beam's nod sample interval, lift sample interval and
    keyframe pair starting from the previous beam's (beams come in time order, so that is
    mostly right): the same beams shuffled must give the same points, bitwise (the interval
    holding a time is unique, so each point gets the same arithmetic). World frame from a
    3D pose track, the left side lifting mid-batch, nod extrapolated past its samples."""
    from scipy.spatial.transform import Rotation

    model = AssemblyModel.from_design(DESIGN, TABLE_I_PERTURBATIONS, "table-1")
    rng = np.random.default_rng(5)
    m = 12
    ranges = rng.uniform(0.2, 5.0, (m, LIDAR.n_steps))
    ranges[rng.random(ranges.shape) < 0.05] = np.nan
    batch = ScanBatch.from_arrays(LIDAR.steps, ranges, 0.05 + np.arange(m) * T_SCAN)
    t_nod = np.arange(0.0, 0.9, 0.004)
    nod = (t_nod, 0.3 * np.sin(3 * t_nod))
    up = model.lift_left.lifted_rad
    lifting = (np.array([0.0, 0.4, 0.6, 5.0]), np.array([0.0, 0.0, up, up]))
    tp = np.linspace(-0.2, 1.5, 9)
    T = np.tile(np.eye(4), (len(tp), 1, 1))
    T[:, :3, :3] = Rotation.random(len(tp), random_state=2).as_matrix()
    T[:, :3, 3] = rng.normal(size=(len(tp), 3))
    kw = dict(mirror_left=lifting, frame="world", robot_from_sensor=np.eye(4),
              world_from_robot=PoseTrack(tp, T), nod_outside="extrapolate")
    a = assemble(model, batch, nod, **kw)
    order = rng.permutation(batch.steps.size)
    shuffled = ScanBatch(batch.steps[order], batch.ranges_m[order], batch.scan[order],
                         batch.scan_time_s)
    b = assemble(model, shuffled, nod, **kw)
    assert a.meta == b.meta and a.meta["mirror_moving"] > 0 and a.meta["blocked"] > 0
    ia = np.lexsort((a.step, a.scan))
    ib = np.lexsort((b.step, b.scan))
    for name in ("xyz", "t", "range_m", "nod_rad", "step", "scan", "mirror", "lifted"):
        assert_array_equal(getattr(a, name)[ia], getattr(b, name)[ib], err_msg=name)


def test_kernel_bad_input_named():
    """What the kernel would read unchecked is checked first: a scan index outside the
    scan times, lift samples without a sample."""
    model = AssemblyModel.from_design(DESIGN)
    batch = ScanBatch.from_arrays(LIDAR.steps, np.ones((2, LIDAR.n_steps)), [0.0, 0.1])
    bad = dataclasses.replace(batch, scan=batch.scan + 1)
    with pytest.raises(ParameterError, match=r"scans.scan.*0\.\.1"):
        assemble(model, bad, 0.0)
    with pytest.raises(ParameterError, match="lift samples"):
        assemble(model, batch, 0.0, mirror_left=(np.zeros(0), np.zeros(0)))
    with pytest.raises(ParameterError, match="nod samples"):
        assemble(model, batch, (np.array([0.0]), np.array([0.1])), nod_outside="extrapolate")


def test_numba_loaded_by_assembling_only():
    """Reading clouds and importing the assembly module load no numba (the CLI's other
    commands stay light); the first assembly does."""
    import subprocess
    import sys

    code = ("import sys, numpy as np, nodlidar.runtime.cloud, nodlidar.runtime.assembly as A\n"
            "print('numba' in sys.modules)\n"
            "A.PoseTrack([0.0], np.eye(4)[None]).apply([0.0], np.zeros((1, 3)))\n"
            "print('numba' in sys.modules)\n")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       timeout=120, cwd=ROOT)
    assert p.returncode == 0, p.stderr[-2000:]
    assert p.stdout.split() == ["False", "True"]


def test_kernel_interpolation_is_interpolate_angle():
    """AngleSamples.at runs the kernel's per-beam interpolation: against
    servo_angles.interpolate_angle (numpy's np.interp plus the end-segment lines) in all
    three modes, on unsorted queries inside, outside, on the sample times and NaN. The
    same formula: 1e-12 rad on angles of ~1 rad is rounding only."""
    from nodlidar.runtime.assembly import AngleSamples
    from nodlidar.runtime.servo_angles import interpolate_angle

    rng = np.random.default_rng(8)
    ts = np.cumsum(rng.uniform(0.001, 0.02, 200))
    a = np.cumsum(rng.normal(0, 0.05, 200))
    q = np.concatenate([rng.uniform(ts[0] - 0.3, ts[-1] + 0.3, 3000), ts, [np.nan]])
    rng.shuffle(q)
    smp = AngleSamples.of((ts, a))
    for mode in ("nan", "clamp", "extrapolate"):
        want = interpolate_angle(ts, a, q, outside=mode)
        got = smp.at(q, mode)
        assert_array_equal(np.isnan(got), np.isnan(want), err_msg=mode)
        assert_allclose(got, want, atol=1e-12, rtol=0, err_msg=mode)
    assert_array_equal(smp.at(q[:3000].reshape(3, 1000)), smp.at(q[:3000]).reshape(3, 1000))
    one = AngleSamples.of(([1.0], [0.2]))
    assert_allclose(one.at([0.5, 1.0, 1.5], "nan"), [np.nan, 0.2, np.nan])
    assert_allclose(one.at([0.5, 1.0, 1.5], "clamp"), [0.2, 0.2, 0.2])
    with pytest.raises(ParameterError, match="samples"):
        one.at([1.0], "extrapolate")


def test_kernel_signature_does_not_change_with_array_layout():
    """Read-only, strided or int32 inputs (a buffer, a view, a driver's dtype) are made
    plain before the kernel: the same points and no new compiled signature (each would be
    another multi-second compilation in the middle of a run)."""
    from nodlidar.runtime import _assembly_kernel as K

    model = AssemblyModel.from_design(DESIGN)
    rng = np.random.default_rng(9)
    batch = ScanBatch.from_arrays(LIDAR.steps, rng.uniform(0.2, 5.0, (3, LIDAR.n_steps)),
                                  [0.1, 0.2, 0.3])
    nod = (np.arange(0.0, 0.6, 0.01), np.linspace(-0.2, 0.2, 60))
    ref = assemble(model, batch, nod)
    n_sig = len(K.assemble_points.signatures)
    r = np.repeat(batch.ranges_m, 2)[::2]  # strided view
    r.setflags(write=False)
    odd = ScanBatch(batch.steps.astype(np.int32), r, batch.scan, batch.scan_time_s)
    t_nod = np.repeat(nod[0], 2)[::2]
    t_nod.setflags(write=False)
    got = assemble(model, odd, AngleSamples(t_nod, nod[1]))  # as given: not re-sorted
    assert len(K.assemble_points.signatures) == n_sig
    assert_array_equal(got.xyz, ref.xyz)  # the same arithmetic on the same numbers


def test_kernel_projection_is_beam_model_points():
    """The kernel's projection and nod against BeamModel.points (the numpy projection of
    BeamColumns.project, used outside the assembly) on the kept beams: deployed and
    lifted sides, ranges short of the mirror, the Table I perturbed model. The
    same formula in the same order: 1e-12 m on points of a few metres is rounding only."""
    model = AssemblyModel.from_design(DESIGN, TABLE_I_PERTURBATIONS, "table-1")
    rng = np.random.default_rng(12)
    ranges = rng.uniform(0.2, 5.0, (4, LIDAR.n_steps))
    tm = model.deployed.t_mirror
    short = (rng.random(ranges.shape) < 0.1) & (tm > 0)
    ranges[short] = (tm * np.ones((4, 1)))[short] * 0.5
    batch = ScanBatch.from_arrays(LIDAR.steps, ranges, 0.1 + np.arange(4) * T_SCAN)
    up = model.lift_right.lifted_rad
    pc = assemble(model, batch, nod_samples(), mirror_right=(np.array([0.0, 5.0]), np.full(2, up)))
    assert pc.lifted.any() and (~pc.lifted).any() and (pc.range_m < 0.2).any()
    for lifted, bm in ((False, model.deployed), (True, model.lifted)):
        sel = pc.lifted == lifted
        want = bm.points(pc.step[sel], pc.range_m[sel], pc.nod_rad[sel])
        assert_allclose(pc.xyz[sel], want, atol=1e-12, rtol=0)


_LIVE_AFTER_WARM_UP = r"""
import sys
import numpy as np
from nodlidar.runtime import _assembly_kernel as K
from nodlidar.runtime.assembly import AssemblyModel, PoseTrack, ScanBatch, assemble, warm_up
from nodlidar.solver import solve
from nodlidar.spec import load_design

model = AssemblyModel.from_design(solve(load_design(sys.argv[1])))
assert not K.assemble_points.signatures
warm_up(model)
n_sig = len(K.assemble_points.signatures)
lidar = model.lidar
rng = np.random.default_rng(3)
batch = ScanBatch.from_arrays(lidar.steps, rng.uniform(0.2, 5.0, (4, lidar.n_steps)),
                              [0.0, 0.1, 0.2, 0.3])
t = np.arange(-0.1, 0.6, 0.002)
nod = (t, 0.3 * np.sin(t))                                     # servo samples, as live
lift = (t, np.linspace(model.lift_left.deployed_rad, model.lift_left.lifted_rad, t.size))
T = np.eye(4)
T[:3, 3] = (0.1, 0.0, 0.3)
poses = PoseTrack([0.0, 0.5], np.stack([np.eye(4), T]))
assemble(model, batch, nod, mirror_left=lift, mirror_right="lifted")
assemble(model, batch, nod, frame="world", robot_from_sensor=T, world_from_robot=poses)
one = ScanBatch(batch.steps[:lidar.n_steps].astype(np.int32), batch.ranges_m[:lidar.n_steps],
                batch.scan[:lidar.n_steps], batch.scan_time_s[:1])      # a bag's one scan
assemble(model, one, nod, nod_outside="clamp")
assert len(K.assemble_points.signatures) == n_sig == 1, K.assemble_points.signatures
print("one signature")
"""


def test_warm_up_compiles_the_one_version_live_captures_use():
    """numba compiles at the first call (3-6 s the first time on a machine): inside a live
    capture that stalled the loop reading the lidar (a first ``nodlidar record`` on an
    empty cache dropped 62 scans). ``warm_up`` (called by Session.open) must leave
    nothing to compile for live-shaped calls: servo samples, lift samples moving, the
    world frame with a pose track, a driver's int32 steps. A fresh interpreter, so no
    earlier test has compiled anything."""
    import subprocess
    import sys

    proc = subprocess.run([sys.executable, "-c", _LIVE_AFTER_WARM_UP,
                           str(ROOT / "design" / "urg04lx-paper.toml")],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "one signature" in proc.stdout
