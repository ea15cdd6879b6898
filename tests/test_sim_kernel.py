"""The simulator's compiled kernels (nodlidar/sim/_kernel.py) against the numpy functions
whose formulas they repeat: geometry's Rodrigues, reflection and nod pitch, the sensor pose,
trimesh's ray preparation for embree, the scene trajectories and the URG measurement.

Tolerances: the kernels perform the same IEEE operations in the same order as the numpy
originals, so they agree to the last bit or within a few ulps where numpy's cos/sin or a
BLAS matrix product may round differently; 1e-12 (m, rad, unitless on O(1) inputs) is
~5000 ulps of 2e-16, tight enough that any wrong sign, term or axis fails by orders of
magnitude. The embree rays must be bit-identical (``assert_array_equal``): a different
float32 ray could hit another triangle at an edge.
"""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from nodlidar import geometry
from nodlidar.sim import _kernel as K
from nodlidar.sim.scene import BackAndForth, ConstantVelocity, Fixed, SensorPose


def _unit_rows(rng, n):
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def test_rodrigues_kernel_is_geometry_rotate_about_axis():
    rng = np.random.default_rng(1)
    v = rng.normal(size=(500, 3)) * 3
    k = _unit_rows(rng, 500)
    a = rng.uniform(-np.pi, np.pi, 500)
    got = K.rodrigues(v, k, np.cos(a), np.sin(a))
    assert_allclose(got, geometry.rotate_about_axis(v, k, a), rtol=0, atol=1e-12)
    # and it is a rotation, not just the same wrong formula: the matrix form agrees
    ref = np.array([geometry.matrix_from_axis_angle(k[i], a[i]) @ v[i] for i in range(20)])
    assert_allclose(got[:20], ref, rtol=0, atol=1e-12)


def test_reflect_kernel_is_geometry_reflect():
    rng = np.random.default_rng(2)
    d = _unit_rows(rng, 500)
    n = _unit_rows(rng, 500)
    assert_allclose(K.reflect(d, n), geometry.reflect(d, n), rtol=0, atol=1e-12)


def test_mirror_rays_turn_back_as_geometry_does():
    """mirror_rays' rotation of rays into the unturned glass frame and of the normal out of
    it: geometry.rotate_about_line / rotate_about_axis by -angle / +angle."""
    rng = np.random.default_rng(3)
    n = 300
    o = rng.normal(size=(n, 3)) * 0.1
    d = _unit_rows(rng, n)
    point = np.array([0.05, -0.02, 0.03])
    axis = _unit_rows(rng, 1)[0]
    normal = _unit_rows(rng, 1)[0]
    ang = rng.uniform(-1.0, 1.0, n)
    alive = np.ones(n, dtype=bool)
    last = np.full(n, -1)
    big = 1e12  # squared radius [m^2]: every ray meets both spheres
    idx, ol, dl, nrm, o32, d32 = K.mirror_rays(o, d, alive, last, 0, np.zeros(3), big, point,
                                              axis, np.cos(ang), np.sin(ang), normal,
                                              np.zeros(3), big, np.zeros(3), 1.0)
    assert_array_equal(idx, np.arange(n))
    assert_allclose(ol, geometry.rotate_about_line(o, point, axis, -ang), rtol=0, atol=1e-12)
    assert_allclose(dl, geometry.rotate_about_axis(d, axis, -ang), rtol=0, atol=1e-12)
    assert_allclose(nrm, geometry.rotate_about_axis(normal, axis, ang), rtol=0, atol=1e-12)
    # rays just reflected by this mirror, or dead, are not cast at it
    last[:10] = 0
    alive[10:20] = False
    idx2 = K.mirror_rays(o, d, alive, last, 0, np.zeros(3), big, point, axis, np.cos(ang),
                         np.sin(ang), normal, np.zeros(3), big, np.zeros(3), 1.0)[0]
    assert_array_equal(idx2, np.arange(20, n))


def test_world_rays_are_the_nod_pitch_then_the_sensor_pose():
    rng = np.random.default_rng(4)
    n = 400
    p_head = rng.normal(size=(n, 3)) * 0.1
    d_head = _unit_rows(rng, n)
    pivot = np.array([0.01, 0.0, -0.05])
    nod = rng.uniform(-0.5, 0.5, n)
    t = np.sort(rng.uniform(0, 5, n))
    pose = SensorPose((0.3, -0.2, 0.4), 0.7, (0.2, 0.1, 0.0), t0_s=1.0)
    o, d, _, _ = K.world_rays(p_head - pivot, d_head, pivot, np.cos(nod), np.sin(nod), t,
                              pose.rotation, np.asarray(pose.position_m),
                              np.asarray(pose.velocity_m_s), pose.t0_s, np.zeros(3), 1.0)
    o_ref = pose.to_world(geometry.pitch_about_pivot(p_head, nod, pivot), t)
    d_ref = geometry.pitch_about_pivot(d_head, nod) @ pose.rotation.T
    assert_allclose(o, o_ref, rtol=0, atol=1e-12)
    assert_allclose(d, d_ref, rtol=0, atol=1e-12)


