"""Tolerance analysis: the [tolerance] table, the batched trace against MirrorPatch.perturbed
and verify, the Monte Carlo's reproducibility (seed, chunks, Dask workers), sensitivities."""

from pathlib import Path

import numpy as np
import pytest
from numpy.testing import assert_allclose

from nodlidar.analysis.tolerance import (
    LidarMount,
    LidarSigma,
    MirrorSigma,
    ToleranceSpec,
    _problem,
    _sample,
    monte_carlo,
    mounted_patches,
    sensitivities,
    tolerance_spec,
    trace_samples,
)
from nodlidar.errors import ParameterError
from nodlidar.geometry import Perturbation, arc_point, bearing_of, reflect_rays
from nodlidar.solver import solve
from nodlidar.spec import load_design
from nodlidar.verify import verify

ROOT = Path(__file__).resolve().parents[1]
PAPER = ROOT / "design" / "urg04lx-paper.toml"


@pytest.fixture(scope="module")
def design():
    return solve(load_design(PAPER))


# --- the [tolerance] table ----------------------------------------------------------------

def test_defaults_when_absent(design):
    tol = tolerance_spec(design.spec.replace(sections={}))   # a design file without [tolerance]
    assert tol == ToleranceSpec()
    assert tol.sigma_for("L1") == MirrorSigma()
    assert tol.lidar == LidarSigma()


def test_parse_overrides_and_round_trip(design):
    table = {"distribution": "uniform", "dalpha_rad": 0.002, "dd_m": 0.0,
             "mirrors": {"L2": {"dbeta_rad": 0.005}},
             "lidar": {"yaw_rad": 0.001, "offset_m": 0.0005},
             "ranges_m": [1, 3], "samples": 50, "seed": 7, "chunk_size": 20}
    tol = tolerance_spec(table)
    assert tol.distribution == "uniform" and tol.ranges_m == (1.0, 3.0)
    # a per-mirror table overrides only the keys it names
    assert tol.sigma_for("L2") == MirrorSigma(0.002, 0.005, 0.0)
    assert tol.sigma_for("R1") == MirrorSigma(0.002, 0.001, 0.0)
    assert_allclose(tol.lidar.as_array(), [0.001, 0, 5e-4, 5e-4, 5e-4, 0.0])
    assert tolerance_spec(tol.to_dict()) == tol
    # and it is read from a design file's [tolerance] table
    spec = design.spec.replace(sections={"tolerance": table})
    assert tolerance_spec(spec) == tol


@pytest.mark.parametrize("table, field", [
    ({"distribution": "cauchy"}, "tolerance.distribution"),
    ({"dalpha_rad": -1e-3}, "tolerance.dalpha_rad"),
    ({"dalpha": 1e-3}, "tolerance.dalpha"),
    ({"mirrors": {"L1": {"dd": 1}}}, "tolerance.mirrors.L1.dd"),
    ({"mirrors": {"L1": {"dd_m": "x"}}}, "tolerance.mirrors.L1.dd_m"),
    ({"lidar": {"spin_rad": 0.1}}, "tolerance.lidar.spin_rad"),
    ({"lidar": {"roll_rad": -0.1}}, "tolerance.lidar.roll_rad"),
    ({"samples": 0}, "tolerance.samples"),
    ({"ranges_m": [0.0]}, "tolerance.ranges_m"),
    ({"percentiles": [101]}, "tolerance.percentiles"),
])
def test_bad_tables_name_the_field(table, field):
    with pytest.raises(ParameterError) as exc:
        tolerance_spec(table)
    assert exc.value.field == field


def test_unknown_mirror_is_an_error(design):
    tol = tolerance_spec({"mirrors": {"L9": {"dd_m": 0.001}}})
    with pytest.raises(ParameterError, match="tolerance.mirrors.L9"):
        monte_carlo(design, tol, samples=2)


# --- the batched trace against the geometry core -----------------------------------------

