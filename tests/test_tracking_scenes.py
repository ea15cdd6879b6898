"""Tracking on scenes beyond the paper's (issue 13): clustering of nearby objects, the
multi-object tracker, the online evaluation harness and ``study mirrors --scene``.

References: closed forms (GOSPA of one pair, trajectory velocity against finite differences
of its positions), the simulator's per-beam truth, the scene files' own motion.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from numpy.testing import assert_allclose

from nodlidar.cli import main
from nodlidar.tracking import evaluate as E
from nodlidar.tracking.segment import cluster_points


@pytest.fixture(scope="module")
def design():
    from nodlidar.paper import PAPER_DESIGN
    from nodlidar.solver import solve
    from nodlidar.spec import load_design

    return solve(load_design(PAPER_DESIGN))


def _arc(cx, cy, r=0.18, n=30, view=(0.0, 0.0)):
    """Front arc of a vertical cylinder seen from ``view``, at several heights (x, y, z)."""
    a0 = np.arctan2(view[1] - cy, view[0] - cx)
    a = a0 + np.linspace(-1.2, 1.2, n)
    xy = np.column_stack([cx + r * np.cos(a), cy + r * np.sin(a)])
    return np.concatenate([np.column_stack([xy, np.full(n, z)]) for z in (0.2, 0.6, 1.0)])


def test_plane_clustering_separates_people_side_by_side():
    # two people (r 0.18 m) 0.42 m apart: a 6 cm gap. Range-adaptive linking in the top view
    # (5 cm at 2-3 m) keeps them apart; the paper's fixed 0.15 m radius merges them
    p = np.concatenate([_arc(2.5, -0.21), _arc(2.5, 0.21)])
    eps = np.clip(4.0 * np.hypot(p[:, 0], p[:, 1]) * 2 * np.pi / 1024, 0.05, 0.15)
    lab = cluster_points(p[:, :2], eps, 5, attach_m=0.15)
    assert len(np.unique(lab)) == 2
    assert len(np.unique(lab[:90])) == 1 and len(np.unique(lab[90:])) == 1
    # the fixed 3D radius joins the two people at each height (and splits each person by
    # height: slices 0.4 m apart)
    lab3 = cluster_points(p, 0.15, 5)
    assert set(lab3[:90]) == set(lab3[90:]) and len(set(lab3)) == 3


def test_plane_clustering_attaches_sparse_edge_points():
    # a lone grazing-edge point 8 cm off the arc joins it (within attach_m), a point 30 cm
    # away stays noise (-1)
    p = np.concatenate([_arc(2.0, 0.0)[:, :2], [[2.0, 0.26], [2.0, 0.5]]])
    lab = cluster_points(p, 0.05, 5, attach_m=0.15)
    assert lab[-2] == lab[0] and lab[-1] == -1


def test_mover_truth_velocity_is_the_derivative_of_position():
    from nodlidar.sim.scene import load_scene, scene_from_dict

    for f in ("design/scenes/track-crossing.toml", "paper-tracking", "stop-and-go"):
        sc = load_scene(f) if f != "stop-and-go" else scene_from_dict({"mover": [{
            "trajectory": "waypoints", "points_m": [[1, -1, 0], [2, 0, 0], [2, 1.5, 0]],
            "speed_m_s": [0.7, 0.4], "pause_s": 1.5}]})
        t = np.linspace(0.3, 7.7, 40)
        h = 1e-4
        p0, v = E.mover_truth(sc, t)
        p1, _ = E.mover_truth(sc, t + h)
        # central/forward difference of a piecewise-linear path: exact away from the turns
        assert_allclose((p1 - p0) / h, v, atol=1e-6)


def test_online_convergence_definition():
    assert E.online_convergence([0.05, 0.0, 0.0], [0, 0, 0]) == 2
    assert E.online_convergence([0.0, 0.0, 0.0], [0, 3.0, 0]) == 3
    assert E.online_convergence([0.0, 0.0, np.nan], [0, 0, 0]) is None
    assert E.online_convergence([0.0], [0.0]) == 1


def test_gospa_of_one_pair_is_the_capped_distance():
    # GOSPA (p = 1, alpha = 2) of one estimate and one truth: min(d, c) (closed form)
    from nodlidar.sim.scene import load_scene

    sc = load_scene("paper-tracking")
    t = 1.0
    pos, _ = E.mover_truth(sc, [t])
    for d, want in ((0.3, 0.3), (1.5, 1.0)):
        res = E.OnlineResult(sc, True, "renyi", 0, 1, scan_t_s=[t],
                             confirmed=[[(t, float(pos[0, 0, 0]) + d, float(pos[0, 0, 1]))]])
        assert_allclose(E._gospa(res, 1.0), want, rtol=1e-9)
    # no track at all: the missed truth costs c / 2
    res = E.OnlineResult(sc, True, "renyi", 0, 1, scan_t_s=[t], confirmed=[[]])
    assert_allclose(E._gospa(res, 1.0), 0.5, rtol=1e-9)


def test_tracker_takes_scan_points_from_the_live_path(design):
    # the live/recording path hands ScanPoints (not Segmented scans): the tracker segments
    from nodlidar.tracking.simdata import simulate_scans
    from nodlidar.tracking.tracker import Tracker

    scans = simulate_scans(design, 12, seed=0)
    trk = Tracker(range_sigma=design.lidar.range_sigma_m)
    states = [st for s in scans for st in trk.update(s)]
    assert states and any(st.confirmed for st in states)
    # the confirmed track is on the cylinder: within its radius + the centroid's offset of
    # the visible front (< r) of the true axis
    pos, _ = E.mover_truth(__import__("nodlidar.sim.scene", fromlist=["x"]).load_scene(
        "paper-tracking"), [states[-1].t_s])
    assert np.hypot(states[-1].x_m - pos[0, 0, 0], states[-1].y_m - pos[0, 0, 1]) < 0.18


def test_view_scan_is_when_the_beams_first_meet_the_mover(design):
    """``view_scan`` is the first scan whose returns hold ``VIEW_POINTS`` of the mover, by
    the simulator's truth, and no track can follow it earlier. The person of
    track-entering-view starts 58 deg to the side, 0.94 m out: lifted (+-120 deg) sees them
    from the first scan; the mirrors' view (+-40 deg) only once they have walked to ~0.6 m
    / 1.0 m forward, i.e. after the 0.3 m/s walk of several scans (measured: scan 8)."""
    for dep in (True, False):
        r = E.run_online(design, "design/scenes/track-entering-view.toml", 12,
                         mirrors_deployed=dep, seed=0)
        m = E.evaluate(r)["movers"][0]
        counts = [c.get(1, 0) for c in r.returns]
        print(dep, m["view_scan"], m["first_scan"], counts)
        assert m["view_scan"] == 1 + next(i for i, c in enumerate(counts) if c >= E.VIEW_POINTS)
        assert m["first_scan"] is not None and m["first_scan"] >= m["view_scan"]
        if dep:
            assert 4 <= m["view_scan"] <= 10
        else:
            assert m["view_scan"] == 1


def _runs(design, scene, n, seeds):
    return E.compare_mirrors(design, scene, seeds, n, ("renyi",))


@pytest.mark.slow
@pytest.mark.parametrize("scene,n", [("design/scenes/track-crossing.toml", 80),
                                     ("design/scenes/track-side-by-side.toml", 60)])
def test_two_people_keep_their_tracks(design, scene, n):
    """Each person keeps one track (purity >= 0.9, no identity switch) in every seed and
    configuration; final velocity within 0.03 m/s and 5 deg of the scene's."""
    for r in _runs(design, scene, n, range(2)):
        for m in r["movers"]:
            print(r["config"], r["seed"], m)
            assert m["purity"] >= 0.9
            assert m["id_switches"] == 0
            assert abs(m["final_err_v_m_s"]) <= 0.03
            assert abs(m["final_err_heading_deg"]) <= 5.0