def test_embree_rays_are_trimesh_intersects_first_rays_bit_for_bit():
    """The float32 rays embree gets are exactly those trimesh's intersects_first passes,
    so the same triangles are hit (checked on a cast, too)."""
    import trimesh
    from trimesh.ray.ray_pyembree import RayMeshIntersector
    from trimesh.util import unitize

    rng = np.random.default_rng(5)
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=1.3)
    mesh.apply_translation([2.0, 0.3, -0.1])
    rmi = RayMeshIntersector(mesh)
    wrap = rmi._scene
    n = 5000
    o = rng.normal(size=(n, 3)) * 0.2
    d = (np.array([2.0, 0.3, -0.1]) + rng.normal(size=(n, 3)) * 0.8) - o
    d *= rng.uniform(0.5, 3.0, (n, 1))  # not unit: unitize's own rounding is part of it
    o32, d32 = K.embree_rays(o, d, np.asarray(wrap.origin, dtype=float), float(wrap.scale))
    ref_o = ((np.array(o, dtype=np.float32).astype(np.float64) - wrap.origin)
             * wrap.scale).astype(np.float32)
    ref_d = unitize(np.array(d, dtype=np.float32)).astype(np.float32)
    assert_array_equal(o32, ref_o)
    assert_array_equal(d32, ref_d)
    tri = wrap.scene.run(o32, d32)
    assert_array_equal(tri, rmi.intersects_first(o, d))
    assert np.mean(tri >= 0) > 0.3  # the cast hits something


@pytest.mark.parametrize("traj", [
    Fixed((1.0, -2.0, 0.5)),
    ConstantVelocity((1.0, 0.5, 0.0), (0.3, -0.2, 0.01), t0_s=2.0),
    BackAndForth((2.5, -1.5, 0.0), (3.5, 1.5, 0.0), 0.5, t0_s=0.7),
])
def test_mover_positions_are_the_scene_trajectories(traj):
    from nodlidar.sim.raycast import _trajectory_kernel_args

    t = np.linspace(-20.0, 40.0, 2001)  # before t0 and over many legs
    kind, p0, p1, leg_s, t0, _ = _trajectory_kernel_args(traj)
    # positions O(5 m) at t up to 40 s: 1e-12 m is a few ulps of the phase arithmetic
    assert_allclose(K.mover_positions(kind, p0, p1, leg_s, t0, t), traj.position(t),
                    rtol=0, atol=1e-12)


def test_mover_swept_precull_keeps_exactly_the_rays_of_the_per_ray_cull():
    """mover_rays first drops rays missing the sphere swept over the rays' time span; the
    rays it keeps must be exactly those of the per-ray test alone (positions given)."""
    from nodlidar.sim.raycast import _trajectory_kernel_args

    rng = np.random.default_rng(6)
    traj = BackAndForth((1.0, -0.5, 0.0), (1.0, 0.5, 0.0), 3.0)  # fast: a wide sweep
    n = 3000
    t = np.sort(rng.uniform(0.0, 0.4, n))  # spans a turnaround (one leg = 1/3 s)
    o = rng.normal(size=(n, 3)) * 0.05
    aim = traj.position(t) + rng.normal(size=(n, 3)) * 0.5
    d = aim - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    centre, r2 = np.array([0.0, 0.0, 0.5]), 0.3 ** 2
    kind, p0, p1, leg_s, t0, speed = _trajectory_kernel_args(traj)
    got = K.mover_rays(o, d, t, kind, p0, p1, leg_s, t0, speed, np.zeros((0, 3)), centre, r2,
                       np.zeros(3), 1.0)
    ref = K.mover_rays(o, d, t, -1, p0, p1, leg_s, t0, speed, traj.position(t), centre, r2,
                       np.zeros(3), 1.0)
    assert 100 < len(ref[0]) < n  # some rays culled, some kept
    for a, b in zip(got, ref, strict=True):
        assert_array_equal(a, b)


def test_measure_kernel_is_the_urg_model():
    """Noise sigma (10 mm to 1 m, 1 % beyond), mm rounding, NaN for no return: the numpy
    formula of LidarModel.range_sigma_m written out here."""
    from nodlidar.lidar import LIDAR_MODELS
    from nodlidar.sim.raycast import measure

    model = LIDAR_MODELS["URG-04LX"]
    r = np.concatenate([np.linspace(0.02, 5.6, 997), [np.nan, np.inf, -np.inf]])
    z = np.random.default_rng(7).standard_normal(r.shape)
    near, knee, rel = model.range_noise
    finite = np.where(np.isfinite(r), r, np.nan)
    sig = np.where(np.nan_to_num(finite) <= knee, near, rel * np.nan_to_num(finite))
    ref = np.round((finite + z * sig) * 1000.0) / 1000.0
    got = measure(r, model, np.random.default_rng(7))  # the same draws
    assert_allclose(got, ref, rtol=0, atol=1e-12, equal_nan=True)
    assert_allclose(measure(r, model, None, noise=False), np.round(finite * 1000) / 1000,
                    rtol=0, atol=1e-12, equal_nan=True)
    assert np.array_equal(np.isnan(got), ~np.isfinite(r))
    # scalars in, scalar out
    assert measure(1.23456, model, None, noise=False) == pytest.approx(1.235, abs=1e-12)


def test_import_nodlidar_does_not_import_numba():
    code = ("import sys, nodlidar, nodlidar.cli; nodlidar.cli.build_parser(); "
            "sys.exit(1 if 'numba' in sys.modules else 0)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr
