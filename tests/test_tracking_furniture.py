"""Static things in a furnished room are not movers (issue 13: "rooms with doorways and
furniture"): the online segmentation's static support, and the evaluation of false tracks
and of a person standing still."""

from __future__ import annotations

import numpy as np
import pytest

from nodlidar.paper import PAPER_DESIGN
from nodlidar.solver import solve
from nodlidar.spec import load_design
from nodlidar.tracking.segment import OnlineSegmenter, SegmentConfig
from nodlidar.tracking.voxels import VoxelGrid, WindowVoxelMap

ROOM = "design/scenes/track-room-furniture.toml"


@pytest.fixture(scope="module")
def design():
    return solve(load_design(PAPER_DESIGN))


def _one_ray_scan(m, scan, t_s, hit):
    """One scan of two rays along +x from the origin: a ray that stops at 1.05 m (a hit in
    the voxel [1.0, 1.1)) when ``hit``, and one that passes through that voxel to 3 m."""
    start = np.zeros((2, 3))
    d = np.array([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    r = np.array([1.05 if hit else np.nan, 3.0])
    pts = np.array([[1.05, 0.05, 0.05]]) if hit else np.zeros((0, 3))
    m.integrate(scan, pts, start + [0, 0.05, 0.05], d, r, np.zeros(2), t_s=t_s)


@pytest.mark.parametrize("old_hit_t, query_t, static_age, expected", [
    (0.0, 3.0, 2.0, False),   # hit 3 s before, traversed since: static support, consistent
    (None, 3.0, 2.0, True),   # never hit before: free, then occupied -> inconsistent
    (0.0, 1.5, 2.0, True),    # the earlier hit is younger than the static age
    (0.0, 3.0, 0.0, True),    # static support off: the voxel test alone
])
def test_static_support_of_a_voxel(old_hit_t, query_t, static_age, expected):
    # a voxel hit at old_hit_t, traversed at t = 1 s (a ray passing beside what is in it),
    # hit again at query_t: inconsistent only without a hit at least static_age before
    m = WindowVoxelMap(VoxelGrid(0.1), window_scans=60, static_age_s=static_age)
    if old_hit_t is not None:
        _one_ray_scan(m, 0, old_hit_t, hit=True)
    _one_ray_scan(m, 10, 1.0, hit=False)
    _one_ray_scan(m, 20, query_t, hit=True)
    p = np.array([[1.05, 0.05, 0.05]])
    assert m.inconsistent(p, 20, 1, t_s=query_t)[0] == expected
    # the hit of the query's own scan never supports itself
    assert not m.static_support(p, query_t - 1e-9).any() or old_hit_t is not None


def test_static_support_forgets_with_the_window():
    # the supporting hit drops out of the window with its scan
    m = WindowVoxelMap(VoxelGrid(0.1), window_scans=2, static_age_s=2.0)
    _one_ray_scan(m, 0, 0.0, hit=True)
    _one_ray_scan(m, 10, 1.0, hit=False)
    _one_ray_scan(m, 20, 3.0, hit=True)  # scan 0 is out (window 2)
    assert m.inconsistent(np.array([[1.05, 0.05, 0.05]]), 20, 1, t_s=3.0)[0]


def test_static_speed_is_validated():
    from nodlidar.errors import ParameterError

    with pytest.raises(ParameterError, match="static_speed_m_s"):
        SegmentConfig(static_speed_m_s=-0.1)
    assert SegmentConfig().static_age_s == pytest.approx(0.1 / 0.05)
    assert SegmentConfig(static_speed_m_s=0.0).static_age_s == 0.0


def _segment(design, scene, n, dep, cfg, seed=0):
    from nodlidar.tracking.simdata import simulate_scans

    scans = simulate_scans(design, n, mirrors_deployed=dep, scene=scene, seed=seed)
    seg = OnlineSegmenter(cfg, design.lidar.range_sigma_m)
    return [(s, seg.update(s)) for s in scans]


@pytest.mark.slow
@pytest.mark.parametrize("dep", [True, False], ids=["mirrors", "lifted"])
def test_furniture_is_not_dynamic_after_the_first_nod_cycle(design, dep):
    # The furnished room, 80 scans (two nod cycles of 4 s). Per scan, dynamic clusters that
    # are mostly static world (simulator truth 0). Without static support (the segmentation
    # before it) the pole, the table's edges, the door frame and the standing person are
    # dynamic in every nod cycle (measured, seed 0: 1.5 clusters per scan with mirrors, 4.7
    # lifted). With it, after the first cycle (scan >= 40; the map must have seen a surface
    # once, 2 s before, to know it stays): none with mirrors (seeds 0-3), and lifted a few
    # small clusters at voxel boundaries (seed 0: 1 in scans 40-79, a 5-8 point piece of
    # the table's edge, against ~190 without). The standing person never; the walker is
    # still found.
    out = {}
    for name, cfg in (("off", SegmentConfig(static_speed_m_s=0.0)), ("on", SegmentConfig())):
        false_clusters, stander, walker = [], [], []
        for s, g in _segment(design, ROOM, 80, dep, cfg):
            objs = g.objects()
            false_clusters.append(sum((s.truth_id[i] == 0).mean() > 0.5 for i in objs))
            stander.append(bool(np.any(s.truth_id[g.dynamic] == 2)))
            walker.append(bool(np.any(s.truth_id[g.dynamic] == 1)))
        out[name] = (np.array(false_clusters), np.array(stander), np.array(walker))
    f_off, st_off, _ = out["off"]
    f_on, st_on, w_on = out["on"]
    # the test can fail: without static support the second cycle is full of false clusters
    assert f_off[40:].mean() > 1.0 and st_off[40:].sum() >= 5
    if dep:
        assert f_on[40:].sum() == 0, np.flatnonzero(f_on)
    else:
        assert f_on[40:].sum() <= 0.05 * f_off[40:].sum(), (f_on[40:].sum(), f_off[40:].sum())
    assert st_on[40:].sum() == 0
    assert w_on.sum() >= 3  # the walker is found (5-8 scans before it leaves the view)


@pytest.mark.slow
def test_static_support_keeps_the_slowest_mover(design):
    # the slowest mover (0.05 m/s, receding along the line of sight: it stays
    # longest in its own voxels) is still found in nearly every scan, from the first
    from test_tracking_scenes import _grid_scene

    sc = _grid_scene(0.05, 0.0)
    for dep in (True, False):
        det = {}
        for name, cfg in (("off", SegmentConfig(static_speed_m_s=0.0)), ("on", SegmentConfig())):
            hits = [bool(np.any(s.truth_id[g.dynamic] == 1))
                    for s, g in _segment(design, sc, 60, dep, cfg)]
            det[name] = np.array(hits)
        # measured (seed 0): 51 of 60 scans without static support, 48-50 with it
        assert det["on"].sum() >= 0.9 * det["off"].sum(), (dep, det["on"].sum(), det["off"].sum())
        assert np.flatnonzero(det["on"])[0] == np.flatnonzero(det["off"])[0]


def test_evaluation_of_false_tracks_and_a_person_standing_still():
    # a hand-made online result: track 1 follows the standing person (speed estimates
    # 0.004 m/s, headings anything), track 2 is a table edge (all its points static, truth 0)
    from nodlidar.sim.scene import scene_from_dict
    from nodlidar.tracking.evaluate import OnlineResult, evaluate

    sc = scene_from_dict({"name": "t", "mover": [
        {"name": "stander", "radius_m": 0.18, "height_m": 1.7, "trajectory": "fixed",
         "position_m": [2.0, 0.0, 0.0]}]})
    res = OnlineResult(sc, True, "renyi", 0, 5)
    rng = np.random.default_rng(0)
    for k in range(5):
        res.records.append({"scan": k, "track": 1, "t_s": 0.1 * k, "x_m": 2.0, "y_m": 0.0,
                            "v_m_s": 0.004, "heading_rad": float(rng.uniform(-3, 3)),
                            "confirmed": k >= 1, "counts": {1: 30}})
        res.records.append({"scan": k, "track": 2, "t_s": 0.1 * k, "x_m": 1.0, "y_m": 1.0,
                            "v_m_s": 0.3, "heading_rad": 0.0, "confirmed": k >= 1,
                            "counts": {0: 12, 1: 1}})
        res.scan_t_s.append(0.1 * k)
        res.confirmed.append([])
    ev = evaluate(res)
    m = ev["movers"][0]
    # judged on speed alone (no heading for a mover standing still): within 0.01 m/s from
    # the first estimate
    assert m["conv"] == 1 and m["final_err_heading_deg"] == 0.0
    assert ev["false_tracks"] == 1


@pytest.mark.slow
@pytest.mark.parametrize("dep", [True, False], ids=["mirrors", "lifted"])
def test_furniture_is_not_a_tracks_own_path(design, dep):
    # TrackerConfig.follow_supported_m_s lets a moving track take a supported cluster when
    # its support is the tracks' own earlier points. A start-up ghost takes a table's edge
    # while static support cannot yet judge it (the map's first 2 s); had those points
    # counted as a track's path, moving ghosts would take the furniture's supported
    # clusters from then on. Counted: supported clusters that are mostly static world
    # (simulator truth 0) with points a track took in that scan. Measured, seed 0, with
    # mirrors / lifted: 5 / 20 when every point tracks took counted as their path, 1 / 2
    # with dynamic clusters only, 0 / 1 once the track must also surely move.
    from nodlidar.tracking.tracker import Tracker

    trk = Tracker(range_sigma=design.lidar.range_sigma_m)
    taken_static = 0
    for s, g in _segment(design, ROOM, 80, dep, SegmentConfig()):
        trk.update(g)
        got = [tr.points[-1] for tr in trk.tracks.values() if tr.last_scan == s.scan]
        for idx in g.supported_objects():
            if (s.truth_id[idx] == 0).mean() <= 0.5:
                continue
            mine = {tuple(p) for p in s.points[idx]}
            taken_static += any(any(tuple(p) in mine for p in pts) for pts in got)
    assert taken_static <= 3, taken_static


@pytest.mark.parametrize("dep", [True, False], ids=["mirrors", "lifted"])
@pytest.mark.parametrize("seed", [0, 5])
def test_a_person_standing_still_is_never_a_confirmed_track(design, dep, seed):
    """``TrackerConfig.confirm_speed_m_s``: in the furnished room's first nod sweep static
    support cannot judge the standing person yet (nothing was hit there 2 s before), so
    their clusters are dynamic and a track follows them - at ~0.005 m/s, after a first
    velocity from two scans of 0.03-0.11 +- 0.1 m/s (seed 5, mirrors: 0.11). A track is
    confirmed only once its speed surely reaches the static speed (0.05 m/s): theirs never
    does. Without: a confirmed track on them (measured, 30 scans, both seeds and
    configurations)."""
    from nodlidar.tracking.evaluate import run_online
    from nodlidar.tracking.tracker import TrackerConfig

    def confirmed_on_stander(speed):
        res = run_online(design, ROOM, 30, mirrors_deployed=dep, seed=seed,
                         tracker=TrackerConfig(confirm_speed_m_s=speed))
        return [r["track"] for r in res.records
                if r["confirmed"] and 2 * r["counts"].get(2, 0) > sum(r["counts"].values())]

    assert confirmed_on_stander(0.05) == []
    assert confirmed_on_stander(0.0)  # the test can fail: the stander's track


def test_a_pole_is_not_confirmed_when_its_speed_is_within_its_uncertainty(scene_runs):
    """``benchmarks/heldout/v-cartable.toml``, lifted, seed 0: its pole is dynamic in the first
    nod sweep (nothing was hit there 2 s before), its speed over 3 scans reads 0.072 +- 0.120
    m/s (measured; then 0.020, 0.009), above ``confirm_speed_m_s``, and by its speed alone it
    is confirmed (a false track). ``confirm_sigmas`` (default 1.5) asks the speed to be 1.5
    of its own standard deviations from zero as well: the pole stays tentative. So does it
    with the older option, ``confirm_sure_scans`` = 4 (the speed less one sd until the
    velocity is 4 scans old; it delays 0.05 m/s movers more). The movers are unchanged by
    either."""
    from pathlib import Path

    from nodlidar.sim.scene import load_scene
    from nodlidar.tracking.evaluate import evaluate, run_online
    from nodlidar.tracking.tracker import TrackerConfig

    scene = load_scene(Path(__file__).resolve().parents[1] / "benchmarks" / "heldout"
                       / "v-cartable.toml")
    cfgs = {"default": TrackerConfig(), "speed alone": TrackerConfig(confirm_sigmas=0.0),
            "sure for 4": TrackerConfig(confirm_sigmas=0.0, confirm_sure_scans=4)}
    ev = {k: evaluate(run_online(scene_runs.design, scene, 90, mirrors_deployed=False, seed=0,
                                 tracker=c))
          for k, c in cfgs.items()}
    false = {k: e["false_tracks"] for k, e in ev.items()}
    assert false == {"default": 0, "speed alone": 1, "sure for 4": 0}, false
    for k in ("default", "sure for 4"):
        for a, b in zip(ev["speed alone"]["movers"], ev[k]["movers"]):
            assert (a["conv_scan"], a["id_switches"], a["tracks"]) == \
                (b["conv_scan"], b["id_switches"], b["tracks"]), (k, a, b)


def test_a_tables_face_sliding_along_itself_is_not_a_mover(design):
    """``TrackerConfig.hold_sliding_lines``: with the mirrors deployed the table's front face
    is cut by the direct window's edge, and at start-up (no static support yet) part of it
    is dynamic. Its other end is where the nodding scan line leaves the face over the top:
    from scan to scan that end slides along the face, and the cluster reads 2.2-2.7 m/s
    along itself (measured, seed 0, scans 4-7; a thin line, sd 8-11 mm across, 0.1-0.22 m
    along). Only its speed across the line may confirm it; the walker's track is unchanged."""
    from nodlidar.tracking.evaluate import evaluate, run_online
    from nodlidar.tracking.tracker import TrackerConfig

    def run(hold):
        res = run_online(design, ROOM, 30, mirrors_deployed=True, seed=0,
                         tracker=TrackerConfig(hold_sliding_lines=hold))
        return evaluate(res), res

    (on, _), (off, res_off) = run(True), run(False)
    assert on["false_tracks"] == 0, on["false_tracks"]
    assert off["false_tracks"] == 1, off["false_tracks"]  # the test can fail: the table
    # the false track's speed, when confirmed, read along the table's face (yaw 10 deg)
    ghost = [r for r in res_off.records if r["confirmed"] and r["counts"].get(0, 0)
             and r["v_m_s"] == r["v_m_s"]][0]
    assert ghost["v_m_s"] > 1.0 and abs(np.degrees(ghost["heading_rad"]) - 10.0) < 5.0, ghost
    walker = [m for m in on["movers"] if m["mover"] == "walker"][0]
    walker_off = [m for m in off["movers"] if m["mover"] == "walker"][0]
    assert walker["conv_scan"] == walker_off["conv_scan"] and walker["tracks"] == \
        walker_off["tracks"], (walker, walker_off)


def test_a_line_is_known_by_its_shape_after_the_tracks_motion():
    """``Tracker._line_normal``: a straight face (0.4 m, 1 cm noise across it) is a line with
    its normal; a person's front arc is not; a line moving along itself over three scans is
    still the same line once moved back along the track's velocity, and a round object
    smeared by its motion is not made one."""
    from types import SimpleNamespace

    from nodlidar.tracking.tracker import _LINE_THIN, Tracker

    rng = np.random.default_rng(0)

    def track(clusters, v):
        pts = [np.column_stack([c, np.zeros(len(c))]) for c in clusters]
        times = [np.full(len(c), 0.1 * k) for k, c in enumerate(clusters)]
        x = np.array([0.0, 0.0, *v])
        return SimpleNamespace(points=pts, times=times, x=x, outline_len=[np.zeros(0)] * len(pts))

    s = np.linspace(-0.2, 0.2, 40)
    d = np.array([np.cos(0.3), np.sin(0.3)])  # the face's direction
    n_true = np.array([-d[1], d[0]])

    def face(shift):
        return (np.outer(s, d) + rng.normal(0, 0.01, (40, 1)) * n_true + shift)

    n, dirn = Tracker._line_normal(track([face(0)] * 3, (0.0, 0.0)))
    assert abs(abs(n @ n_true) - 1.0) < 1e-3 and dirn < _LINE_THIN, (n, dirn)
    a = np.linspace(-1.2, 1.2, 40)
    arc = 0.2 * np.column_stack([-np.cos(a), np.sin(a)])  # a 0.2 m cylinder's front
    assert Tracker._line_normal(track([arc] * 3, (0.0, 0.0))) is None
    # sliding along itself at 1 m/s: moved back, one line
    v = 1.0 * d
    n, _ = Tracker._line_normal(track([face(0.1 * k * v) for k in range(3)], v))
    assert abs(abs(n @ n_true) - 1.0) < 1e-3, n
    # a cylinder's front (+-46 deg of it) moving across at 1.5 m/s: its three arcs smeared
    # along the motion make a line (the test can fail), moved back they coincide, no line
    a = np.linspace(-0.8, 0.8, 40)
    arc = 0.2 * np.column_stack([-np.cos(a), np.sin(a)])
    v = np.array([0.0, 1.5])
    arcs = [arc + 0.1 * k * v for k in range(3)]
    assert Tracker._line_normal(track(arcs, (0.0, 0.0))) is not None
    assert Tracker._line_normal(track(arcs, v)) is None


def test_a_face_with_a_stub_of_the_next_face_is_still_a_line():
    """``Tracker._line_normal``'s dominant line: a 0.5 m face (1 cm noise) with a stub of the
    perpendicular face at its corner (a cabinet or table seen from a driving robot) is that
    face while the stub is under a fifth of the points; its plain spread is not thin. With
    a stub of a third of the points it is an L (not a line), and a person's front arc is
    still no line."""
    from types import SimpleNamespace

    from nodlidar.tracking.tracker import _LINE_THIN, Tracker

    rng = np.random.default_rng(1)

    def track(c):
        pts = [np.column_stack([c, np.zeros(len(c))])] * 3
        return SimpleNamespace(points=pts, times=[np.zeros(len(c))] * 3,
                               x=np.zeros(4), outline_len=[np.zeros(0)] * 3)

    def corner(n_face, n_stub, stub_m):
        face = np.column_stack([np.linspace(0.0, 0.5, n_face), rng.normal(0, 0.01, n_face)])
        stub = np.column_stack([rng.normal(0, 0.01, n_stub), np.linspace(0.02, stub_m, n_stub)])
        return np.vstack([face, stub])

    short = corner(46, 9, 0.18)  # 16 % of the points on the stub
    ev = np.linalg.eigvalsh(np.cov(short.T))
    assert np.sqrt(ev[0] / ev[1]) > _LINE_THIN  # the test can fail: not thin as a whole
    n, dirn = Tracker._line_normal(track(short))
    assert abs(n[1]) > 0.999 and dirn < _LINE_THIN, (n, dirn)
    assert Tracker._line_normal(track(corner(40, 20, 0.3))) is None  # an L
    a = np.linspace(-1.0, 1.0, 40)
    arc = 0.19 * np.column_stack([-np.cos(a), np.sin(a)]) + rng.normal(0, 0.01, (40, 2))
    assert Tracker._line_normal(track(arc)) is None


def test_a_second_rooms_table_face_is_not_a_mover_either(design):
    """``design/scenes/track-three-room.toml`` (written before ``hold_sliding_lines``, a
    false track in each of seeds 0-7 with mirrors): the table's near face at -39 deg, cut
    by the direct window's -40 deg edge. Seed 3, 30 scans: no false track with the rule,
    one without; the walkers' tracks the same."""
    from pathlib import Path

    from nodlidar.sim.scene import load_scene
    from nodlidar.tracking.evaluate import evaluate, run_online
    from nodlidar.tracking.tracker import TrackerConfig

    scene = load_scene(Path(__file__).resolve().parents[1] / "design" / "scenes"
                       / "track-three-room.toml")
    ev = {hold: evaluate(run_online(design, scene, 30, mirrors_deployed=True, seed=3,
                                    tracker=TrackerConfig(hold_sliding_lines=hold)))
          for hold in (True, False)}
    assert ev[True]["false_tracks"] == 0 and ev[False]["false_tracks"] == 1, \
        (ev[True]["false_tracks"], ev[False]["false_tracks"])
    for a, b in zip(ev[True]["movers"], ev[False]["movers"]):
        assert (a["tracks"], a["conv_scan"]) == (b["tracks"], b["conv_scan"]), (a, b)


def test_a_young_tracks_speed_along_a_face_does_not_confirm_it(design):
    """``design/scenes/track-edge-box-away.toml``, lifted, seed 6: a 0.4 x 0.8 m box face-on,
    moving along its face at 0.4 m/s. A new track's first cluster ends where the low scan
    line meets the floor, and its second scan reads ~2 m/s along the face (measured, seed 3:
    2.17 m/s at 3 deg from the face's direction). With ``hold_sliding_lines`` the floor is no
    outline, the face's extent is not shown, and only the speed across the face, less the
    along-face speed the line's direction turns across, may confirm it: the extra tracks on
    the box stay tentative. Without: one of them is confirmed, two identity switches."""
    from pathlib import Path

    from nodlidar.sim.scene import load_scene
    from nodlidar.tracking.evaluate import evaluate, run_online
    from nodlidar.tracking.tracker import TrackerConfig

    scene = load_scene(Path(__file__).resolve().parents[1] / "design" / "scenes"
                       / "track-edge-box-away.toml")
    box = {hold: evaluate(run_online(design, scene, 45, mirrors_deployed=False, seed=6,
                                     tracker=TrackerConfig(hold_sliding_lines=hold)))["movers"][0]
           for hold in (True, False)}
    assert box[True]["id_switches"] == 0 and len(box[True]["tracks"]) >= 2, box[True]
    assert box[False]["id_switches"] == 2, box[False]  # the test can fail


def test_a_ghost_seen_once_is_not_re_acquired_while_its_furniture_is_still_there(design):
    """``TrackerConfig.reacquire_gone_only``: ``design/scenes/track-pace-room.toml``, lifted,
    seed 4. At scan 35 a cluster on the table's edge starts a track (seen once: a start-up
    ghost); at scan 57 the thin lamp 2.2 m away turns dynamic (the visitor walks behind it,
    rays pass beside it) and, with nothing nearer to where the ghost was, re-acquisition of
    lone tracks gave it the ghost's track: two sightings 2.2 s apart, 1 m/s, a confirmed
    false track. The table is still there: the latest scan that looked at the ghost's place
    found most beams ending in it, so the ghost is not re-acquired. The movers unchanged."""
    from nodlidar.tracking.evaluate import evaluate, run_online
    from nodlidar.tracking.tracker import TrackerConfig

    room = "design/scenes/track-pace-room.toml"

    def run(gone_only):
        res = run_online(design, room, 90, mirrors_deployed=False, seed=4,
                         tracker=TrackerConfig(reacquire_gone_only=gone_only))
        return evaluate(res), res

    (on, _), (off, res_off) = run(True), run(False)
    assert on["false_tracks"] == 0 and off["false_tracks"] == 1, \
        (on["false_tracks"], off["false_tracks"])  # the test can fail: the lamp's track
    ghost = [r for r in res_off.records if r["confirmed"] and r["counts"].get(0, 0)][0]
    assert ghost["v_m_s"] > 0.5, ghost  # a speed from a jump, not from the lamp's motion
    for a, b in zip(on["movers"], off["movers"]):
        assert (a["conv_scan"], a["id_switches"], a["tracks"]) == \
            (b["conv_scan"], b["id_switches"], b["tracks"]), (a, b)


def test_a_velocity_must_lay_the_sightings_on_one_another_to_confirm():
    """``Tracker._sightings_agree`` (``TrackerConfig.confirm_overlap``, 0.5): moved back along
    the velocity, the better covered of the latest sighting and the earlier ones has half
    its points within 0.1 m of the other. A person's front arc (a 0.19 m cylinder, 1 cm
    noise) seen twice agrees at its velocity, and when the second sighting shows more of it
    (growing into the view); at a velocity 2 m/s off (0.2 m in 0.1 s) it does not. A
    table's top seen along one scan line and its front edge in the next (the nod meets them
    in turn) do not lay on one another at the velocity the registration gave them (0.99 m/s,
    measured in ``track-drive-room``), nor at zero."""
    from types import SimpleNamespace

    from nodlidar.tracking.tracker import Tracker, TrackerConfig

    rng = np.random.default_rng(0)
    trk = Tracker(TrackerConfig())

    def track(clusters, v, dt=0.1):
        pts = [np.column_stack([c, np.zeros(len(c))]) for c in clusters]
        times = [np.full(len(c), dt * k) for k, c in enumerate(clusters)]
        return SimpleNamespace(points=pts, times=times, x=np.array([0.0, 0.0, *v]),
                               scans=list(range(len(pts))), start=0)

    def arc(center, a0, a1, n=40):
        a = np.linspace(a0, a1, n)
        return (np.asarray(center) + 0.19 * np.column_stack([-np.cos(a), np.sin(a)])
                + rng.normal(0, 0.01, (n, 2)))

    v = np.array([0.0, 0.5])  # across the view, 2 m ahead
    c0, c1 = np.array([2.0, 0.0]), np.array([2.0, 0.05])
    assert trk._sightings_agree(track([arc(c0, -1.0, 1.0), arc(c1, -1.0, 1.0)], v))
    # growing into the view: the first sighting a third of the arc
    assert trk._sightings_agree(track([arc(c0, 0.3, 1.0, 14), arc(c1, -1.0, 1.0)], v))
    assert not trk._sightings_agree(track([arc(c0, -1.0, 1.0), arc(c1, -1.0, 1.0)],
                                          v + [2.0, 0.0]))
    # the table (top 3.4-4.6 x -1.9 to -1.1 m): a scan line across its top near the corner,
    # then its front edge (x = 3.4) from the corner along 0.55 m
    s = np.linspace(0.0, 1.0, 50)
    top = np.column_stack([3.4 + 0.75 * s, -1.1 - 0.35 * s ** 2]) + rng.normal(0, 0.01, (50, 2))
    edge = np.column_stack([np.full(38, 3.42), np.linspace(-1.1, -1.65, 38)]) \
        + rng.normal(0, 0.01, (38, 2))
    for vel in ([-0.75, -0.64], [0.0, 0.0]):
        assert not trk._sightings_agree(track([top, edge], vel, dt=0.2)), vel
    # off: anything agrees
    off = Tracker(TrackerConfig(confirm_overlap=0.0))
    assert off._sightings_agree(track([top, edge], [0.0, 0.0], dt=0.2))


@pytest.mark.slow
def test_a_driving_robots_table_is_not_confirmed_on_two_of_its_parts(design):
    """``design/scenes/track-drive-room.toml`` (held out as ``w-drive-room`` until session 21:
    a false track, lifted, in 7 of 8 seeds): the robot drives at 0.25 m/s past a table; the
    nod meets the table's top (scan 74), then its front edge (scan 76), and the track on them
    read 0.99 m/s and was confirmed. With ``confirm_overlap`` the two sightings do not lie on
    one another at that velocity: no false track in seeds 0 and 1, one in each without; the
    person's track is the same."""
    from pathlib import Path

    from nodlidar.sim.scene import load_scene
    from nodlidar.tracking.evaluate import evaluate, run_online
    from nodlidar.tracking.tracker import TrackerConfig

    scene = load_scene(Path(__file__).resolve().parents[1] / "design" / "scenes"
                       / "track-drive-room.toml")
    for seed in (0, 1):
        ev = {f: evaluate(run_online(design, scene, 90, mirrors_deployed=False, seed=seed,
                                     tracker=TrackerConfig(confirm_overlap=f)))
              for f in (0.5, 0.0)}
        assert (ev[0.5]["false_tracks"], ev[0.0]["false_tracks"]) == (0, 1), \
            (seed, ev[0.5]["false_tracks"], ev[0.0]["false_tracks"])
        a, b = ev[0.5]["movers"][0], ev[0.0]["movers"][0]
        assert (a["conv_scan"], a["tracks"], a["id_switches"]) == \
            (b["conv_scan"], b["tracks"], b["id_switches"]), (seed, a, b)