def test_batch_agrees_with_perturbed_patches_and_verify(design):
    rng = np.random.default_rng(3)
    n = 4
    dm = rng.normal(size=(n, 4, 3)) * [2e-3, 3e-3, 3e-4]
    D = design.design_distance_m
    traces = trace_samples(design, dm, ranges_m=[D])
    lo = design.lidar.step_min
    for k in range(n):
        pert = {m.name: Perturbation.from_array(dm[k, i]) for i, m in enumerate(design.mirrors)}
        v = verify(design, pert)
        for i, (m, tr) in enumerate(zip(design.mirrors, traces, strict=True)):
            idx = m.steps - lo
            caught = v.hit[idx] == i
            # the batch knows which beams fall off their own finite patch; verify also sees
            # a beam that still hits its own patch but meets a neighbour (moved) first
            assert np.all(tr.on_patch[k][caught])
            assert np.all(v.hit[idx][tr.on_patch[k] & ~caught] >= 0)
            # same plane, same reflection: round-off only (a few ulp of ~1 rad)
            assert_allclose(tr.bearing[k, caught, 0], v.bearing_at_d[idx][caught], rtol=0,
                            atol=1e-13)
    assert sum(np.count_nonzero(~t.on_patch) for t in traces) > 0  # the edge case was exercised


def test_batch_lidar_mount_agrees_with_transformed_patches(design):
    rng = np.random.default_rng(4)
    n = 3
    dm = rng.normal(size=(n, 4, 3)) * [1e-3, 1e-3, 1e-4]
    dl = rng.normal(size=(n, 6)) * [2e-3, 2e-3, 5e-4, 5e-4, 5e-4, 2e-3]   # yaw pitch x y z roll
    ranges = [0.5, 4.0]
    traces = trace_samples(design, dm, dl, ranges_m=ranges)
    for k in range(n):
        pert = {m.name: Perturbation.from_array(dm[k, i]) for i, m in enumerate(design.mirrors)}
        patches = mounted_patches(design, pert, LidarMount.from_array(dl[k]))
        for m, p, tr in zip(design.mirrors, patches, traces, strict=True):
            th = design.lidar.bearing_from_step(m.steps)
            d0 = np.stack([np.cos(th), np.sin(th), np.zeros_like(th)], -1)
            _, hit, out = reflect_rays(np.zeros_like(d0), d0, p.origin_, p.normal_)
            for j, r in enumerate(ranges):
                P = arc_point(hit, out, r)
                assert_allclose(tr.points[k, :, j], P, rtol=0, atol=1e-13)
                assert_allclose(tr.bearing[k, :, j], bearing_of(P), rtol=0, atol=1e-13)
            assert_allclose(tr.elevation[k], np.arcsin(out[:, 2]), rtol=0, atol=1e-15)


def test_elevation_is_about_two_dbeta(design):
    # The paper: a tilt dbeta lifts the reflected beam by 2 dbeta. Exactly it is
    # asin(cos(theta_r) sin(2 dbeta)): 2 dbeta at normal incidence only, less at the
    # 10-70 deg these mirrors see.
    dbeta = np.array([-5e-3, 1e-3, 4e-3])
    dm = np.zeros((3, 4, 3))
    dm[:, :, 1] = dbeta[:, None]
    traces = trace_samples(design, dm, ranges_m=[2.0])
    for m, tr in zip(design.mirrors, traces, strict=True):
        th = design.lidar.bearing_from_step(m.steps)
        d0 = np.stack([np.cos(th), np.sin(th), np.zeros_like(th)], -1)
        cos_r = np.abs(d0 @ m.patch.normal_)
        el = np.abs(tr.elevation)
        assert_allclose(el, np.arcsin(cos_r[None] * np.sin(2 * np.abs(dbeta))[:, None]),
                        rtol=1e-9)
        assert np.all(el <= 2 * np.abs(dbeta)[:, None] * (1 + 1e-9))
        # at the most nearly normal beam it is 2 dbeta within (1 - cos theta_r)
        i = np.argmax(cos_r)
        assert_allclose(el[:, i], 2 * np.abs(dbeta), rtol=1 - cos_r[i] + 1e-4)
    # sign: the tilt direction sets up or down, the same for every beam of a mirror
    assert np.all(np.sign(traces[0].elevation[0]) == np.sign(traces[0].elevation[0, 0]))


