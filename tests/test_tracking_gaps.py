"""Tracks across the nod's blind part: a new object that nothing but a track seen once could
be continues it (``TrackerConfig.reacquire_births_m_s``); a young track's vague prediction
does not win a sure track's cluster (``TrackerConfig.assign_likelihood``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from nodlidar.errors import ParameterError
from nodlidar.tracking.scans import ScanPoints
from nodlidar.tracking.tracker import Tracker, TrackerConfig


@pytest.mark.parametrize("seed", [1, 2])
def test_a_person_seen_once_before_the_blind_part_keeps_the_track(seed, scene_runs):
    """``design/scenes/track-side-by-side-fast.toml``, mirrors: the left person is seen
    (dynamic) in scan 5, then the nod's lower part sees only the floor before them until
    scan 25, by when they are 1.2 m on, beyond the gate of a track without a velocity.
    Measured, 45 scans, seeds 0-7, without / with: the left person had two tracks (one
    switch) in 6 of 8 seeds (1, 2, 4, 5, 6, 7) / one track in all 8 (in seed 2 both
    people are new in scan 25, 1.20 and 1.30 m from where the left one was seen: the
    nearer is it); the right person one track either way. Seed 2 since
    ``reacquire_unique_m`` (the two new ones about as near): the left one's new track is
    pending on track 1 for a scan, its own path traced back meets the sighting, and it
    continues track 1; the pending track was never confirmed (never reported)."""
    on = scene_runs("track-side-by-side-fast.toml", 45, seed, True, reacquire_births_m_s=1.5)
    scene_runs.assert_kept(on, tentative_ok=True)
    assert on["left"]["tracks"][0] == 1 and len(on["left"]["tentative_tracks"]) == (seed == 2)
    # the failure, without: a second track for the left person (the first, seen once, was
    # never confirmed: no identity switch since 2026-12-06, but the person is not reported
    # until their second sighting in the new track)
    off = scene_runs("track-side-by-side-fast.toml", 45, seed, True,
                     reacquire_births_m_s=0.0)["left"]
    assert len(off["tracks"]) == 2 and off["tentative_tracks"] == off["tracks"][:1], off


class _Arcs:
    """Stub of Segmented: scan ``k``, a 40-point arc of a 0.18 m cylinder (facing the
    sensor at the origin) at each of ``movers`` (dynamic clusters, in this order) and of
    ``still`` (returns that no cluster is dynamic on), or nothing (one beam, no return).
    The beams have no geometry: each arc's ends count as window cuts, unless ``outlined``
    puts a beam with no return on either side of it (its silhouette)."""

    def __init__(self, k: int, movers=(), still=(), outlined: bool = False):
        arcs = []
        gap = np.full((1, 3), np.nan)
        for c in list(movers) + list(still):
            ang = np.linspace(-1.0, 1.0, 40) + np.arctan2(c[1], c[0])
            xy = np.asarray(c) - 0.18 * np.column_stack([np.cos(ang), np.sin(ang)])
            arc = np.column_stack([xy, np.linspace(0.2, 1.0, 40)])
            arcs.append(np.concatenate([gap, arc, gap]) if outlined else arc)
        pts = np.concatenate(arcs) if arcs else np.full((1, 3), np.nan)
        n = len(pts)
        t = k * 0.1 + np.linspace(0, 0.09, n)
        self.scan = ScanPoints(k, np.arange(n), t, np.full(n, -1),
                               np.where(np.isnan(pts[:, 0]), np.nan, 1.0), pts, pts, pts,
                               np.zeros(n))
        self._n = len(movers)
        w = 42 if outlined else 40
        self._first = 1 if outlined else 0
        lab = np.repeat(np.arange(len(arcs)), w) if arcs else np.full(1, -1)
        if outlined and arcs:
            lab[np.isnan(pts[:, 0])] = -1
        self.cluster = lab
        self.dynamic = (lab >= 0) & (lab < self._n)
        self.ground = np.zeros(n, bool)
        self._w = w

    def objects(self):
        return [self._w * i + self._first + np.arange(40) for i in range(self._n)]


def _run(scans, **config) -> Tracker:
    trk = Tracker(TrackerConfig(**config))
    for s in scans:
        trk.update(s)
    return trk


def test_a_lone_track_takes_the_new_object_nothing_else_could_be():
    # seen once at (3.3, 0.2), then 23 scans of nothing; a new object 0.73 m on (0.3 m/s):
    # beyond the 0.6 m gate of a track without a velocity, within 1.5 m/s x 2.3 s
    gap = [_Arcs(k) for k in range(1, 23)]
    first = [_Arcs(0, [(3.3, 0.2)])]
    trk = _run(first + gap + [_Arcs(23, [(2.65, 0.44)])])
    assert sorted(trk.tracks) == [1] and trk.tracks[1].scans == [0, 23]
    # two new objects it could have reached, 0.69 and 0.94 m from its place: either could
    # be it (reacquire_unique_m, 0.5 m), so neither continues it; with the rule off, the
    # nearer one does and the other is new
    two_new = first + gap + [_Arcs(23, [(2.8, 1.0), (2.65, 0.44)])]
    trk = _run(two_new)
    assert sorted(trk.tracks) == [1, 2, 3] and trk.tracks[1].scans == [0]
    trk = _run(two_new, reacquire_unique_m=0.0)
    assert sorted(trk.tracks) == [1, 2]
    near = _Arcs(23, [(2.65, 0.44)]).scan.points[:, :2].mean(axis=0)  # the same points
    np.testing.assert_allclose(trk.tracks[1].centroids[-1], near, atol=1e-12)
    # the other one 1.3 m farther than the nearer: the nearer is it
    trk = _run(first + gap + [_Arcs(23, [(1.9, 1.9), (2.65, 0.44)])])
    assert sorted(trk.tracks) == [1, 2] and trk.tracks[1].scans == [0, 23]
    # another object nearer to where it was (not moving in this scan, or the furniture a
    # start-up ghost was on): not this one
    trk = _run(first + gap + [_Arcs(23, [(2.65, 0.44)], [(3.2, -0.3)])])
    assert sorted(trk.tracks) == [1, 2]
    trk = _run(first + gap + [_Arcs(23, [(2.65, 0.44)], [(3.3, 0.2)])])
    assert sorted(trk.tracks) == [1, 2]
    # two lone tracks, one new object as near to both: which one is it? A new track
    two = [_Arcs(0, [(3.3, 0.6), (3.3, -0.6)])]
    trk = _run(two + gap + [_Arcs(23, [(2.8, 0.0)])])
    assert sorted(trk.tracks) == [1, 2, 3]
    # farther (3.8 m) than 1.5 m/s could have gone in the 2.3 s (3.4 m): a new object
    trk = _run(first + gap + [_Arcs(23, [(0.6, -2.6)])])
    assert sorted(trk.tracks) == [1, 2]


def test_a_track_seen_once_does_not_gate_one_of_two_that_could_be_it():
    """``reacquire_unique_m``: seen once at (3.3, 0.2), then 22 scans of nothing; two new
    objects 0.24 and 0.52 m from its place, both within the 0.6 m gate of a track without a
    velocity (``benchmarks/heldout/y-three.toml``, mirrors, seed 0: the person seen once
    was the farther one, the nearer had walked into their place)."""
    first = [_Arcs(0, [(3.3, 0.2)])]
    gap = [_Arcs(k) for k in range(1, 23)]
    both = first + gap + [_Arcs(23, [(3.3, 0.44), (2.78, 0.2)])]
    trk = _run(both)
    assert sorted(trk.tracks) == [1, 2, 3] and trk.tracks[1].scans == [0]
    # the farther one seen alone a scan earlier: then it was the only one, and it is
    young = first + gap[:-1] + [_Arcs(22, [(2.78, 0.2)]), _Arcs(23, [(3.3, 0.44), (2.78, 0.2)])]
    trk = _run(young)
    assert sorted(trk.tracks) == [1, 2] and trk.tracks[1].scans == [0, 22, 23]
    # off: the gate's nearest, as before
    trk = _run(both, reacquire_unique_m=0.0)
    assert trk.tracks[1].scans == [0, 23]
    # alone (the other 1.9 m away, beyond 0.24 + 0.5 m): it continues the track
    trk = _run(first + gap + [_Arcs(23, [(3.3, 0.44), (2.0, 1.6)])])
    assert trk.tracks[1].scans == [0, 23]


def test_of_two_that_could_be_a_track_seen_once_the_one_whose_path_passes_its_place_is_it():
    """``reacquire_unique_m``: seen once at (3.3, 0.2) in scan 0; from scan 23 on, X walks
    +y at 0.3 m/s on a path through that place (0.69 m from it in scan 23) and Y walks -x at
    0.3 m/s (0.57 m from it, nearer, on a path 0.49 m wide of it at scan 0). Each is a new
    track pending on track 1; X's own motion, traced back, meets the sighting (within
    ``stitch_turned_m``, 0.35 m), and X continues track 1. With the rule off, the nearer
    one (Y) takes it at once."""
    def objs(k):
        return [(3.3, 0.2 + 0.03 * k), (2.9 - 0.03 * (k - 23), 0.6)]

    scans = [_Arcs(0, [(3.3, 0.2)])] + [_Arcs(k) for k in range(1, 23)] + \
        [_Arcs(k, objs(k)) for k in range(23, 30)]
    trk = _run(scans)
    assert trk.tracks[1].scans[:2] == [0, 23] and trk.tracks[1].scans[-1] == 29
    x = [trk.tracks[1].centroids[i] for i in range(1, len(trk.tracks[1].scans))]
    assert all(abs(c[0] - 3.3) < 0.25 for c in x), x  # X's column, never Y's
    others = [t for tid, t in trk.tracks.items() if tid != 1]
    assert len(others) == 1 and abs(others[0].centroids[-1][1] - 0.6) < 0.25
    off = _run(scans, reacquire_unique_m=0.0)
    assert off.tracks[1].scans[:2] == [0, 23] and abs(off.tracks[1].centroids[1][1] - 0.6) < 0.25


def test_a_person_seen_once_behind_another_is_not_given_the_one_beside_them(scene_runs):
    """``benchmarks/heldout/y-three.toml`` (a person in front of two walking one behind the
    other), mirrors, seed 0: L is seen once in scan 1, then hidden by the front person and
    the nod's blind part; in scan 27 L is 0.52 m from that sighting and R, behind L, has
    walked to 0.24 m from it. Before ``reacquire_unique_m`` the track seen once took R
    (the nearer): an identity switch for L."""
    path = str(Path(__file__).resolve().parents[1] / "benchmarks" / "heldout" / "y-three.toml")
    on = scene_runs(path, 45, 0, True)
    assert on["L"]["id_switches"] == 0 and on["R"]["id_switches"] == 0, on
    assert not set(on["L"]["tracks"]) & set(on["R"]["tracks"]), on
    off = scene_runs(path, 45, 0, True, reacquire_unique_m=0.0)
    assert off["L"]["id_switches"] == 1 and off["L"]["tracks"][0] in off["R"]["tracks"], off


def _vague_on_sure(**config):
    """Track 1 (sure: 10 scans at 0.4 m/s along +y) and track 2 (seen in scans 8 and 9 only,
    its two-scan velocity pointing across track 1's path), then ten scans of nothing, then
    one cluster, put where track 2's prediction is: 1.1 s on, track 2's position sd is
    ~0.14 m, track 1's 0.05 m, and the cluster is track 1's object, 0.08 m off its
    prediction."""
    trk = Tracker(TrackerConfig(**config))

    def a(k):
        return (2.0, -1.0 + 0.04 * k)

    for k in range(10):
        trk.update(_Arcs(k, [a(k)] + ([(2.5 - 0.045 * (k - 9), -0.64 + 0.04 * (k - 9))]
                                      if k >= 8 else [])))
    for k in range(10, 20):
        trk.update(_Arcs(k))
    probe = _Arcs(20, [a(20)])
    t = float(probe.scan.t_s.mean())
    pred = [np.asarray(trk._predict(trk.tracks[i], t).state_vector, float).ravel()[[0, 2]]
            for i in (1, 2)]
    at = np.array(a(20)) + pred[1] - probe.scan.points[:, :2].mean(axis=0)
    scan = _Arcs(20, [tuple(at)])
    c = scan.scan.points[:, :2].mean(axis=0)
    cov = [np.asarray(trk._predict(trk.tracks[i], t).covar, float)[np.ix_([0, 2], [0, 2])]
           for i in (1, 2)]
    trk.update(scan)
    return trk, c, pred, cov


def test_a_vague_prediction_does_not_win_a_sure_tracks_cluster():
    trk, c, pred, cov = _vague_on_sure()
    # the set-up: the cluster is on track 2's prediction, 0.05-0.1 m off track 1's, and
    # track 2's prediction is the vaguer by far (so nearer in its own sigmas)
    # (within 1 cm: moved, the arc turns to face the sensor and its centroid shifts by mm)
    np.testing.assert_allclose(c, pred[1], atol=0.01)
    assert 0.05 < np.hypot(*(c - pred[0])) < 0.1
    assert np.sqrt(np.linalg.eigvalsh(cov[1])[-1]) > 2 * np.sqrt(np.linalg.eigvalsh(cov[0])[-1])
    d2 = [float((c - p) @ np.linalg.solve(S + np.eye(2) * 0.01, c - p)) for p, S in zip(pred, cov)]
    assert d2[1] < d2[0]
    # by likelihood: track 1 takes it; track 2 coasts on, free to take its own object
    assert sorted(trk.tracks) == [1, 2]
    assert trk.tracks[1].last_scan == 20 and trk.tracks[2].last_scan == 9
    # by d^2 alone: track 2 took it, track 1 shared it, and the younger ended
    trk, *_ = _vague_on_sure(assign_likelihood=False)
    assert sorted(trk.tracks) == [1]
    assert [(t.track_id, t.last_scan) for t in trk.ended] == [(2, 20)]


@pytest.mark.parametrize("seed", [2, 4])
def test_side_by_side_on_the_diagonal_keeps_both_tracks(seed, scene_runs):
    """``design/scenes/track-side-by-side-diagonal.toml``, mirrors: the right person is seen
    in scans 12 and 13, then the nod's lower part sees the floor before them for ten scans;
    their track's two-scan velocity is 0.6 m/s at ~85 deg (truth 0.4 at 45), so 1.1 s on
    its prediction falls on the left person. Measured, 45 scans, seeds 0-7, by d^2 alone /
    by likelihood: that track won the left person's cluster, was coalesced into the left
    track, and the right person got a second track in seeds 2 and 4 / one track each in
    all 8."""
    on = scene_runs("track-side-by-side-diagonal.toml", 45, seed, True, assign_likelihood=True)
    scene_runs.assert_kept(on)
    # the failure, without: a second track for the right person (with the segmentation of
    # then: the scan-line links, SegmentConfig.scan_line_sigmas, alone keep it away in seed 2)
    off = scene_runs("track-side-by-side-diagonal.toml", 45, seed, True,
                     segment={"scan_line_sigmas": 0.0}, assign_likelihood=False)
    assert off["right"]["id_switches"] == 1 and len(off["right"]["tracks"]) == 2, off["right"]



def test_a_moving_track_that_turned_unseen_is_reacquired_only_when_asked():
    """Opt-in ``reacquire_moving``: a track moving +y at 0.4 m/s for 10 scans, unseen for
    12, is seen again 0.25 m *behind* where it was last seen (it turned in the gap): 1.1 m
    from its constant-velocity prediction, beyond every gate, within its speed x 1.3 s
    + ``gate_m`` of where it was. By default: a new track; with the option: the same
    track, its motion restarted."""
    seen = [_Arcs(k, [(3.0, -1.0 + 0.04 * k)]) for k in range(10)]
    gap = [_Arcs(k) for k in range(10, 22)]
    back = _Arcs(22, [(3.0, -0.89)])
    trk = _run(seen + gap + [back])
    assert sorted(trk.tracks) == [1, 2]
    trk = Tracker(TrackerConfig(reacquire_moving=True))
    for s in seen + gap[:-1]:
        trk.update(s)
    assert trk.tracks[1].motion is not None
    trk.update(gap[-1])
    trk.update(back)
    assert sorted(trk.tracks) == [1] and trk.tracks[1].scans[-1] == 22
    assert trk.tracks[1].start == 10  # the motion starts afresh at the new sighting
    # too far for its own speed: 0.4 m/s x 1.3 s + 0.6 m = 1.12 m; 1.5 m is someone else
    trk = Tracker(TrackerConfig(reacquire_moving=True))
    for s in seen + gap:
        trk.update(s)
    trk.update(_Arcs(22, [(3.0, -0.36 - 1.5)]))
    assert sorted(trk.tracks) == [1, 2]


def _pacing(k_back: int, x_back: float = 3.0, v_back: float = -0.04):
    """Scans 0-9: a mover at x 3.0 m going +y at 0.4 m/s; 10-21: nothing (the nod's blind
    part; it turns at scan 16, at y -0.36); from 22 to ``k_back``: seen again at
    ``x_back``, moving ``v_back`` m per scan along y from where it would be after the turn."""
    seen = [_Arcs(k, [(3.0, -1.0 + 0.04 * k)]) for k in range(10)]
    gap = [_Arcs(k) for k in range(10, 22)]
    back = [_Arcs(k, [(x_back, -0.36 - 0.04 * 6 + v_back * (k - 22))])
            for k in range(22, k_back)]
    return seen + gap + back


def test_a_track_lost_while_it_turned_is_continued_when_the_motions_meet():
    """``TrackerConfig.stitch_turned_m``: a mover that turned in the nod's blind part is
    seen again beyond every gate of its track (the grid's back-and-forth movers at 0.6
    and 1.0 m/s: one switch per seed before). The new track's motion, traced back, meets
    the lost track's at the turn: the lost track continues, the new one is never
    confirmed (never reported as an object). Without it: two confirmed tracks."""
    trk = Tracker(TrackerConfig())
    out = [st for s in _pacing(28) for st in trk.update(s)]
    assert sorted(trk.tracks) == [1] and trk.tracks[1].scans[-1] == 27
    assert trk.tracks[1].start == 10  # the motion starts afresh with the new sighting
    assert float(trk.tracks[1].x[3]) < -0.3  # now going -y
    # track 2 was reported only as tentative, and ended when track 1 took its scans
    assert not any(st.confirmed for st in out if st.track_id == 2)
    assert [st.alive for st in out if st.track_id == 2][-1] is False
    assert 2 not in [t.track_id for t in trk.all_tracks()]  # its points are track 1's now
    old = _run_with(_pacing(28), stitch_turned_m=0.0)  # fails without: two tracks
    assert sorted(old.tracks) == [1, 2] and old.tracks[2].scans[-1] == 27


def _run_with(scans, **config) -> Tracker:
    trk = Tracker(TrackerConfig(**config))
    for s in scans:
        trk.update(s)
    return trk


def _stop_in_the_gap(k_end: int = 38) -> list:
    """0.7 m/s along +y for 10 scans, nothing for 14 (the nod's blind part), in which it
    stops 0.21 m on (at scan 12: 0.84 m short of where it would be); then standing
    there."""
    seen = [_Arcs(k, [(3.0, -1.0 + 0.07 * k)], outlined=True) for k in range(10)]
    gap = [_Arcs(k) for k in range(10, 24)]
    still = [_Arcs(k, [(3.0, -1.0 + 0.07 * 12)], outlined=True) for k in range(24, k_end)]
    return seen + gap + still


def _walk_off_in_the_gap(k_end: int = 45) -> list:
    """0.4 m/s along +y for 10 scans, standing for 15, nothing for 12, in which it walks
    off along +x at 1 m/s (from scan 25: 1.2 m on when seen again at scan 37)."""
    stand = (3.0, -1.0 + 0.04 * 10)
    seen = [_Arcs(k, [(3.0, -1.0 + 0.04 * k)], outlined=True) for k in range(10)]
    seen += [_Arcs(k, [stand], outlined=True) for k in range(10, 25)]
    gap = [_Arcs(k) for k in range(25, 37)]
    off = [_Arcs(k, [(stand[0] + 0.1 * (k - 25), stand[1])], outlined=True)
           for k in range(37, k_end)]
    return seen + gap + off


@pytest.mark.parametrize("scans", [_stop_in_the_gap, _walk_off_in_the_gap],
                         ids=["stopped", "walked off"])
def test_a_track_lost_while_it_stopped_or_walked_off_is_continued(scans):
    """``TrackerConfig.stitch_stopped``: a person who stops while the nod looks away is
    seen again standing on their path, short of every gate of the track; one who stood
    and walked off unseen, 1.2 m on at 1 m/s. Their paths meet the lost track's, but the
    speed changed: without it, two tracks (an identity switch in every run of
    ``benchmarks/heldout/r-stopgo.toml``)."""
    trk = _run(scans())
    end = scans()[-1].scan.scan
    assert sorted(trk.tracks) == [1] and trk.tracks[1].scans[-1] == end
    assert trk.tracks[1].moved  # still reported as the object it was
    old = _run_with(scans(), stitch_stopped=False)
    assert 2 in old.tracks and old.tracks[2].scans[-1] == end  # a new track took it
    assert 1 not in old.tracks or old.tracks[1].scans[-1] < old.tracks[2].scans[0]


def test_a_new_track_whose_motion_does_not_meet_the_lost_one_is_its_own():
    # the same gap, but the new object walks 0.5 m to the side of the turn (parallel paths
    # 0.5 m apart never meet), or at 1.0 m/s (2.5 times the lost track's speed): another
    # mover, not the lost one turned
    for scans in (_pacing(28, x_back=3.5), _pacing(28, v_back=-0.1)):
        trk = _run(scans)
        assert 2 in trk.tracks and trk.tracks[2].scans[0] == 22, sorted(trk.tracks)
        assert trk.tracks[2].scans[-1] == 27 and trk.tracks[2].parent is None
        assert trk.tracks[1].scans[-1] == 9  # the lost track kept nothing of it


def test_a_young_track_follows_its_person_down_the_nods_sweep(scene_runs):
    """``design/scenes/track-four-crossing.toml``, mirrors, seed 6: person A (0.5 m/s, 2 m
    out) is dynamic in one scan of the first sweep; in the next scans the nod shows them at
    new heights where few rays had passed, and only a few of their points are inconsistent
    (too few for a birth). Continuing a track on that weaker evidence
    (``TrackerConfig.follow_inconsistent_fraction``) gives it a velocity within the sweep.
    Measured, 60 scans: converged at scan 6 with it, 28 (the next sweep) without; seeds 0-7
    with mirrors 6 28 28 28 6 6 28 4 -> 5 28 13 13 6 6 6 4."""
    a = scene_runs("track-four-crossing.toml", 60, 6, True)["A"]
    assert a["conv_scan"] is not None and a["conv_scan"] <= 8, a
    assert a["id_switches"] == 0 and len(a["tracks"]) == 1, a
    old = scene_runs("track-four-crossing.toml", 60, 6, True, follow_inconsistent_fraction=1.0)["A"]
    assert old["conv_scan"] is not None and old["conv_scan"] >= 27, old  # the next sweep


def test_a_reacquired_track_forgets_its_sighting_before_the_gap():
    """``reacquire_forget_scans``: a track seen once (at y = 1.9 m) and re-acquired after
    the gap by an object that nothing else could be, here 1.92 m on 2.2 s later and walking
    at 0.6 m/s. The two sightings imply 0.87 m/s: right only if they were one object at
    one speed. ``benchmarks/heldout/s-push.toml``, mirrors, seed 3: the one sighting was
    a person, the object re-acquired the trolley they pushed ahead of them, and with the
    person's points in its window the trolley's track read 0.085 m/s fast to the end (scan
    65). Six sightings after re-acquisition the window drops the one before the gap."""
    def run(forget):
        trk = Tracker(TrackerConfig(reacquire_forget_scans=forget))
        scans = [_Arcs(0, [(3.0, 1.9)], outlined=True)] + [_Arcs(k) for k in range(1, 22)] + \
            [_Arcs(k, [(3.0, -0.02 - 0.06 * (k - 22))], outlined=True) for k in range(22, 40)]
        speed = {}
        for s in scans:
            for st in trk.update(s):
                assert st.track_id == 1  # one track throughout, either way
                speed[s.scan.scan] = st.v_m_s
        return speed

    on, off = run(6), run(0)
    # the same until the sixth sighting since; then the object's own speed (the stub's
    # arcs, facing the sensor, read 0.593 m/s for 0.6 once settled: 0.01 m/s)
    assert on[26] == off[26] and on[26] > 0.8
    assert abs(on[27] - 0.6) <= 0.01 and abs(on[39] - 0.6) <= 0.01
    assert off[28] > 0.8 and off[30] > 0.75  # the failure: the gap's speed lingers
    with pytest.raises(ParameterError, match="reacquire_forget_scans = -1"):
        TrackerConfig(reacquire_forget_scans=-1)


def test_side_by_side_seen_twice_before_the_blind_part_is_decided_by_the_new_motions(
        scene_runs):
    """``TrackerConfig.ambiguous_chi2``: ``design/scenes/track-side-by-side-blind.toml``
    (two people 0.42 m apart walking side by side towards the sensor), mirrors, seed 5.
    The right person is seen in scans 7 and 8 before the nod's blind part, with a velocity
    15 deg off towards the left one (0.49 m/s, sd 0.11 m/s). Predicted 1.8 s on, both
    people are about equally likely: costs 4.16 (left) and 4.35 (right), measured. Taken
    by the cost, the track went to the left person and the right one got a new track (an
    identity switch). Left to the two new tracks' own motions (:meth:`Tracker._stitch`),
    the one whose path meets the lost track's nearer continues it: the right person."""
    on = scene_runs("track-side-by-side-blind.toml", 50, 5, True)
    assert on["R"]["id_switches"] == 0 and on["L"]["id_switches"] == 0, on
    assert on["R"]["conv"] is not None and on["L"]["conv"] is not None, on
    # the right person's first track is the one it had before the blind part: the left
    # person's is another
    assert min(on["R"]["tracks"]) < min(on["L"]["tracks"]), on
    off = scene_runs("track-side-by-side-blind.toml", 50, 5, True, ambiguous_chi2=0.0)
    assert off["R"]["id_switches"] == 1, off  # the failure, without


def test_ambiguous_chi2_is_checked():
    with pytest.raises(ParameterError, match="ambiguous_chi2"):
        TrackerConfig(ambiguous_chi2=-1.0)