@pytest.mark.slow
def test_three_people_the_two_always_in_view_keep_their_tracks(design):
    """A and B keep one track each (purity >= 0.9, no switch) in both configurations;
    before labels_observe_motion, B with mirrors switched in 7 of 8 seeds (its second
    sighting gave ~200 m/s). C, hidden longer than a track coasts, is not judged."""
    for r in _runs(design, "design/scenes/track-three-people.toml", 80, range(2)):
        for m in r["movers"][:2]:
            print(r["config"], r["seed"], m)
            assert m["purity"] >= 0.9
            assert m["id_switches"] == 0
            assert abs(m["final_err_v_m_s"]) <= 0.03
            assert abs(m["final_err_heading_deg"]) <= 5.0


@pytest.mark.slow
def test_paper_case_online_convergence(design):
    """The paper's scene, live tracker, online: mirrors converge by scan 7 (median over 8
    seeds) and no later than lifted. Both converge within a few scans of each other, so
    4 seeds do not order them (measured with the default "overlap" fusion, drawn pairs and
    "adaptive" pairs: 5.0 vs 4.5 over seeds 0-3, 5.0 vs 5.0 over 0-7; with all pairs, the
    default before: 5.5 vs 4.5 and 5.0 vs 5.0; with "kalman" and 300 points, the default
    before that: 6.0 vs 5.5 and 5.5 vs 6.0)."""
    runs = _runs(design, "paper-tracking", 38, range(8))
    row = E.summary_rows(runs)[0]
    print(row)
    assert row["conv_mirrors"] is not None and row["conv_mirrors"] <= 7
    assert row["conv_lifted"] is None or row["conv_mirrors"] <= row["conv_lifted"]