def test_lidar_roll_tilts_the_two_sides_opposite_ways(design):
    """A roll of the lidar about x is seen as the left mirrors dipping one way and the right
    ones the other: reflected beams leave the scan plane with opposite signs, by about
    2 * roll * |n_y| cos(theta_r) (the roll tilts each vertical mirror by roll * n_y)."""
    from nodlidar.geometry import matrix_from_axis_angle, rot_y, rot_z

    roll = 2e-3
    # the mount rotation is z-y-x (yaw, pitch, roll), right-handed about each axis
    R = LidarMount(yaw=0.3, pitch=-0.2, roll=0.1).rotation()
    assert_allclose(R, rot_z(0.3) @ rot_y(-0.2) @ matrix_from_axis_angle([1.0, 0, 0], 0.1),
                    rtol=0, atol=1e-15)
    dl = np.zeros((1, 6))
    dl[0, 5] = roll
    traces = trace_samples(design, np.zeros((1, 4, 3)), dl, ranges_m=[2.0])
    for m, tr in zip(design.mirrors, traces, strict=True):
        el = tr.elevation[0]
        assert np.all(np.sign(el) == np.sign(el[0])) and np.all(np.abs(el) > 1e-4)
        th = design.lidar.bearing_from_step(m.steps)
        d0 = np.stack([np.cos(th), np.sin(th), np.zeros_like(th)], -1)
        n = m.patch.normal_
        # the batch against the reference path (mounted_patches + reflect_rays)
        assert_allclose(el, np.arcsin(tr_out_z(design, m, roll)), rtol=0, atol=1e-12)
        # first order: in the lidar frame the normal is rot_x(-roll) n = n - roll*n_y*ez, so
        # out_z = 2 roll n_y (d.n); second-order terms are ~roll relative (2e-3)
        assert_allclose(el, 2 * roll * n[1] * (d0 @ n), rtol=5e-3)
    left = [t.elevation[0, 0] for m, t in zip(design.mirrors, traces, strict=True) if m.side == "L"]
    right = [t.elevation[0, 0] for m, t in zip(design.mirrors, traces, strict=True) if m.side == "R"]
    assert np.sign(left[0]) == np.sign(left[1]) == -np.sign(right[0]) == -np.sign(right[1])


def tr_out_z(design, m, roll):
    """z of the reflected direction via the reference path (mounted_patches + reflect_rays)."""
    patch = mounted_patches(design, None, LidarMount(roll=roll))[list(design.mirrors).index(m)]
    th = design.lidar.bearing_from_step(m.steps)
    d0 = np.stack([np.cos(th), np.sin(th), np.zeros_like(th)], -1)
    _, _, out = reflect_rays(np.zeros_like(d0), d0, patch.origin_, patch.normal_)
    return out[:, 2]


def test_roll_column_keeps_the_other_draws_of_a_seed(design):
    """Adding a roll spread changes no other sampled error of a seed (roll is drawn last)."""
    a = _problem(design, tolerance_spec({"lidar": {"yaw_rad": 1e-3, "offset_m": 1e-4}}))
    b = _problem(design, tolerance_spec({"lidar": {"yaw_rad": 1e-3, "offset_m": 1e-4,
                                                   "roll_rad": 1e-3}}))
    dm_a, dl_a = _sample(a, 50, np.random.SeedSequence(3))
    dm_b, dl_b = _sample(b, 50, np.random.SeedSequence(3))
    assert np.array_equal(dm_a, dm_b) and np.array_equal(dl_a[:, :5], dl_b[:, :5])
    assert np.all(dl_a[:, 5] == 0) and dl_b[:, 5].std() > 0


def test_zero_sigma_gives_zero_error(design):
    zero = ToleranceSpec(mirror=MirrorSigma(0.0, 0.0, 0.0), samples=30, chunk_size=16)
    r = monte_carlo(design, zero, workers=0)
    # nominal geometry through the batch and the BeamModel: round-off only
    for k in ("bearing_error_max", "bearing_error_mean", "elevation_max", "height_max"):
        assert np.max(np.abs(getattr(r, k))) < 1e-12, k
    assert np.max(r.range_error_max) < 1e-12
    assert not r.edge_misses.any()


def test_uniform_is_bounded_and_normal_has_the_sigma(design):
    for dist in ("uniform", "normal"):
        tol = tolerance_spec({"distribution": dist, "dalpha_rad": 1e-3, "dbeta_rad": 2e-3,
                              "dd_m": 3e-4, "lidar": {"yaw_rad": 1e-3}})
        prob = _problem(design, tol)
        dm, dl = _sample(prob, 20000, np.random.SeedSequence(1))
        half = np.array([1e-3, 2e-3, 3e-4])
        if dist == "uniform":
            assert np.all(np.abs(dm) <= half)
            assert_allclose(dm.std(axis=(0, 1)), half / np.sqrt(3), rtol=0.02)
        else:
            assert_allclose(dm.std(axis=(0, 1)), half, rtol=0.02)
        assert np.all(dl[:, 1:] == 0) and dl[:, 0].std() > 0


