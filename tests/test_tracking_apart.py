"""What the scan sees between and through objects: clusters the scan saw free space between
are two objects, however close their centroids (:func:`nodlidar.tracking.segment.seen_apart`,
``TrackerConfig.merge_seen_apart``); neighbouring beams on one surface are one object,
whatever the range noise (:func:`nodlidar.tracking.segment.scan_line_links`,
``SegmentConfig.scan_line_sigmas``); rays through where an object was end just behind it
when it walks straight away (:func:`nodlidar.tracking.segment.seen_through`,
``TrackerConfig.follow_seen_through_m``)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from nodlidar.tracking.scans import ScanPoints
from nodlidar.tracking.segment import (
    cluster_points,
    hidden_between,
    scan_line_links,
    seen_apart,
    seen_through,
)
from nodlidar.tracking.voxels import VoxelGrid

STEP = 2 * np.pi / 1024
SCENES = Path(__file__).resolve().parents[1] / "design" / "scenes"


def _scan(discs: list[tuple[float, float, float]], boxes: list[tuple[float, float, float, float]] = (),
          z: float = 0.5, back_m: float = 4.5) -> tuple[ScanPoints, np.ndarray]:
    """A noise-free 2D scan at height ``z`` from the origin over -60..60 deg: vertical
    cylinders ``(x, y, radius)``, axis-aligned boxes ``(x0, y0, x1, y1)`` and a back wall at
    ``x = back_m``. Returns the scan and each beam's object (0 the wall, 1.. the discs, then
    the boxes)."""
    k = int(np.radians(60) / STEP)
    th = np.arange(-k, k + 1) * STEP
    d = np.stack([np.cos(th), np.sin(th), np.zeros_like(th)], axis=1)
    r = back_m / np.cos(th)
    obj = np.zeros(len(th), int)
    for i, (cx, cy, rad) in enumerate(discs, start=1):
        b = d[:, 0] * cx + d[:, 1] * cy
        disc = b * b - (cx * cx + cy * cy - rad * rad)
        t = b - np.sqrt(np.maximum(disc, 0))
        hit = (disc > 0) & (t > 0) & (t < r)
        r[hit], obj[hit] = t[hit], i
    for i, (x0, y0, x1, y1) in enumerate(boxes, start=1 + len(discs)):
        with np.errstate(divide="ignore", invalid="ignore"):
            tx = np.sort(np.stack([x0 / d[:, 0], x1 / d[:, 0]]), axis=0)
            ty = np.sort(np.stack([y0 / d[:, 1], y1 / d[:, 1]]), axis=0)
        tin, tout = np.maximum(tx[0], ty[0]), np.minimum(tx[1], ty[1])
        hit = (tin < tout) & (tin > 0) & (tin < r)
        r[hit], obj[hit] = tin[hit], i
    n = len(th)
    pts = r[:, None] * d + np.array([0.0, 0.0, z])
    start = np.tile([0.0, 0.0, z], (n, 1))
    return ScanPoints(0, np.arange(n), np.zeros(n), np.full(n, -1), r, pts, start, d,
                      np.zeros(n)), obj


def test_a_gap_between_two_people_is_seen_but_not_inside_one_object():
    # two people (r 0.18 m) side by side 0.42 m apart, 2 m out, abreast across the line of
    # sight: a 6 cm gap the beams (1.2 cm apart at 2 m) pass through to the wall
    scan, obj = _scan([(2.0, -0.21, 0.18), (2.0, 0.21, 0.18)])
    a, b = np.flatnonzero(obj == 1), np.flatnonzero(obj == 2)
    assert seen_apart(scan, a, b)
    assert seen_apart(scan, b, a)
    # one person split into two clusters (its two halves): the segment between them is
    # inside the person, where no ray goes
    one, obj1 = _scan([(2.0, 0.0, 0.2)])
    p = np.flatnonzero(obj1 == 1)
    assert not seen_apart(one, p[: len(p) // 2], p[len(p) // 2:])
    # a 0.6 x 0.4 m box seen on its corner: its two faces as two clusters are one object
    box, objb = _scan([], [(1.8, -0.5, 2.4, -0.1)])
    q = np.flatnonzero(objb == 1)
    face = box.points[q, 0] > 1.8 + 1e-6  # the side face (y = -0.1 m), not the front x = 1.8
    assert face.any() and (~face).any()
    assert not seen_apart(box, q[face], q[~face])


def test_the_gap_must_be_at_the_objects_height():
    # the same gap seen only by rays above both clusters (the clusters' points at z 0.5 m,
    # the rays at 1.2 m: over two low boxes, not between them; over one box's top, the
    # chord between its faces would be crossed too). The beams between the two are put in
    # another window, so that only the rays can tell (one window's scan line is the
    # other test, below)
    scan, obj = _scan([(2.0, -0.21, 0.18), (2.0, 0.21, 0.18)])
    a, b = np.flatnonzero(obj == 1), np.flatnonzero(obj == 2)
    mirror = np.where(obj == 0, 1, -1)
    pts = scan.points.copy()
    pts[:, 2] = 0.5
    high = ScanPoints(0, scan.steps, scan.t_s, mirror, scan.range_m, pts,
                      scan.ray_start + np.array([0.0, 0.0, 0.7]), scan.ray_dir, scan.ray_offset)
    assert not seen_apart(high, a, b)
    low = ScanPoints(0, scan.steps, scan.t_s, mirror, scan.range_m, pts, scan.ray_start,
                     scan.ray_dir, scan.ray_offset)
    assert seen_apart(low, a, b)


def test_one_behind_the_other_is_a_jump_in_depth_not_a_grazing_surface():
    # a disc partly behind another, to one side: no ray reaches the free space
    # between them (every beam past the front disc's edge ends on the far one), but the
    # scan line jumps in depth at the front one's edge, once
    scan, obj = _scan([(1.5, 0.0, 0.1), (1.82, 0.15, 0.2)])
    a, b = np.flatnonzero(obj == 1), np.flatnonzero(obj == 2)
    assert len(a) and len(b)
    assert seen_apart(scan, a, b)
    # a wall seen at 70-80 deg incidence, split into two clusters: it recedes by a similar
    # step at every beam, so the step between the two is no occlusion
    th = np.arange(int(np.radians(70) / STEP), int(np.radians(80) / STEP) + 1) * STEP
    r = 0.8 / np.cos(th)
    d = np.stack([np.cos(th), np.sin(th), np.zeros_like(th)], axis=1)
    n = len(th)
    wall = ScanPoints(0, np.arange(n), np.zeros(n), np.full(n, -1), r, r[:, None] * d,
                      np.zeros((n, 3)), d, np.zeros(n))
    half = n // 2
    assert not seen_apart(wall, np.arange(half), np.arange(half + 1, n))
    # one person with a thin pole in front of it: its two sides are two clusters, with two
    # jumps between them (to the pole and back) - a third object, not one behind the other
    pole, objp = _scan([(2.0, 0.0, 0.2), (1.5, 0.0, 0.03)])
    person = np.flatnonzero(objp == 1)
    left, right = person[person < np.flatnonzero(objp == 2).min()], \
        person[person > np.flatnonzero(objp == 2).max()]
    assert len(left) and len(right)
    assert not seen_apart(pole, left, right)


def test_a_face_cut_by_a_nearer_object_is_hidden_between_its_pieces():
    # a 0.8 m box's face 2.75 m out with a person (r 0.18 m) 2.5 m out in front of its
    # middle: every beam between the face's two visible pieces ends on the person, 0.25 m
    # or more in front of both; the pieces' ends are 0.4 m apart
    scan, obj = _scan([(2.5, 0.0, 0.18)], [(2.75, -0.4, 3.25, 0.4)])
    face = np.flatnonzero(obj == 2)
    person = np.flatnonzero(obj == 1)
    left, right = face[face < person.min()], face[face > person.max()]
    assert len(left) >= 5 and len(right) >= 5
    assert hidden_between(scan, left, right) and hidden_between(scan, right, left)
    assert not seen_apart(scan, left, right)
    gap = np.hypot(*(scan.points[left[-1], :2] - scan.points[right[0], :2]))
    assert 0.35 < gap < 0.45, gap
    assert not hidden_between(scan, left, right, max_gap_m=0.3)
    # two people abreast: the beams between them reach the wall, behind both
    two, obj2 = _scan([(2.0, -0.21, 0.18), (2.0, 0.21, 0.18)])
    assert not hidden_between(two, np.flatnonzero(obj2 == 1), np.flatnonzero(obj2 == 2))
    # one person partly behind another: the scan line steps from one to the other, no
    # beam between them
    near, objn = _scan([(1.5, 0.0, 0.1), (1.82, 0.15, 0.2)])
    assert not hidden_between(near, np.flatnonzero(objn == 1), np.flatnonzero(objn == 2))
    # a beam between the pieces that ends beside them (the face itself, seen through a
    # hole in the occluder) is no hiding
    holed = dataclasses.replace(scan, range_m=scan.range_m.copy())
    mid = person[len(person) // 2]
    holed.range_m[mid] = scan.range_m[left[-1]]
    assert not hidden_between(holed, left, right)


def test_two_tracks_sharing_a_box_unseen_apart_become_one(scene_runs):
    """``design/scenes/track-edge-box-away.toml``, lifted, seed 5: the box's first track
    missed it for a scan (its prediction 0.6 m off after the nod's blind part) and a second
    track was born on it; once confirmed, the two split the box's one cluster between their
    predictions and took it in turns. With ``TrackerConfig.shared_scans`` the younger ends
    after four such sightings: 2 identity switches and converged at scan 36 (measured);
    without it, 10 switches and scan 64. With ``TrackerConfig.newton_recentre`` (default
    since the twenty-seventh session: the refinement's minimiser changed) the first track
    keeps the box on this seed (0 switches, scan 54, with or without the rule), so the
    situation the rule is for is made here with the old minimiser path."""
    box = scene_runs("track-edge-box-away.toml", 70, 5, False, newton_recentre=False)["box"]
    assert box["id_switches"] <= 2 and box["conv"] is not None, box
    old = scene_runs("track-edge-box-away.toml", 70, 5, False, newton_recentre=False,
                     shared_scans=0)["box"]
    assert old["id_switches"] >= 5, old  # the failure, without the rule


def test_shared_scans_is_checked():
    from nodlidar.errors import ParameterError
    from nodlidar.tracking.tracker import TrackerConfig

    with pytest.raises(ParameterError, match="shared_scans = -1 .*>= 0"):
        TrackerConfig(shared_scans=-1)
    with pytest.raises(ParameterError, match="shared_dv_m_s = -1.0 .*>= 0"):
        TrackerConfig(shared_dv_m_s=-1.0)


def test_a_cluster_of_few_beams_does_not_lend_its_outer_edge():
    # a box's face and, beyond its corner, the side face at grazing incidence receding
    # ~0.1 m per beam, then the background 1 m further: the side face's last two beams as
    # their own cluster are part of the same surface, and the jump to the background at
    # their outer edge is not between the two (measured: hd-box-fast, mirrors, seed 5,
    # scan 26 - a second track took the box)
    r = np.array([1.90, 1.91, 1.90, 1.89, 1.91, 1.90, 2.00, 2.10, 2.21, 3.15, 3.16, 3.15])
    th = (np.arange(len(r)) - 6) * STEP
    d = np.stack([np.cos(th), np.sin(th), np.zeros_like(th)], axis=1)
    n = len(r)
    scan = ScanPoints(0, np.arange(n), np.zeros(n), np.full(n, -1), r, r[:, None] * d,
                      np.zeros((n, 3)), d, np.zeros(n))
    assert not seen_apart(scan, np.arange(7), np.array([7, 8]))
    # a person behind another's edge is still seen apart from it with few beams of its own:
    # the jump lies between the two
    r2 = r.copy()
    r2[7:9] = [2.45, 2.46]
    behind = ScanPoints(0, np.arange(n), np.zeros(n), np.full(n, -1), r2, r2[:, None] * d,
                        np.zeros((n, 3)), d, np.zeros(n))
    assert seen_apart(behind, np.arange(7), np.array([7, 8]))


def _noisy(scan: ScanPoints, rng: np.random.Generator, rel: float = 0.01) -> ScanPoints:
    """``scan`` with the URG-04LX's range noise beyond 1 m (1 % of the range, along each ray)."""
    r = scan.range_m * (1 + rel * rng.standard_normal(len(scan.range_m)))
    return dataclasses.replace(scan, range_m=r, points=scan.ray_start + r[:, None] * scan.ray_dir)


def _labels(scan: ScanPoints, sigmas: float, rel: float = 0.01) -> np.ndarray:
    """The segmentation's top-view clustering of every beam (its linking distance, floor,
    minimum size and attachment), with scan-line links at ``sigmas`` (0: none)."""
    idx = np.arange(len(scan.range_m))
    eps = np.clip(4.0 * scan.range_m * STEP, 0.05, 0.15)
    links = (scan_line_links(scan, idx, eps, sigmas * np.sqrt(2) * rel * scan.range_m)
             if sigmas else None)
    return cluster_points(scan.points[:, :2], eps, 5, attach_m=0.15, links=links)


def _share(discs, boxes, sigmas: float, test, draws: int = 200) -> float:
    """Share of ``draws`` noisy scans of the objects in which ``test(labels of each
    object's beams)`` holds (seeded: the same draws for every call)."""
    rng = np.random.default_rng(0)
    base, obj = _scan(discs, boxes)
    hits = 0
    for _ in range(draws):
        lab = _labels(_noisy(base, rng), sigmas)
        hits += bool(test([lab[obj == i] for i in range(1, obj.max() + 1)]))
    return hits / draws


def _one(lab: np.ndarray) -> bool:
    return len(set(lab.tolist()) - {-1}) == 1


def _main(lab: np.ndarray) -> int:
    """The cluster most of the beams are in."""
    return int(np.bincount(lab[lab >= 0]).argmax()) if (lab >= 0).any() else -1


@pytest.mark.parametrize("box", [(1.3, -2.1, 1.8, -0.9), (1.8, -1.6, 2.2, -1.0)],
                         ids=["cart-1.2m", "box-0.6m"])
def test_a_face_seen_obliquely_is_one_cluster_whatever_the_range_noise(box):
    # a cart's 1.2 m face at 35-58 deg bearing, 1.6-2.5 m out, and the 0.6 m face of a box,
    # with the URG's 1 % range noise: neighbours' points move along their rays, and steps
    # between neighbours of 0.06-0.1 m exceed the linking distance (5-6 cm there). Measured
    # over 200 draws: the cart's face is one cluster in 6.5 % of them without the scan-line
    # links, 98 % with; the box's in 26 % / 99.5 %. The bounds leave room for other draws
    one = _share([], [box], 2.0, lambda objs: _one(objs[0]))
    none = _share([], [box], 0.0, lambda objs: _one(objs[0]))
    assert one >= 0.95 and none <= 0.5, (one, none)


@pytest.mark.parametrize("discs", [[(2.0, -0.21, 0.18), (2.0, 0.21, 0.18)],
                                   [(2.0, 0.0, 0.18), (2.3, 0.33, 0.18)]],
                         ids=["abreast", "one-behind"])
def test_links_along_the_scan_line_do_not_join_two_people(discs):
    # two people 0.42-0.45 m apart: abreast (rays through the 6 cm gap to the wall, 2.5 m
    # further: a link needs consecutive beams) and one partly behind the other (a 0.25 m
    # step in depth at the boundary, above the allowance: 5 cm + 2 sqrt 2 x 2 cm). Each
    # person's beams are mostly in a cluster of their own in every draw. (A single edge
    # beam may attach to the other person's cluster, with or without the links: the
    # tracker's split by what the scan saw apart is for that)
    apart = _share(discs, [], 2.0, lambda objs: _main(objs[0]) != _main(objs[1]))
    assert apart == 1.0, apart


def test_scan_line_sigmas_is_checked():
    from nodlidar.errors import ParameterError
    from nodlidar.tracking.segment import SegmentConfig

    with pytest.raises(ParameterError, match="scan_line_sigmas = -1.0 .*>= 0"):
        SegmentConfig(scan_line_sigmas=-1.0)


def test_a_long_cart_keeps_one_track(scene_runs):
    # design/scenes/track-long-cart.toml: the noise broke the cart's 1.2 m face into two to
    # four clusters, two tracks followed its two ends at its own velocity, and the identity
    # switched between them scan by scan (lifted, seeds 0 / 1: 16 / 17 switches; with
    # mirrors no seed converged in 90 scans). Now one track, converged (measured: lifted at
    # scan 2 / 2 with the cart, mirrors 4 / 5)
    for seed in (0, 1):
        for mirrors in (False, True):
            cart = scene_runs("track-long-cart.toml", 90, seed, mirrors)["cart"]
            assert cart["id_switches"] == 0 and len(cart["tracks"]) == 1, (seed, mirrors, cart)
            assert cart["conv"] is not None, (seed, mirrors, cart)


@pytest.mark.parametrize("seed", [0, 1])
def test_furniture_broken_by_the_noise_is_not_a_track(seed, scene_runs):
    # design/scenes/track-room-furniture.toml, lifted: pieces of the furniture's faces,
    # broken off by the range noise, kept enough inconsistent points in the first nod cycle
    # to pass for movers, and 2 / 4 false tracks were confirmed (seeds 0 / 1). Linked along
    # the scan line, each piece is part of its surface, whose consistent points outweigh
    # them: none
    from nodlidar.sim.scene import load_scene
    from nodlidar.tracking.evaluate import evaluate, run_online

    scene = load_scene(SCENES / "track-room-furniture.toml")
    ev = evaluate(run_online(scene_runs.design, scene, 90, mirrors_deployed=False, seed=seed))
    assert ev["false_tracks"] == 0, ev["false_tracks"]
    assert ev["movers"][0]["id_switches"] == 0


def test_a_fast_box_keeps_one_track(scene_runs):
    """``design/scenes/track-box-fast.toml``, mirrors: a person-sized box at 0.6 m/s. Its far
    corner, two or three beams beside the front face at grazing incidence, was seen apart
    from the face by the jump at the corner's own outer edge, and a second track took the
    box (seed 5: tracks 1 and 2 from scan 26, 3 switches). Measured, 90 scans, seeds 0-7:
    switches 4 -> 2 (seed 1, at the turn at scan 67: a piece is seen apart by a ray and
    the turned box's cluster goes to it for two scans)."""
    box = scene_runs("track-box-fast.toml", 45, 5, True)["box"]  # fails without: 2 tracks
    assert box["id_switches"] == 0 and box["tracks"] == [1] and box["purity"] >= 0.99, box


def test_a_box_cut_by_a_persons_shadow_keeps_one_track(scene_runs):
    """``design/scenes/track-side-by-side-box.toml``, mirrors: a box walking behind a person
    (as the sensor sees it) is cut by the person's shadow into two pieces 0.4-0.45 m apart,
    beyond ``merge_m``; the trailing piece got a track of its own and the identity switched
    between the two (measured, 80 scans, seeds 0-7: 4 2 3 5 3 2 3 2 switches; lifted
    sees more of the box: none). Across a gap the scan saw nothing of
    (``TrackerConfig.merge_hidden_m``): one track, no switch, in every seed."""
    for seed in (0, 1):
        box = scene_runs("track-side-by-side-box.toml", 60, seed, True)["box"]
        assert box["id_switches"] == 0 and len(box["tracks"]) == 1, (seed, box)
        assert box["purity"] >= 0.99, (seed, box)
    old = scene_runs("track-side-by-side-box.toml", 60, 0, True, merge_hidden_m=0.0)["box"]
    assert old["id_switches"] >= 1 and len(old["tracks"]) == 2, old  # the failure, without


def test_two_people_behind_a_third_are_not_one_object(scene_runs):
    """``design/scenes/track-two-behind-one.toml``, lifted, seed 4: two people abreast behind a
    third, who hides the gap between them and most of one. Their pieces lie on both sides of
    the third's shadow, as a box's do, but span 0.8 m: without the extent bound
    (``TrackerConfig.merge_hidden_extent_m``) the hidden person's pieces joined the other's
    track and their longest track's purity was 0.09 (measured; 1.0 with the bound)."""
    right = scene_runs("track-two-behind-one.toml", 60, 4, False)["R"]
    assert right["purity"] >= 0.99, right
    old = scene_runs("track-two-behind-one.toml", 60, 4, False, merge_hidden_extent_m=10.0)["R"]
    assert old["purity"] < 0.5, old  # the failure, without the bound


def test_merge_hidden_m_is_checked():
    from nodlidar.errors import ParameterError
    from nodlidar.tracking.tracker import TrackerConfig

    with pytest.raises(ParameterError, match="merge_hidden_m = -0.1 .*>= 0"):
        TrackerConfig(merge_hidden_m=-0.1)
    with pytest.raises(ParameterError, match="merge_hidden_extent_m = -1.0 .*>= 0"):
        TrackerConfig(merge_hidden_extent_m=-1.0)


@pytest.mark.parametrize("range_m", [2.6, 2.8, 3.0])
def test_one_cluster_of_two_people_is_split_where_the_scan_saw_them_apart(range_m):
    # two people 0.42 m apart, a 6 cm gap: beyond ~2.5 m the clustering's linking distance
    # (4 beam spacings) bridges it and they are one cluster; the beams through the gap
    # split it, into exactly the two people
    from nodlidar.tracking.segment import SegmentConfig, _split_seen_apart, cluster_points

    cfg = SegmentConfig()
    scan, obj = _scan([(range_m, -0.21, 0.18), (range_m, 0.21, 0.18)])
    lab = np.where(obj > 0, 0, -1)
    idx = np.flatnonzero(obj > 0)
    eps = np.clip(cfg.cluster_beams * scan.range_m[idx] * STEP, cfg.cluster_min_m,
                  cfg.cluster_radius_m)
    assert cluster_points(scan.points[idx, :2], eps).max() == 0  # one cluster
    assert _split_seen_apart(scan, lab, np.array([0]), cfg)
    assert len(np.unique(lab[idx])) == 2
    for c in np.unique(lab[idx]):
        assert len(np.unique(obj[lab == c])) == 1  # each part is one person, whole
    # one object as wide as two people is not split (nothing seen through it)
    one, obj1 = _scan([(range_m, 0.0, 0.4)])
    lab1 = np.where(obj1 > 0, 0, -1)
    assert not _split_seen_apart(one, lab1, np.array([0]), cfg)


def test_two_people_in_one_cluster_keep_their_tracks(scene_runs):
    """``design/scenes/track-side-by-side-near.toml``, mirrors, seed 6: the two people were
    one cluster in scan 4, the right person's young track took it, its first velocity came
    from the merged centroid (0.39 m/s at -118 deg for 0.3 m/s at -160 deg) and from scan 7
    it followed the left person; the right person got a second track. Split where the scan
    saw them apart (``SegmentConfig.split_seen_apart_beams``), each keeps one."""
    movers = scene_runs("track-side-by-side-near.toml", 20, 6, True)
    for m in movers.values():
        assert m["id_switches"] == 0 and len(m["tracks"]) == 1 and m["purity"] >= 0.99, m
    # fails without the split: the right person's two tracks (and without
    # follow_inconsistent_fraction, with which the right person's young track takes its own
    # weak cluster first, since 2026-12-06)
    old = scene_runs("track-side-by-side-near.toml", 20, 6, True,
                     segment={"split_seen_apart_beams": 0}, follow_inconsistent_fraction=1.0)
    assert old["right"]["id_switches"] == 1, old["right"]


@pytest.mark.parametrize("mirrors", [True, False])
def test_people_walking_away_side_by_side_are_two_tracks_from_the_start(mirrors):
    """``design/scenes/track-side-by-side-away.toml``: two people 0.45 m apart walking away
    from 0.8-1.0 m out at 0.4 m/s. Their visible backs' centroids are closer than
    ``merge_m`` (0.38 m), so without the free-space test one track took both (measured,
    seed 0, 30 scans, with mirrors: track 1 held both people in scans 1-8, purity
    0.60 / 0.40 and the right person's identity switched; lifted, not in this seed)."""
    from nodlidar.paper import PAPER_DESIGN
    from nodlidar.sim.scene import load_scene
    from nodlidar.solver import solve
    from nodlidar.spec import load_design
    from nodlidar.tracking.evaluate import evaluate, run_online
    from nodlidar.tracking.tracker import TrackerConfig

    design = solve(load_design(PAPER_DESIGN))
    sc = load_scene(SCENES / "track-side-by-side-away.toml")

    def run(apart: bool):
        res = run_online(design, sc, 30, mirrors_deployed=mirrors, seed=0,
                         tracker=TrackerConfig(merge_seen_apart=apart))
        both = [r["scan"] for r in res.records if r["counts"].get(1) and r["counts"].get(2)]
        return evaluate(res)["movers"], both

    movers, both = run(True)
    assert not both  # no track ever holds both people
    for m in movers:
        assert m["purity"] == 1.0 and m["id_switches"] == 0 and len(m["tracks"]) == 1, movers
    if mirrors:
        movers, both = run(False)
        assert both[:3] == [1, 2, 3]  # the failure, without the test
        assert min(m["purity"] for m in movers) < 0.9


def test_a_few_stray_points_do_not_make_a_track_follow_a_second_mover():
    # a hand-made online result: track 1 follows A (30 points a scan), track 2 follows B;
    # in scans 2 and 4 B is seen only as 1 stray point at the edge of A's cluster (track 1).
    # Track 1 follows its majority (A) only: B is unfollowed there, not switched to track 1
    # and back (before: 4 switches); a merged cluster (scan 5: 20 A, 25 B in track 1)
    # follows B, its majority, and A is unfollowed in that scan
    from nodlidar.sim.scene import scene_from_dict
    from nodlidar.tracking.evaluate import OnlineResult, evaluate

    sc = scene_from_dict({"name": "t", "mover": [
        {"name": n, "radius_m": 0.18, "height_m": 1.7, "trajectory": "constant_velocity",
         "start_m": [2.0, y, 0.0], "velocity_m_s": [0.3, 0.0, 0.0]}
        for n, y in (("A", -0.21), ("B", 0.21))]})
    res = OnlineResult(sc, True, "renyi", 0, 6)
    for k in range(6):
        t = 0.1 * k
        a = {1: 30} if k not in (2, 4) else {1: 30, 2: 1}
        if k == 5:
            a = {1: 20, 2: 25}
        res.records.append({"scan": k, "track": 1, "t_s": t, "x_m": 2.0 + 0.3 * t,
                            "y_m": -0.21, "v_m_s": 0.3, "heading_rad": 0.0,
                            "confirmed": True, "counts": a})
        if k not in (2, 4, 5):
            res.records.append({"scan": k, "track": 2, "t_s": t, "x_m": 2.0 + 0.3 * t,
                                "y_m": 0.21, "v_m_s": 0.3, "heading_rad": 0.0,
                                "confirmed": True, "counts": {2: 28}})
        res.scan_t_s.append(t)
        res.confirmed.append([])
    a, b = evaluate(res)["movers"]
    assert a["id_switches"] == 0 and a["tracks"] == [1] and a["scans_followed"] == 5
    # B: track 2 in scans 0, 1, 3, then track 1 (its majority) in scan 5: one real change
    assert b["tracks"] == [1, 2] and b["id_switches"] == 1 and b["scans_followed"] == 4


def test_a_track_never_confirmed_is_no_identity():
    # one mover: track 1 (tentative, one scan: never confirmed) in scan 0, then hidden, then
    # track 2 (confirmed) to the end - one identity, no switch; a tentative track between two
    # confirmed ones is no identity either, while a change between two confirmed tracks is
    from nodlidar.sim.scene import scene_from_dict
    from nodlidar.tracking.evaluate import OnlineResult, evaluate

    sc = scene_from_dict({"name": "t", "mover": [
        {"name": "A", "radius_m": 0.18, "height_m": 1.7, "trajectory": "constant_velocity",
         "start_m": [2.0, 0.0, 0.0], "velocity_m_s": [0.0, 0.3, 0.0]}]})

    def run(tracks_confirmed):
        res = OnlineResult(sc, False, "renyi", 0, len(tracks_confirmed))
        for k, (tid, conf) in enumerate(tracks_confirmed):
            t = 0.1 * k
            res.records.append({"scan": k, "track": tid, "t_s": t, "x_m": 2.0, "y_m": 0.3 * t,
                                "v_m_s": 0.3, "heading_rad": np.pi / 2, "confirmed": conf,
                                "counts": {1: 20}})
            res.scan_t_s.append(t)
            res.confirmed.append([])
        return evaluate(res)["movers"][0]

    a = run([(1, False), (2, False), (2, True), (2, True)])
    assert a["id_switches"] == 0 and a["tracks"] == [1, 2] and a["tentative_tracks"] == [1]
    assert a["first_scan"] == 1  # scan 0, the first a track (tentative or not) followed it
    assert a["reported_scan"] == 3  # scan 2, the first a confirmed one did
    b = run([(2, False), (2, True), (1, False), (2, True)])
    assert b["id_switches"] == 0 and b["tentative_tracks"] == [1]
    assert b["first_scan"] == 1 and b["reported_scan"] == 2
    # a confirmed track's records from before its confirmation are not a report
    assert run([(1, False), (1, False), (1, True)])["reported_scan"] == 3
    assert run([(1, False), (1, False)])["reported_scan"] is None  # never reported
    c = run([(2, False), (2, True), (3, False), (3, True)])  # two reported identities
    assert c["id_switches"] == 1 and c["tentative_tracks"] == []


@pytest.mark.parametrize("seed", [0, 1])
def test_a_young_track_does_not_jump_to_the_person_beside_its_own(seed):
    """``design/scenes/track-side-by-side-near.toml``, lifted: two people 0.42 m apart, each
    dynamic in some scans only. When only one is, the other's young track (its gate still
    spans both) took it; its own person is there, in a cluster that is not dynamic, nearer
    to the prediction and seen apart from the first (``TrackerConfig.hold_seen_apart``).
    Measured, 40 scans, without / with: left tracks [1, 2, 3] (2 switches) / [2], right
    [1, 2] (1 switch, purity 0.96) / [1], in both seeds."""
    from nodlidar.paper import PAPER_DESIGN
    from nodlidar.sim.scene import load_scene
    from nodlidar.solver import solve
    from nodlidar.spec import load_design
    from nodlidar.tracking.evaluate import evaluate, run_online
    from nodlidar.tracking.tracker import TrackerConfig

    design = solve(load_design(PAPER_DESIGN))
    sc = load_scene(SCENES / "track-side-by-side-near.toml")

    def run(hold: bool):
        res = run_online(design, sc, 40, mirrors_deployed=False, seed=seed,
                         tracker=TrackerConfig(hold_seen_apart=hold))
        return evaluate(res)["movers"]

    for m in run(True):
        # (a track never confirmed, e.g. pending on a track seen once, is no identity:
        # TrackerConfig.reacquire_unique_m)
        reported = [t for t in m["tracks"] if t not in m["tentative_tracks"]]
        assert m["id_switches"] == 0 and len(reported) == 1 and m["purity"] >= 0.99, m
    assert sum(m["id_switches"] for m in run(False)) > 0  # the failure, without the hold


def test_the_rays_through_where_an_object_was_end_just_behind_it():
    """``seen_through``: "occupied, then seen through", the evidence of an object walking
    straight away from the sensor (``TrackerConfig.follow_seen_through_m``)."""
    grid = VoxelGrid(0.1)
    before, ob = _scan([(2.0, 0.1, 0.18)])
    keys = grid.keys(before.points[ob == 1])
    margin = 0.15  # 1.5 voxels, the carving margin (noise-free here)
    # walked 0.6 m straight away: every beam on its back crosses where its front was
    away, oa = _scan([(2.6, 0.1, 0.18)])
    a = np.flatnonzero(oa == 1)
    assert seen_through(away, a, keys, grid, margin, 1.5).all()
    # still there: its own voxels are within the margin of its points
    still, os_ = _scan([(2.0, 0.1, 0.18)])
    assert not seen_through(still, np.flatnonzero(os_ == 1), keys, grid, margin, 1.5).any()
    # walked sideways: no beam on it crossed where it was; the wall behind where it was is
    # seen through, but 2.3 m on, beyond the reach (and with a longer reach it counts)
    side, osd = _scan([(2.0, 0.8, 0.18)])
    assert not seen_through(side, np.flatnonzero(osd == 1), keys, grid, margin, 1.5).any()
    wall = np.flatnonzero(osd == 0)
    assert not seen_through(side, wall, keys, grid, margin, 1.5).any()
    assert seen_through(side, wall, keys, grid, margin, 3.0).sum() >= 10


@pytest.mark.parametrize("seed", [0, 1])
def test_a_person_walking_straight_away_keeps_one_track(seed, scene_runs):
    """``design/scenes/track-walking-away.toml``, lifted: one person walking straight away
    at 0.5 m/s. "Free, then occupied" sees it only where the nod comes back to a height;
    in between its clusters are not dynamic, but the rays through where its back was end
    on it (``TrackerConfig.follow_seen_through_m``). Measured, 70 scans, seeds 0-3, without
    / with: followed in 7-8 / 13-21 scans, 2 tracks (lost after scan ~8) / one track,
    converged at scan 3-6, final speed within 0.001 m/s and heading 0.13 deg."""
    on = scene_runs("track-walking-away.toml", 70, seed, False, follow_seen_through_m=1.5)
    scene_runs.assert_kept(on)
    # the failure, without: lost after a few scans, then a second track (in seed 1 the
    # second was never confirmed: no identity switch, and its one velocity-less record no
    # estimate, since 2026-12-06)
    # (and without follow_inconsistent_fraction: alone, it follows the walker a few scans
    # longer, 10-11, and then loses it too)
    off = scene_runs("track-walking-away.toml", 70, seed, False, follow_seen_through_m=0.0,
                     follow_inconsistent_fraction=1.0)["walker"]
    assert off["scans_followed"] <= 8 and len(off["tracks"]) >= 2, off


@pytest.mark.parametrize("mirrors", [True, False])
def test_two_people_who_meet_and_walk_on_together_keep_their_tracks(mirrors, scene_runs):
    """``design/scenes/track-meet.toml``: two people walk towards each other at 0.5 m/s,
    meet 0.5 m apart and turn together to walk away side by side. Each filter carried its
    track on past the turn (the clusters stayed within both tracks' gates): measured,
    seeds 0-7, mirrors / lifted, an identity switch in every run before this session's
    rules, none after. ``maneuver_turn_deg`` restarts each track's motion at the turn;
    without it the two predictions cross and the tracks swap people (16 / 16 switches,
    purity 0.42-0.51)."""
    scene_runs.assert_kept(scene_runs("track-meet.toml", 85, 0, mirrors))
    movers = scene_runs("track-meet.toml", 85, 0, mirrors, maneuver_turn_deg=0.0)
    assert sum(m["id_switches"] for m in movers.values()) >= 1, movers


def test_two_tracks_whose_people_the_scan_saw_apart_both_go_on(scene_runs):
    """``coalesce_seen_apart``: after the meeting's turn the two tracks' filtered positions
    came within ``coalesce_m`` while the people, 0.5 m apart, were seen apart, and the
    younger track ended; its person got a new one. Measured without it, seeds 0-7,
    mirrors / lifted: ``track-meet`` 0 / 5 switches, the meeting scenes together
    (``track-meet`` and ``benchmarks/heldout/s-meet-*``, ``s-part``) 9 / 10 against 2 / 4
    with it. Lifted, seed 1: a switch without it, none with it."""
    scene_runs.assert_kept(scene_runs("track-meet.toml", 85, 1, False))
    movers = scene_runs("track-meet.toml", 85, 1, False, coalesce_seen_apart=False)
    assert sum(m["id_switches"] for m in movers.values()) >= 1, movers


def test_a_face_receding_into_the_split_is_not_seen_apart():
    # a 0.5 m box's side face at grazing incidence (11 deg from the rays, 3.2-3.7 m out)
    # recedes ~0.1 m per beam; split by the segmentation near its far end, with range
    # noise, the step across the split can pass jump_m while the far piece's one or two
    # steps happen to be small (measured: design/scenes/track-two-boxes.toml, mirrors,
    # seed 2, scan 73: steps 0.09, 0.12, then 0.155 across the split, then -0.03, 0.07 -
    # a second track took the box). The face led into the step: no occlusion
    rng = np.random.default_rng(0)
    base, obj = _scan([], [(3.15, 0.655, 3.65, 1.155)])
    q = np.flatnonzero(obj == 1)
    order = q[np.argsort(base.range_m[q])]
    draws = 300
    apart = {k: 0 for k in (2, 3, 4)}
    for _ in range(draws):
        s = _noisy(base, rng)
        for k in apart:
            apart[k] += seen_apart(s, order[:-k], order[-k:])
    # measured 3 of 300 for each split (21 of 300 each before the near side counted)
    assert max(apart.values()) / draws <= 0.03, apart
    # a person (r 0.2 m) behind the box's far corner is seen apart as before: their centre
    # 0.95 m beyond the corner (x) always, 0.65 m in most draws, 0.45 m in some (their
    # surface near the face's end)
    share = {}
    for cx in (4.1, 4.3, 4.6):
        base2, obj2 = _scan([(cx, 0.5, 0.2)], [(3.15, 0.655, 3.65, 1.155)])
        a, b = np.flatnonzero(obj2 == 2), np.flatnonzero(obj2 == 1)
        share[cx] = np.mean([seen_apart(_noisy(base2, rng), a, b) for _ in range(draws)])
    assert share[4.6] == 1.0 and share[4.3] >= 0.8 and share[4.1] >= 0.2, share


@pytest.mark.parametrize("seed", [2, 3])
def test_the_box_behind_another_is_not_followed_by_tracks_on_its_pieces(seed, scene_runs):
    """``design/scenes/track-two-boxes.toml`` (two 0.5 m boxes pushed together, the far one
    mostly behind the near one), mirrors. Measured, seeds 2 and 3, the nineteenth session's
    code: the far box went through 4 tracks (5 and 3 switches): its side face at grazing
    incidence, split by the segmentation, was "seen apart" into two objects (and the near
    box's face too: a track born on its piece took the far box's). Now one track until the
    near box hides it all (scans 30-66 in seed 2), and one after: the far box's sightings
    before are too few (3 scans) for a velocity that carries its track across the gap."""
    on = scene_runs("track-two-boxes.toml", 90, seed, True)
    assert len(on["far"]["tracks"]) <= 2 and on["far"]["id_switches"] <= 1, on
    assert on["near"]["tracks"] == [1] and on["near"]["conv"] is not None, on