def test_cli_study_scene_json(tmp_path, capsys):
    out = tmp_path / "s"
    assert main(["study", "mirrors", "--scene", "paper-tracking", "--scans", "12", "--seeds",
                 "1", "--entropy", "renyi", "--out", str(out), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["scene"] == "paper-tracking" and len(doc["runs"]) == 2
    assert {r["config"] for r in doc["runs"]} == {"mirrors", "lifted"}
    assert doc["summary"][0]["mover"] == "cylinder"
    # the cylinder starts in both views: seen as a mover from the first scans in both
    for cfg in ("mirrors", "lifted"):
        assert 1 <= doc["summary"][0][f"first_scan_{cfg}"] <= 3
        assert 1 <= doc["summary"][0][f"view_scan_{cfg}"] <= doc["summary"][0][f"first_scan_{cfg}"]
    assert (out / "scene_study.md").stat().st_size > 0
    # the output exists now: refused without --force, one line
    assert main(["study", "mirrors", "--scene", "paper-tracking", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "--force" in err and len(err.strip().splitlines()) == 1


def test_window_map_answers_as_the_full_map_within_its_window():
    # random rays over 12 scans: for the latest scan (no later evidence), the windowed map
    # (window >= 12) gives exactly the full map's answers; with a window of 3 it forgets
    # traversals older than 3 scans and only those
    from nodlidar.tracking.voxels import VoxelGrid, VoxelMap, WindowVoxelMap

    rng = np.random.default_rng(3)
    grid = VoxelGrid(0.1)
    full, win, short = VoxelMap(grid), WindowVoxelMap(grid, window_scans=12), \
        WindowVoxelMap(grid, window_scans=3)
    for k in range(12):
        d = rng.normal(size=(200, 3))
        d /= np.linalg.norm(d, axis=1)[:, None]
        start = rng.uniform(-0.5, 0.5, (200, 3))
        r = rng.uniform(0.5, 3.0, 200)
        for m in (full, win, short):
            m.integrate(k, start + r[:, None] * d, start, d, r, np.zeros(200))
    q = rng.uniform(-3, 3, (5000, 3))
    a = full.inconsistent(q, 11)
    assert a.sum() > 200  # 474 of 5000 query points (seed 3)
    assert np.array_equal(win.inconsistent(q, 11), a)
    assert np.array_equal(win.free_count(q), full.free_count(q))
    b = short.inconsistent(q, 11)
    assert not np.any(b & ~a) and b.sum() < a.sum()
    assert short.n_keys == sum(len(k) for k in win._keys[-3:])


def test_window_map_index_answers_as_the_search_scan_by_scan():
    # the slot index (one search for every kept scan) against the search per kept scan it
    # replaced, over windows that wrap many times, scans with no ray, rays with no return,
    # static support on and off, and scan gaps of 1 and 2
    from nodlidar.tracking.voxels import VoxelGrid, WindowVoxelMap

    rng = np.random.default_rng(1)
    seen = np.zeros(2, int)
    for window in (1, 3, 12, 60, 64):
        for age in (0.0, 0.35):
            fast = WindowVoxelMap(VoxelGrid(0.1), window_scans=window, static_age_s=age)
            slow = WindowVoxelMap(VoxelGrid(0.1), window_scans=window, static_age_s=age)
            slow._free_index = slow._hit_index = None  # the search scan by scan
            for k in range(100):
                n = 0 if k % 17 == 5 else 60
                d = rng.normal(size=(n, 3))
                d /= np.linalg.norm(d, axis=1)[:, None]
                start, r = rng.uniform(-0.3, 0.3, (n, 3)), rng.uniform(0.3, 2.0, n)
                r[rng.random(n) < 0.1] = np.nan
                hits = start + np.nan_to_num(r)[:, None] * d
                for m in (fast, slow):
                    m.integrate(k, hits, start, d, r, np.zeros(n), t_s=0.1 * k)
                q = rng.uniform(-2, 2, (300, 3))
                q[:100] = hits[rng.integers(0, max(n, 1), 100)] if n else q[:100]
                for gap in (1, 2):
                    for t in (np.nan, 0.1 * k, 0.1 * k - 0.2):
                        a = fast.inconsistent(q, k, gap, t_s=t)
                        assert np.array_equal(a, slow.inconsistent(q, k, gap, t_s=t))
                        seen += [a.sum(), (~a).sum()]
                sup = fast.static_support(q, 0.1 * k)
                assert np.array_equal(sup, slow.static_support(q, 0.1 * k))
                if age > 0:
                    seen[0] += sup.sum()
    assert seen.min() > 1000  # both answers were given many times


def test_connected_labels_are_scipys():
    # the clustering's connected components against scipy's on random graphs: the same
    # labels, numbered by each component's smallest node
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    from nodlidar.tracking.segment import connected_labels

    rng = np.random.default_rng(0)
    for _ in range(500):
        n = int(rng.integers(1, 300))
        e = int(rng.integers(0, 3 * n))
        a, b = rng.integers(0, n, e), rng.integers(0, n, e)
        ref = connected_components(coo_matrix((np.ones(e), (a, b)), shape=(n, n)),
                                   directed=False)[1]
        assert np.array_equal(connected_labels(n, a, b), ref)
    # a path numbered backwards: one component, however long the chain of roots
    n = 1000
    assert np.array_equal(connected_labels(n, np.arange(1, n), np.arange(n - 1)), np.zeros(n))


def test_unique_keys_is_np_unique():
    # the sort-based unique the carving and the tracker use, against numpy's own: a scan's
    # carving (few distinct keys among many), negative keys, and the empty and one-key ends
    from nodlidar.tracking.voxels import unique_keys

    rng = np.random.default_rng(5)
    for keys in (rng.integers(-3000, 3000, 40_000), rng.integers(0, 1 << 62, 500),
                 np.array([7]), np.zeros(0, np.int64), np.full(9, -2)):
        u = unique_keys(keys)
        assert u.dtype == keys.dtype and np.array_equal(u, np.unique(keys))


@pytest.mark.parametrize("bins_per_point", [0.0, 8.0, 1e9])
def test_batched_voxel_grid_equals_one_evaluation_per_velocity(bins_per_point):
    # the batched pass (one sort of an (m, n) key array) against eq. 12 evaluated velocity by
    # velocity (voxel_entropy, itself checked against an independent oracle in
    # test_tracking.py): same pixels, same counts -> equal to rounding of the float sums
    from nodlidar.tracking.motion import _voxel_entropy_grid, compensate, voxel_entropy

    rng = np.random.default_rng(0)
    P = rng.normal(size=(800, 3)) * 0.2
    T = rng.uniform(0, 4, 800)
    W = rng.normal(size=(25, 2)) * 0.1
    # bins_per_point 0: the sorted runs; 1e9: the bincount; 8: the default choice
    a = _voxel_entropy_grid(P[:, :2], T, W, 4.0, 0.03, 0.01, bins_per_point)
    b = [voxel_entropy(compensate(P, T, w, 4.0) + [0.01, 0.01, 0.0], 0.03) for w in W]
    assert_allclose(a, b, rtol=1e-12)


def _scene(name):
    """The path of ``design/scenes/NAME.toml`` in this repository."""
    from pathlib import Path

    return Path(__file__).resolve().parents[1] / "design" / "scenes" / f"{name}.toml"


def _grid_scene(speed, heading_deg, length_m=3.0):
    """The study's speed x heading scene (:func:`nodlidar.tracking.evaluate.grid_scene`)."""
    return E.grid_scene(speed, heading_deg, length_m)


@pytest.mark.slow
def test_reflected_windows_alone_are_not_biased_for_a_slow_mover(design):
    """Issue 13 measured 0.036-0.041 m/s from each reflected window alone for a 0.05 m/s
    object. Through the live pipeline (assembled scans, top-view clusters, one track per
    object) each window's points alone give the motion within 4 mm/s and 2 deg (measured:
    0.048-0.050 m/s, within 1.1 deg, seeds 0-1): the scatter of 60 scans of range noise,
    well apart from the old 9-14 mm/s shortfall."""
    from nodlidar.tracking.motion import MotionEstimate, refine_motion
    from nodlidar.tracking.simdata import simulate_scans
    from nodlidar.tracking.tracker import Tracker

    scans = simulate_scans(design, 60, scene=_grid_scene(0.05, 45.0), seed=0)
    trk = Tracker(range_sigma=design.lidar.range_sigma_m)
    for s in scans:
        trk.update(s)
    tr = max(trk.all_tracks(), key=lambda t: len(t.scans))
    P, T = np.concatenate(tr.points[-40:]), np.concatenate(tr.times[-40:])
    M = np.concatenate(tr.mirrors[-40:])
    guess = MotionEstimate(0.05, np.radians(45.0))
    for m in np.unique(M[M >= 0]):
        sel = M == m
        assert sel.sum() > 500
        est = refine_motion(P[sel], T[sel], guess, max_points=300)
        print("window", m, sel.sum(), est.v_m_s, np.degrees(est.heading_rad))
        assert abs(est.v_m_s - 0.05) <= 0.004
        assert abs(np.degrees(est.heading_rad) - 45.0) <= 2.0


class _OneBlob:
    """Stub of Segmented: scan k with one 20-point blob moving at 0.13 m/s along y."""

    def __init__(self, k):
        from nodlidar.tracking.scans import ScanPoints

        pts = np.random.default_rng(k).normal([2.0, 0.013 * k, 0.5], 0.02, (20, 3))
        n = len(pts)
        self.scan = ScanPoints(k, np.arange(n), np.full(n, k * 0.1), np.full(n, -1),
                               np.ones(n), pts, pts, pts, np.zeros(n))

    def objects(self):
        return [np.arange(20)]


class _PacingBlob:
    """Stub of Segmented: a 20-point blob of radius ~2 cm at 1 m/s along +y that turns back
    at scan 30 (t = 3 s), as the speed x heading grid's back-and-forth leg does."""

    def __init__(self, k):
        from nodlidar.tracking.scans import ScanPoints

        t = 0.1 * k
        y = t if t <= 3.0 else 6.0 - t
        pts = np.random.default_rng(k).normal([2.0, y - 1.5, 0.5], 0.02, (20, 3))
        n = len(pts)
        self.scan = ScanPoints(k, np.arange(n), np.full(n, t), np.full(n, -1),
                               np.ones(n), pts, pts, pts, np.zeros(n))

    def objects(self):
        return [np.arange(20)]


class _StopGoBlob:
    """Stub of Segmented: the 20-point blob at 0.5 m/s along +y that stops at scan 20
    (t = 2 s) and walks on at scan 50 (t = 5 s); a beam with no return on either side (its
    silhouette: not cut)."""

    def __init__(self, k):
        from nodlidar.tracking.scans import ScanPoints

        t = 0.1 * k
        y = 0.5 * min(t, 2.0) + 0.5 * max(t - 5.0, 0.0)
        blob = np.random.default_rng(k).normal([2.0, y - 1.5, 0.5], 0.02, (20, 3))
        pts = np.concatenate([np.full((1, 3), np.nan), blob, np.full((1, 3), np.nan)])
        n = len(pts)
        self.scan = ScanPoints(k, np.arange(n), np.full(n, t), np.full(n, -1),
                               np.where(np.isnan(pts[:, 0]), np.nan, 1.0), pts, pts, pts,
                               np.zeros(n))

    def objects(self):
        return [np.arange(1, 21)]


def test_a_track_restarts_its_motion_when_its_object_stops_and_walks_on():
    # maneuver_m_s: 4 scans after the stop the centroids' velocity (0 m/s) is 0.5 m/s off
    # the filtered one; the window restarts with the sightings since, and the track reads
    # the stop (< 0.05 m/s) and, 4 scans after it walks on, its speed (within 0.02 m/s of
    # 0.5: 20 points of 2 cm noise). Without it (0) the window mixes the two motions until
    # the turn gate gives way: 0.46 m/s 0.8 s after the stop, and nothing near 0.5 m/s
    # 0.6 s after it walks on. One track throughout, either way.
    from nodlidar.tracking.tracker import Tracker, TrackerConfig

    speeds = {}
    for m in (0.0, 0.3):
        trk = Tracker(TrackerConfig(maneuver_m_s=m, window_cut_mask="off"))
        seen, v = set(), {}
        for k in range(80):
            for st in trk.update(_StopGoBlob(k)):
                if st.alive:
                    seen.add(st.track_id)
                    v[k] = st.v_m_s
        assert seen == {1}
        speeds[m] = v
    assert speeds[0.3][28] < 0.05 and speeds[0.0][28] > 0.3
    assert abs(speeds[0.3][56] - 0.5) <= 0.02
    assert not abs(speeds[0.0][56] - 0.5) <= 0.1  # a speed near 0, or none (NaN)
    assert abs(speeds[0.3][79] - 0.5) <= 0.01 and abs(speeds[0.0][79] - 0.5) <= 0.01


def test_a_coasting_track_is_not_sure_to_move():
    # TrackerConfig.follow_supported_m_s asks for a track surely moving: its speed three
    # sigmas from zero. The velocity's sigma grows while a track coasts unseen (process
    # noise): a blob at 0.13 m/s followed for 20 scans is sure (sigma 0.020 m/s, measured)
    # and not 1 s later (0.054); one at 1 m/s still is (the furnished room's start-up ghost,
    # tests/test_tracking_furniture.py, took the table after coasting 2 s at 0.25 m/s).
    from nodlidar.tracking.tracker import Tracker, TrackerConfig

    for blob, speed, later, sure_later in ((_OneBlob, 0.13, 3.0, False),
                                           (_PacingBlob, 1.0, 6.0, True)):
        # the stubs' beams have no geometry (steps in no order, rays through the points):
        # their beam lists' ends count as window cuts whose lines cut the blob anywhere
        trk = Tracker(TrackerConfig(window_cut_mask="off"))
        for k in range(20):
            trk.update(blob(k))
        (tr,) = trk.tracks.values()
        assert abs(float(np.hypot(*tr.x[2:])) - speed) < 0.01
        assert trk._surely_moving(tr, 2.0)  # just after its last scan (t = 1.9 s)
        assert trk._surely_moving(tr, later) == sure_later


def test_a_track_keeps_its_object_through_a_turn():
    # turn_reach_m: the cluster after the turn fails the constant-velocity gates (two scans
    # later it is 0.4 m behind the prediction, with a tight covariance) but is near where
    # the track last saw it, so the track takes it and starts its motion afresh. Without
    # it (turn_reach_m = 0) a second track takes the object: the test can fail.
    from nodlidar.tracking.tracker import Tracker, TrackerConfig

    ids = {}
    for reach in (0.0, 0.15):
        trk = Tracker(TrackerConfig(turn_reach_m=reach))
        seen, last = set(), None
        for k in range(60):
            for st in trk.update(_PacingBlob(k)):
                if st.alive:
                    seen.add(st.track_id)
                    last = st
        ids[reach] = seen
        if reach:
            # the motion after the turn is measured from the scans after it only: -1 m/s
            # along y (the blob's shape is exact; 0.03 m/s for 30 scans of 2 cm noise)
            assert abs(last.v_m_s - 1.0) <= 0.03
            assert abs(np.degrees(last.heading_rad) + 90.0) <= 2.0
    assert len(ids[0.0]) >= 2
    assert ids[0.15] == {1}


@pytest.mark.slow
@pytest.mark.parametrize("dep", [True, False], ids=["mirrors", "lifted"])
def test_a_mover_back_on_its_own_path_keeps_its_track(design, dep):
    # The grid's 1.0 m/s mover on its 3 m back-and-forth leg (135 deg), seed 0: after the
    # turn at 6 s it walks back through voxels it hit 2-4 s before, which static support
    # counts as consistent - its clusters are ``supported``, no longer dynamic. Without
    # follow_supported_m_s its track got nothing from scan 70 (mirrors) / 74 (lifted) on,
    # although the simulator sees it to scan 78 (measured); with it the same track
    # follows it to the end. Nothing is born from a supported cluster.
    from nodlidar.tracking.tracker import TrackerConfig

    sc = _grid_scene(1.0, 135.0)
    last = {}
    for follow in (0.0, 0.1):
        res = E.run_online(design, sc, 80, mirrors_deployed=dep, seed=0,
                           tracker=TrackerConfig(follow_supported_m_s=follow))
        # the tracks reported (confirmed): a new track that continues a lost one
        # (TrackerConfig.stitch_turned_m) is tentative until it does
        seq = sorted((r["scan"], r["track"]) for r in res.records
                     if r["counts"].get(1, 0) >= 10 and r["confirmed"])
        tail = [tid for scan, tid in seq if scan >= 66]
        last[follow] = (max(scan for scan, _ in seq), len(set(tail)))
    assert last[0.0][0] <= 74, last  # the test can fail: the track is lost before the end
    assert last[0.1] == (77, 1), last  # one track from the reappearance to the last view


@pytest.mark.slow
@pytest.mark.parametrize("heading, lifted, bound", [(89.4, 67, 67), (135.0, 66, 59)])
def test_a_reversal_restarts_with_the_sightings_after_it(design, heading, lifted, bound):
    # The grid's 0.6 m/s mover, mirrors, seed 0, reverses at scan 50; the nod's blind
    # part follows at 55-65. Lateral (89.4 deg): at scan 52 the six centroids' line lags
    # the reversal 2.25-fold (beyond _agrees' two-fold bound). Refused
    # (maneuver_late_lag 0), the turn gate restarted the motion from one scan at 53, a
    # two-scan window (the second of 8 points) read 0.72 m/s at 124 deg, the track was
    # lost in the blind part and converged at 73. At 135 deg the mirrors' windows cut two
    # of the six sightings (no maneuver test), the gate's one-scan restart read 0.61 m/s
    # and it converged at 66, after the blind part. With maneuver_late_lag the gate's
    # restart at 53 starts with the sightings after the turn that 52's line placed (51,
    # 52), and the track holds the reversed motion before the blind part: at 135 deg it
    # converges before it (56), laterally at its end (67, as lifted). ``lifted``: the
    # lifted configuration's convergence before this change (measured, seed 0).
    from nodlidar.tracking.tracker import TrackerConfig

    sc = _grid_scene(0.6, heading)
    truth = heading - 180.0
    conv, v54 = {}, {}
    for lag in (0.0, 3.0):
        res = E.run_online(design, sc, 80, mirrors_deployed=True, seed=0,
                           tracker=TrackerConfig(maneuver_late_lag=lag))
        conv[lag] = E.evaluate(res)["movers"][0]["conv_scan"]
        v54[lag] = [(r["v_m_s"], np.degrees(r["heading_rad"])) for r in res.records
                    if r["scan"] == 54 and r["confirmed"]]
    assert conv[0.0] >= lifted, conv  # the test can fail: without it, no sooner than lifted
    assert conv[3.0] <= bound, conv
    # at 54 the track already holds the reversal: within 0.05 m/s and 3 deg of 0.6 m/s
    (v, h), = v54[3.0]
    assert abs(v - 0.6) < 0.05 and abs((h - truth + 180) % 360 - 180) < 3.0, v54


@pytest.mark.slow
def test_a_start_from_standing_is_measured_against_the_velocity_before_it(design):
    # A person stands 3 s, then walks across at 0.6 m/s (mirrors, seed 1). The filter
    # follows the start through windows that mix standing and walking, so the centroids'
    # line (0.57 m/s at the walk's 8th sighting) never lay maneuver_m_s (0.3) from the
    # filtered speed (0.40 then): the speed ramped 0.10 -> 0.54 m/s over scans 31-41 and
    # converged at 72 (measured). Against the settled velocity before the line's
    # sightings (standing) the start is a maneuver: restarted at 38, 0.59-0.60 from 39.
    from nodlidar.tracking.tracker import TrackerConfig

    conv, v39 = {}, {}
    for on in (False, True):
        res = E.run_online(design, _scene("track-start-still"), 90, mirrors_deployed=True,
                           seed=1, tracker=TrackerConfig(maneuver_before=on))
        conv[on] = E.evaluate(res)["movers"][0]["conv_scan"]
        v39[on] = [r["v_m_s"] for r in res.records if r["scan"] == 39 and r["confirmed"]]
    assert conv[False] >= 60, conv  # the test can fail: without it, the ramp
    assert conv[True] <= 42, conv
    (v,), (v_off,) = v39[True], v39[False]
    assert abs(v - 0.6) < 0.015 and abs(v_off - 0.6) > 0.1, v39


@pytest.mark.slow
@pytest.mark.parametrize("seed", [2, 4])
def test_people_who_walk_off_unseen_keep_their_tracks(design, seed):
    # Two people meet, stand 3 s and walk off together while the nod looks away (lifted).
    # Across the blind part the six centroids' line held a standing sighting from before
    # it and read 0.16-0.26 m/s for 0.5, under maneuver_m_s: no restart, the track read
    # standing while A walked away, fell behind and lost it - A's rest is a second track
    # that never converges (seeds 2 and 4, measured). The line of the sightings after the
    # gap restarts the motion at its 4th: one track, converged at 74.
    from nodlidar.tracking.tracker import TrackerConfig

    out = {}
    for on in (False, True):
        res = E.run_online(design, _scene("track-meet-stop"), 90, mirrors_deployed=False,
                           seed=seed, tracker=TrackerConfig(maneuver_after_gap=on))
        a, = [m for m in E.evaluate(res)["movers"] if m["mover"] == "A"]
        out[on] = (len(a["tracks"]), a["conv_scan"])
    assert out[False][0] == 2 and out[False][1] is None, out  # the test can fail
    assert out[True][0] == 1 and out[True][1] is not None and out[True][1] <= 76, out


@pytest.mark.slow
def test_a_stop_far_out_restarts_with_its_latest_sightings(design):
    # A person walks away at 1.1 m/s and stops 4.8 m out (lifted, seed 4; 12 points per
    # scan). At 43 the latest three sightings read 0.09 m/s, the line 0.53: a stop 2.1
    # times beyond the line, refused as a change of speed while moving, so the turn gate
    # restarted from one scan at 44 and a two-scan window read 0.49 m/s; eight scans into
    # the stop the track still read 0.16. Taken as a stop (held at 43, confirmed at 44),
    # the window starts with the three sightings at the stop: 0.04 by then.
    from nodlidar.tracking.tracker import TrackerConfig

    v = {}
    for on in (False, True):
        res = E.run_online(design, _scene("track-stop-far"), 60, mirrors_deployed=False,
                           seed=4, tracker=TrackerConfig(maneuver_stop_lag=on))
        v[on] = {r["scan"]: r["v_m_s"] for r in res.records if r["confirmed"]}
    assert v[False][51] > 0.12 and v[False][45] > 0.4, v[False]  # the test can fail
    assert v[True][51] < 0.06 and v[True][44] < 0.25, v[True]


def _beams(rng_m, mirror):
    """A ScanPoints of beams 0..n-1 at ranges ``rng_m`` (NaN: no return) and windows
    ``mirror``, fanned over 90 deg from the origin."""
    from nodlidar.tracking.scans import ScanPoints

    rng_m = np.asarray(rng_m, float)
    n = len(rng_m)
    a = np.linspace(-0.8, 0.8, n)
    d = np.column_stack([np.cos(a), np.sin(a), np.zeros(n)])
    return ScanPoints(0, np.arange(n), np.zeros(n), np.asarray(mirror), rng_m,
                      d * rng_m[:, None], np.zeros((n, 3)), d, np.zeros(n))


def test_window_cut_marks_slices_that_end_at_a_window_edge():
    from dataclasses import replace

    from nodlidar.tracking.segment import window_cut

    rng = np.full(100, 5.0)  # a wall, 5 m
    mirror = np.where(np.arange(100) < 50, -1, 0)
    rng[20:31] = 2.0  # A: wall either side (silhouette edges)
    rng[44:50] = 2.0  # B: ends at the last beam of window -1
    rng[55:60] = 1.0  # an occluder ...
    rng[60:71] = 2.0  # C: ... right beside it, nearer: not a cut (module docstring)
    rng[78:80] = np.nan  # no return beside D: free space, not a cut
    rng[80:86] = 2.0
    s = _beams(rng, mirror)
    assert not window_cut(s, np.arange(20, 31)).any()
    assert window_cut(s, np.arange(44, 50)).all()
    assert not window_cut(s, np.arange(60, 71)).any()
    assert not window_cut(s, np.arange(80, 86)).any()
    assert window_cut(s, np.arange(95, 100)).all()  # the field of view's edge
    # one cluster seen in two windows: only its cut slice is marked
    both = np.r_[np.arange(20, 31), np.arange(50, 56)]
    assert_allclose(window_cut(s, both), np.r_[np.zeros(11), np.ones(6)])
    # a beam the assembly dropped (absent) beside a slice cuts it
    keep = np.flatnonzero(np.arange(100) != 19)
    s2 = replace(s, steps=s.steps[keep], t_s=s.t_s[keep], mirror=s.mirror[keep],
                 range_m=s.range_m[keep], points=s.points[keep], ray_start=s.ray_start[keep],
                 ray_dir=s.ray_dir[keep], ray_offset=s.ray_offset[keep])
    assert window_cut(s2, np.arange(19, 30)).all()  # beams 20..30 are indices 19..29


def test_window_cut_follows_the_surface_and_counts_occluders_when_asked():
    from nodlidar.tracking.segment import window_cut

    rng = np.full(100, 5.0)  # a wall, 5 m; beams 16 mrad apart (3 cm at 2 m)
    mirror = np.where(np.arange(100) < 50, -1, 0)
    rng[20:31] = 2.0  # A: wall either side (silhouette edges)
    rng[40:50] = 2.0  # B: ends at the last beam of window -1
    rng[55:60] = 1.0  # an occluder ...
    rng[60:71] = 2.0  # C: ... right beside it, nearer
    rng[78:80] = np.nan  # no return beside D
    rng[80:86] = 2.0
    s = _beams(rng, mirror)
    part = np.arange(40, 46)  # B's first six beams only: the segmentation left out the rest
    assert not window_cut(s, part).any()  # its own end's neighbour is B itself
    assert window_cut(s, part, reach_m=0.05).all()  # followed along B to the window's edge
    assert not window_cut(s, part, reach_m=0.02).any()  # 3 cm apart: not one surface at 2 cm
    assert window_cut(s, part, reach_m=0.05, max_walk=3).sum() == 0  # stops before the edge
    assert not window_cut(s, np.arange(60, 71), reach_m=0.05).any()
    assert window_cut(s, np.arange(60, 71), reach_m=0.05, occluders=True).all()
    assert window_cut(s, np.arange(64, 71), reach_m=0.05, occluders=True).all()  # C's part
    for silhouette in (np.arange(20, 31), np.arange(80, 86)):  # farther / no return
        assert not window_cut(s, silhouette, reach_m=0.05, occluders=True).any()


def test_slices_cut_by_an_occluder_bias_the_motion(design):
    # A walker at 0.95 m/s comes out from behind a slow one (scans 26-32), lifted, so no
    # mirror window cuts anything; noise-free. Over scans 28-36 the entropy over every
    # point reads -0.031 m/s; without the slices an occluder cuts +0.002 m/s (measured).
    from nodlidar.sim.scene import scene_from_dict
    from nodlidar.tracking.motion import MotionEstimate, incidence_weights, refine_motion
    from nodlidar.tracking.segment import window_cut
    from nodlidar.tracking.simdata import simulate_scans

    movers = [{"radius_m": 0.18, "height_m": 1.7, "trajectory": "constant_velocity",
               "start_m": start, "velocity_m_s": vel}
              for start, vel in (([2.0, -2.0, 0.0], [0.3, 0.9, 0.0]),
                                 ([2.4, 0.4, 0.0], [-0.06, 0.0, 0.0]))]
    sc = scene_from_dict({"name": "fast-slow", "sensor": {"position_m": [0.0, 0.0, 0.4]},
                          "room": {"size_m": [8.0, 6.0, 2.5], "center_m": [2.5, 0.0],
                                   "ceiling": False}, "mover": movers})
    truth = MotionEstimate(float(np.hypot(0.3, 0.9)), float(np.arctan2(0.9, 0.3)), 0.0)
    scans = simulate_scans(design, 36, mirrors_deployed=False, scene=sc, seed=0, noise=False)
    P, T, W, C = [], [], [], []
    for s in scans[28:36]:
        idx = np.flatnonzero(s.truth_id == 1)
        P.append(s.points[idx])
        T.append(s.t_s[idx])
        W.append(incidence_weights(s.points[idx], s.ray_dir[idx], s.steps[idx], s.mirror[idx]))
        assert not window_cut(s, idx).any()  # lifted: no window's edge
        C.append(window_cut(s, idx, reach_m=0.05, occluders=True))
    P, T, W, C = map(np.concatenate, (P, T, W, C))
    assert 0.2 < C.mean() < 0.8  # the test can fail: part of it is occluded
    err = {}
    for name, sel in (("all", np.ones(len(P), bool)), ("unoccluded", ~C)):
        est = refine_motion(P[sel], T[sel], truth, max_points=300, renyi_method="newton",
                            renyi_subsample="pairs", weights=W[sel])
        err[name] = est.v_m_s - truth.v_m_s
    assert err["all"] < -0.015, err  # measured -0.031: the occluded slices read it slow
    # noise-free: the estimator's own error (docs/tracking.md "Incidence weights": ~3 mm/s)
    assert abs(err["unoccluded"]) <= 0.005, err


def test_leaving_out_window_cut_slices_removes_their_bias(design):
    # A person 2 m away at -47 deg bearing entering three mirror windows at once, noise-free
    # (the four-people room's P1): for ten scans each window sees it cut at the window's
    # edge. The entropy over every point of scans 0-15 reads -0.016 m/s and +2.0 deg off;
    # over the slices nothing cuts, -0.002 m/s and -0.1 deg (measured). Lifted, nothing is cut.
    from nodlidar.sim.scene import scene_from_dict
    from nodlidar.tracking.motion import MotionEstimate, incidence_weights, refine_motion
    from nodlidar.tracking.segment import window_cut
    from nodlidar.tracking.simdata import simulate_scans

    sc = scene_from_dict({"name": "p1", "room": {"size_m": [7.0, 6.0, 2.5],
                                                 "center_m": [2.5, 0.0], "ceiling": False},
                          "mover": [{"radius_m": 0.18, "height_m": 1.75,
                                     "trajectory": "constant_velocity",
                                     "start_m": [1.4, -1.5, 0.0], "velocity_m_s": [0.2, 0.4, 0.0]}]})
    truth = MotionEstimate(float(np.hypot(0.2, 0.4)), float(np.arctan2(0.4, 0.2)), 0.0)
    for dep in (True, False):
        P, T, W, C = [], [], [], []
        for s in simulate_scans(design, 16, mirrors_deployed=dep, scene=sc, seed=0, noise=False):
            idx = np.flatnonzero(s.truth_id == 1)
            P.append(s.points[idx])
            T.append(s.t_s[idx])
            W.append(incidence_weights(s.points[idx], s.ray_dir[idx], s.steps[idx], s.mirror[idx]))
            C.append(window_cut(s, idx))
        P, T, W, C = map(np.concatenate, (P, T, W, C))
        err = {}
        for name, sel in (("all", np.ones(len(P), bool)), ("whole", ~C)):
            est = refine_motion(P[sel], T[sel], truth, max_points=300, renyi_method="newton",
                                renyi_subsample="pairs", weights=W[sel])
            err[name] = (est.v_m_s - truth.v_m_s,
                         np.degrees(est.heading_rad - truth.heading_rad))
        if dep:
            assert C.mean() > 0.3  # the test can fail: much of it is cut
            assert abs(err["all"][0]) > 0.01 or abs(err["all"][1]) > 1.5, err
        else:
            assert not C.any()
        # noise-free: what is left is the estimator's own error on a passing cylinder
        # (docs/tracking.md "Incidence weights": ~3 mm/s)
        assert abs(err["whole"][0]) <= 0.005 and abs(err["whole"][1]) <= 1.0, (dep, err)


@pytest.mark.parametrize("keep", [False, True])
def test_track_memory_bounded_by_the_window(keep):
    from nodlidar.tracking.tracker import Tracker, TrackerConfig

    trk = Tracker(TrackerConfig(window_scans=5, keep_points=keep))
    for k in range(12):
        st = trk.update(_OneBlob(k))
    (tr,) = trk.all_tracks()
    kept = [len(p) for p in tr.points]
    assert len(kept) == 12 and st[0].n_points == 240  # counts every point ever taken
    assert kept == ([20] * 12 if keep else [0] * 7 + [20] * 5)


def test_pairs_between_mirror_windows_bias_a_short_window_along_the_line_of_sight(design):
    # The diagnosis of docs/tracking.md "Along the line of sight": a cylinder receding
    # along the line of sight at 0.3 m/s, mirrors deployed, no range noise (the data are
    # exact: median distance to the cylinder at each point's beam time <= 0.2 mm), the entropy
    # estimate over scans 1-2 (one scan period). Measured: all pairs -10.1 deg, pairs within
    # one mirror window +1.1 deg, all pairs with a 5 mm kernel -0.4 deg: the error is the
    # kernel terms between windows (they grow with the kernel: -2.9 deg at 10 mm, -27 at
    # 40 mm), not the data. Asserted with margins of 2-3x the measured values.
    from nodlidar.tracking.motion import MotionEstimate, refine_motion
    from nodlidar.tracking.simdata import simulate_scans

    scans = simulate_scans(design, 3, scene=_grid_scene(0.3, 0.0), seed=0, noise=False)[1:3]
    P = np.concatenate([s.points[s.truth_id == 1] for s in scans])
    T = np.concatenate([s.t_s[s.truth_id == 1] for s in scans])
    M = np.concatenate([s.mirror[s.truth_id == 1] for s in scans])
    assert len(np.unique(M)) >= 3  # the direct window and reflected ones

    def heading_err(sigma, labels=None):
        e = refine_motion(P, T, MotionEstimate(0.3, 0.0), sigma_m=sigma, max_points=300,
                          renyi_method="newton", renyi_subsample="pairs", labels=labels)
        return float(np.degrees(e.heading_rad))

    assert heading_err(0.02) < -5.0
    assert abs(heading_err(0.02, M)) < 3.0
    assert abs(heading_err(0.005)) < 1.5


class _TruthSeg:
    """Stub of Segmented: the simulator's truth as the segmentation (object 1 only)."""

    def __init__(self, scan):
        self.scan = scan

    def objects(self):
        idx = np.flatnonzero(self.scan.truth_id == 1)
        return [idx] if len(idx) else []


def test_adaptive_pairs_remove_the_first_windows_heading_bias(design):
    # The tracker's own window estimates (tr.motion) for a cylinder receding along the line
    # of sight, mirrors deployed, exact scans (no range noise) and the truth as the
    # segmentation, so only the cost differs. Measured, heading after 2..8 scans [deg]:
    # 0.3 m/s all pairs -9.3 -5.9 -3.0 -0.4 +0.0 -0.7 -0.3, adaptive -0.7 +1.1 -0.2 +0.2 then
    # the same; 0.6 m/s all pairs -5.1 -2.9 -1.0 -1.4 -0.6 ..., adaptive -0.1 -0.2 -0.6 +0.6
    # then the same. Asserted: all pairs biased at 2 scans (< -3 deg), adaptive within 2
    # deg for 2-5 scans, and from 6 scans (all pairs in both) the same minimum to 0.1 deg
    # (the warm starts differ; Newton stops within 5e-5 m/s, ~0.01 deg at 0.3 m/s). The
    # entropy alone: the round model (TrackerConfig.round_model) reads these windows'
    # outline and removes the all-pairs bias too (0.3 m/s, 2 scans: +0.15 deg).
    from nodlidar.tracking.simdata import simulate_scans
    from nodlidar.tracking.tracker import Tracker, TrackerConfig

    for speed in (0.3, 0.6):
        scans = simulate_scans(design, 9, scene=_grid_scene(speed, 0.0), seed=0, noise=False)
        heading = {}
        for pairs in ("all", "adaptive"):
            trk = Tracker(TrackerConfig(renyi_pairs=pairs, round_model="off"))
            h = heading[pairs] = {}
            for s in scans:
                trk.update(_TruthSeg(s))
                (tr,) = trk.tracks.values() if trk.tracks else (None,)
                if tr is not None and tr.motion is not None:
                    h[len(tr.scans)] = np.degrees(tr.motion.heading_rad)
        assert TrackerConfig().renyi_pairs == "adaptive"
        assert heading["all"][2] < -3.0, speed
        assert all(abs(heading["adaptive"][n]) < 2.0 for n in range(2, 6)), heading
        late = sorted(n for n in heading["all"] if n >= 6)
        assert len(late) >= 2
        assert_allclose([heading["adaptive"][n] for n in late],
                        [heading["all"][n] for n in late], atol=0.1)


@pytest.mark.slow
@pytest.mark.parametrize("speed, births", [(0.0, 0.0), (1.5, 0.0), (0.0, 1.5)])
def test_reacquisition_keeps_the_early_side_by_side_track(design, speed, births):
    """Side-by-side, seed 1, mirrors, per-window segmentation (docs/tracking.md, "Per-window
    segmentation and re-acquisition"): the right person (mover 2) is segmented at scan 3
    only, then not again until scan 26, 0.75 m on. The truth per beam says who is who:
    with the fixed gate (both options 0) a second track takes the person (the first,
    never confirmed, is no identity switch since 2026-12-06); with
    reacquire_speed_m_s=1.5, or with reacquire_births_m_s=1.5 (the default: the new
    cluster at scan 26 is nearer to where the lone track was than anything else),
    the scan-3 track takes it back - one track, no switch, and its first velocity estimate
    (the 2.3 s baseline) within 0.03 m/s and 5 deg of the scene's. With
    ``reacquire_unique_m`` (the default since 2026-12-07) the left person, new at scan 26
    too and about as near, makes it ambiguous: the right one's new track is pending on the
    scan-3 one until its own motion decides, so this takes the nearer at once (0: off)."""
    from nodlidar.tracking.segment import SegmentConfig
    from nodlidar.tracking.tracker import TrackerConfig

    # follow_inconsistent_fraction off: with it the person's track takes their clusters at
    # scan 7 on (few inconsistent points) and there is no gap to bridge (since 2026-12-06)
    res = E.run_online(design, "track-side-by-side", 30, seed=1,
                       tracker=TrackerConfig(reacquire_speed_m_s=speed,
                                             reacquire_births_m_s=births,
                                             follow_inconsistent_fraction=1.0,
                                             reacquire_unique_m=0.0),
                       segment=SegmentConfig(fraction_per_window=True))
    right = E.evaluate(res)["movers"][1]
    recs = sorted((r for r in res.records if r["counts"].get(2, 0)), key=lambda r: r["scan"])
    assert recs[0]["scan"] == 3 and recs[1]["scan"] == 26  # the gap this is about
    # with the fixed gate a second track takes the person; the scan-3 one was never
    # confirmed, so it is no identity switch (since 2026-12-06), but no velocity until two
    # sightings of the new one
    assert right["id_switches"] == 0
    if not (speed or births):
        assert len(right["tracks"]) == 2 and right["tentative_tracks"] == right["tracks"][:1]
    else:
        assert len(right["tracks"]) == 1 and right["purity"] >= 0.9
        _, vel = E.mover_truth(res.scene, [recs[1]["t_s"]])
        vt = vel[1, 0]
        assert abs(recs[1]["v_m_s"] - np.hypot(*vt[:2])) <= 0.03
        err = np.degrees(recs[1]["heading_rad"] - np.arctan2(vt[1], vt[0]))
        assert abs((err + 180) % 360 - 180) <= 5.0