# --- Monte Carlo reproducibility -------------------------------------------------------------

def _same(a, b):
    for k in ("bearing_error_max", "bearing_error_mean", "range_error_max", "height_max",
              "elevation_max", "edge_misses"):
        assert np.array_equal(getattr(a, k), getattr(b, k)), k


def test_reproducible_from_seed_and_chunked(design):
    calls = []
    a = monte_carlo(design, samples=250, chunk_size=100, seed=11, workers=0,
                    progress=lambda d, t: calls.append((d, t)))
    b = monte_carlo(design, samples=250, chunk_size=100, seed=11, workers=0)
    c = monte_carlo(design, samples=250, chunk_size=100, seed=12, workers=0)
    _same(a, b)
    assert not np.array_equal(a.bearing_error_max, c.bearing_error_max)
    assert calls == [(100, 250), (200, 250), (250, 250)]
    assert a.bearing_error_max.shape == (250, 4, 4)
    # the first chunks of a longer run are the same samples
    d = monte_carlo(design, samples=400, chunk_size=100, seed=11, workers=0)
    assert np.array_equal(d.bearing_error_max[:200], a.bearing_error_max[:200])
    rows = a.table()
    assert len(rows) == 4 * 4 and "bearing_err_p95_deg" in rows[0]
    p = a.percentiles("bearing_error_max")
    assert p.shape == (3, 4, 4) and np.all(np.diff(p, axis=0) >= 0)


def test_identical_with_one_or_two_dask_workers(design):
    kw = dict(samples=300, chunk_size=50, seed=5)
    serial = monte_carlo(design, workers=0, **kw)
    one = monte_carlo(design, workers=1, processes=False, **kw)
    seen = []
    two = monte_carlo(design, workers=2, processes=False, progress=lambda d, t: seen.append(d),
                      **kw)
    _same(serial, one)
    _same(serial, two)
    assert sorted(seen) == seen and seen[-1] == 300 and len(seen) == 6


@pytest.mark.slow
def test_identical_with_worker_processes(design):
    kw = dict(samples=400, chunk_size=100, seed=9)
    _same(monte_carlo(design, workers=0, **kw), monte_carlo(design, workers=2, **kw))


def test_existing_cluster_by_address(design):
    from distributed import Client, LocalCluster

    kw = dict(samples=100, chunk_size=50, seed=2)
    with LocalCluster(n_workers=1, processes=False, dashboard_address=None) as cluster:
        r = monte_carlo(design, scheduler=cluster.scheduler_address, **kw)
        with Client(cluster) as client:
            r2 = monte_carlo(design, client=client, **kw)
    _same(r, monte_carlo(design, workers=0, **kw))
    _same(r, r2)


def test_large_runs_go_to_a_local_cluster_by_default(design, monkeypatch):
    """workers=None: in process up to DASK_MIN_SAMPLES samples, a local Dask cluster (one
    worker per CPU) beyond; a scheduler address always goes to that scheduler."""
    import nodlidar.analysis.tolerance as tolmod

    calls = []

    def fake(prob, sizes, seeds, **kw):
        calls.append(kw)
        m, r = len(prob.mirrors), len(prob.ranges)
        for i, n in enumerate(sizes):
            out = {k: np.zeros((n, m, r), np.float32) for k in
                   ("bearing_error_max", "bearing_error_mean", "range_error_max", "height_max")}
            out["elevation_max"] = np.zeros((n, m), np.float32)
            out["edge_misses"] = np.zeros((n, m), np.int32)
            yield i, out

    monkeypatch.setattr(tolmod, "_dask_chunks", fake)
    big = tolmod.DASK_MIN_SAMPLES + 1
    r = monte_carlo(design, samples=big, chunk_size=20000)
    assert len(calls) == 1 and calls[0]["workers"] is None and calls[0]["scheduler"] is None
    assert r.n_samples == big and r.bearing_error_max.shape == (big, 4, 4)
    monte_carlo(design, samples=10, scheduler="tcp://127.0.0.1:1")
    assert len(calls) == 2 and calls[1]["scheduler"] == "tcp://127.0.0.1:1"
    monte_carlo(design, samples=10)          # small: in process, no Dask
    assert len(calls) == 2


def test_own_cluster_workers_keep_glibc_malloc_defaults():
    """Dask's nanny sets MALLOC_TRIM_THRESHOLD_ in workers, which made a chunk 1.6x slower
    in a worker than in this process (benchmarks/bench_tolerance.py); our cluster unsets it."""
    import os

    from distributed import Client

    from nodlidar.analysis.tolerance import _local_cluster

    with _local_cluster(1, processes=True) as cluster, Client(cluster) as client:
        env = client.run(lambda: os.environ.get("MALLOC_TRIM_THRESHOLD_"))
        threads = client.run(lambda: os.environ.get("OMP_NUM_THREADS"))
    assert list(env.values()) == [None]
    assert list(threads.values()) == ["1"]       # the rest of Dask's worker set-up is kept


# --- sensitivities ---------------------------------------------------------------------------

def test_sensitivities_match_closed_forms(design):
    s = sensitivities(design)
    for name in s.mirror_names:
        fd, cf = s.finite_difference[name], s.closed_form[name]
        for p in ("dalpha", "dbeta", "dd", "lidar_yaw", "lidar_x", "lidar_y"):
            # central differences with h = 1e-6: round-off ~1e-16/1e-6 on O(1) values
            scale = max(1.0, float(np.max(np.abs(cf[p]))))
            assert_allclose(fd[p], cf[p], rtol=0, atol=1e-8 * scale, err_msg=f"{name} {p}")
        # a yaw of the mirror about O turns its reflected beams by about twice the angle
        assert np.all(np.abs(fd["dalpha"] - 2) < 0.1)
        # pitching or rolling the lidar tilts beams out of plane; in-plane bearing is
        # unchanged to first order
        assert np.max(np.abs(fd["lidar_pitch"])) < 1e-6
        assert np.max(np.abs(fd["lidar_roll"])) < 1e-6
    rows = s.table()
    assert len(rows) == 4 * 8 and {r["unit"] for r in rows} == {"deg/deg", "deg/mm"}


def test_sensitivity_predicts_small_perturbation(design):
    # first-order check of the whole chain: bearing change ~ sum of sensitivity * error
    s = sensitivities(design)
    p = np.array([2e-5, 3e-5, 4e-6])
    dm = np.tile(p, (1, 4, 1))
    tr = trace_samples(design, dm, ranges_m=[design.design_distance_m])
    base = trace_samples(design, np.zeros((1, 4, 3)), ranges_m=[design.design_distance_m])
    for i, m in enumerate(design.mirrors):
        fd = s.finite_difference[m.name]
        pred = fd["dalpha"] * p[0] + fd["dbeta"] * p[1] + fd["dd"] * p[2]
        got = tr[i].bearing[0, :, 0] - base[i].bearing[0, :, 0]
        assert_allclose(got, pred, rtol=1e-3, atol=1e-10)


def test_trace_mirror_is_the_perturbed_patch_traced_per_sample(design):
    """_trace_mirror (all samples at once through geometry.perturb_frames) against
    MirrorPatch.perturbed then reflect_rays / intersect, one sample at a time. Same model,
    different evaluation order: ~1e-13 m on ~1 m points, 1e-12 rad on bearings."""
    from nodlidar.analysis.tolerance import _trace_mirror
    from nodlidar.geometry import directions_from_bearings

    rng = np.random.default_rng(21)
    n = 40
    prob = _problem(design, ToleranceSpec(), [0.7, 3.0])
    dl = np.zeros((n, 6))
    for m, md in zip(design.mirrors, prob.mirrors, strict=True):
        # large enough that some beams fall off their patch (on_patch is exercised)
        dm = rng.normal(size=(n, 3)) * [5e-3, 1e-2, 2e-3]
        tr = _trace_mirror(md, dm, dl, prob.ranges)
        d0 = directions_from_bearings(design.lidar.bearing_from_step(m.steps))
        for k in range(n):
            p = m.patch.perturbed(Perturbation.from_array(dm[k]))
            t, hit, out = reflect_rays(np.zeros_like(d0), d0, p.origin_, p.normal_)
            assert_allclose(tr.on_patch[k], np.isfinite(p.intersect(np.zeros_like(d0), d0)[0]))
            assert_allclose(tr.elevation[k], np.arcsin(out[:, 2]), rtol=0, atol=1e-12)
            for j, r in enumerate(prob.ranges):
                P = arc_point(hit, out, r)
                assert_allclose(tr.points[k, :, j], P, rtol=0, atol=1e-12)
                assert_allclose(tr.bearing[k, :, j], bearing_of(P), rtol=0, atol=1e-12)
        assert not tr.on_patch.all() and tr.on_patch.any()
