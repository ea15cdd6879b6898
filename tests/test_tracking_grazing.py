"""Walls seen at grazing incidence are not movers (a corridor, a wall beside or behind the
sensor): the carving margin is measured off long surfaces, not along the ray
(:func:`nodlidar.tracking.segment.grazing_secant`, ``SegmentConfig.grazing_margin``)."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_allclose

from nodlidar.errors import ParameterError
from nodlidar.tracking.scans import ScanPoints
from nodlidar.tracking.segment import OnlineSegmenter, SegmentConfig, grazing_secant

STEP = 2 * np.pi / 1024


def _scan(theta: np.ndarray, r: np.ndarray, steps: np.ndarray | None = None) -> ScanPoints:
    """A 2D scan from the origin: beams at bearings ``theta`` [rad] with ranges ``r`` [m]."""
    n = len(r)
    d = np.stack([np.cos(theta), np.sin(theta), np.zeros(n)], axis=1)
    return ScanPoints(0, np.arange(n) if steps is None else steps, np.zeros(n),
                      np.full(n, -1), r, r[:, None] * d, np.zeros((n, 3)), d, np.zeros(n))


def _wall(x_m: float, deg: float = 75.0):
    """Beams at -deg..deg onto the wall x = x_m (its normal along x: incidence = bearing)."""
    k = int(np.radians(deg) / STEP)
    theta = np.arange(-k, k + 1) * STEP
    return theta, x_m / np.cos(theta)


def test_grazing_secant_follows_the_incidence_on_a_wall():
    theta, r = _wall(2.0)
    sec = grazing_secant(_scan(theta, r), max_secant=10.0)
    near = np.abs(theta) <= np.radians(70)
    # noise-free: the centred line over 11 beams reads the slope of the convex r = x / cos
    # within 0.23 % up to 70 deg (measured); the last 5 beams at each end have a line on one
    # side only, whose middle is 2.5 beams (0.015 rad) towards normal incidence: at most
    # tan(75 deg) * 0.015 = 5.7 % low
    assert_allclose(sec[near], 1 / np.cos(theta[near]), rtol=0.003)
    assert_allclose(sec, 1 / np.cos(theta), rtol=0.06)
    # with the URG-04LX's range noise (1 % of the range beyond 1 m, 2-6 m here) the 11-beam
    # line is unbiased: median error within 2 %, 90 % of the beams within 15 % (measured
    # +0.03..+0.4 % and 8-11 % over five seeds)
    rng = np.random.default_rng(0)
    noisy = grazing_secant(_scan(theta, r + rng.normal(0, 0.01 * r)))
    rel = noisy[near] * np.cos(theta[near]) - 1
    assert abs(float(np.median(rel))) < 0.02
    assert float(np.percentile(np.abs(rel), 90)) < 0.15
    # capped along the wall
    assert grazing_secant(_scan(theta, r), max_secant=2.0).max() == pytest.approx(2.0)


def test_an_edge_beside_a_surface_is_not_grazing():
    # a wall 3 m ahead at normal incidence with a post 1 m in front over 20 beams: the wall's
    # beams next to the post have a flat side, and so do the post's own
    theta = (np.arange(201) - 100) * STEP
    r = 3.0 / np.cos(theta)
    post = slice(90, 110)
    r[post] = 1.0 / np.cos(theta[post])
    sec = grazing_secant(_scan(theta, r), min_run_m=0.0)
    # the beams within 5 of an edge read a line on their flat side, whose middle is 2.5
    # beams (0.015 rad) off: within tan(35 deg) * 0.015 = 1.1 %
    assert_allclose(sec, 1 / np.cos(theta), rtol=0.012)


def test_short_surfaces_keep_the_plain_margin():
    # a 0.6 m face at 68 deg incidence (a box's side): grazing, but not a long surface, so
    # with min_run_m (1.5 m here; the default 0.8 m: next test) its margin is the plain
    # one; a moving face's evidence is the space just in front of it (measured: a 0.13 m/s
    # box 2 m ahead is found scans later when it grows)
    # the face: the line at 0.8 m from the sensor (normal at bearing 0) from 1.72 to 2.32 m
    # along it: 0.6 m long, seen at 65-71 deg, 1.9-2.5 m away
    d = 0.8
    lo, hi = np.arctan(1.72 / d), np.arctan(2.32 / d)
    steps = np.arange(int(np.ceil(lo / STEP)), int(hi / STEP) + 1)
    theta = steps * STEP
    r = d / np.cos(theta)
    scan = _scan(theta, r, steps=steps)
    assert np.median(grazing_secant(scan, min_run_m=0.0)) > 2.0  # 1 / cos 68 deg = 2.7
    assert np.all(grazing_secant(scan, min_run_m=1.5) == 1.0)


def test_a_wall_seen_in_a_short_piece_is_long_enough():
    # the default shortest long surface (0.8 m) lies between the longest side of the movers
    # the tracker is built for (0.6 m: the face above keeps the plain margin) and a wall
    # seen in pieces, cut off by the lidar's range and by someone standing in front of it
    # (a robot driving along a room saw 1.3 m of its side wall)
    d = 0.8
    for length, long in ((0.6, False), (1.0, True), (1.3, True)):
        lo, hi = np.arctan(1.72 / d), np.arctan((1.72 + length) / d)
        steps = np.arange(int(np.ceil(lo / STEP)), int(hi / STEP) + 1)
        theta = steps * STEP
        sec = grazing_secant(_scan(theta, d / np.cos(theta), steps=steps),
                             min_run_m=SegmentConfig().grazing_min_run_m)
        assert (np.median(sec) > 2.0) == long, (length, np.median(sec))


def test_grazing_run_is_validated():
    with pytest.raises(ParameterError, match="grazing_min_run_m"):
        SegmentConfig(grazing_min_run_m=-1.0)


@pytest.fixture(scope="module")
def design():
    from nodlidar.paper import PAPER_DESIGN
    from nodlidar.solver import solve
    from nodlidar.spec import load_design

    return solve(load_design(PAPER_DESIGN))


def _corridor_scans(design, mirrors: bool, drive: bool):
    """The first 2 s (20 scans: before static support can judge anything) in an empty
    corridor 2 m wide, the sensor at rest or driving down it at 0.3 m/s."""
    from nodlidar.sim.scene import scene_from_dict
    from nodlidar.tracking.simdata import simulate_scans

    sensor = {"position_m": [0.0, 0.0, 0.4]}
    if drive:
        sensor["velocity_m_s"] = [0.3, 0.0, 0.0]
    sc = scene_from_dict({"name": "corridor", "sensor": sensor,
                          "room": {"size_m": [12.0, 2.0, 2.5], "center_m": [4.5, 0.0],
                                   "ceiling": False}})
    return simulate_scans(design, 20, mirrors_deployed=mirrors, scene=sc, seed=0)


@pytest.mark.parametrize("mirrors, drive", [(False, False), (True, False), (False, True), (True, True)])
def test_an_empty_corridor_has_no_movers(design, mirrors, drive):
    # nothing moves, so every dynamic point is a false one. Measured, seed 0, dynamic points
    # without / with the grazing margin: at rest 208 / 0 lifted, 5508 / 129 with mirrors;
    # driving 230 / 0 and 4991 / 129. With a person walking in the corridor (seeds 0-7):
    # false tracks 69 / 1 lifted, 69 / 7 with mirrors, the person's track unchanged
    scans = _corridor_scans(design, mirrors, drive)

    def dynamic_points(cfg):
        seg = OnlineSegmenter(cfg)
        return sum(int(seg.update(s).dynamic.sum()) for s in scans)

    before = dynamic_points(SegmentConfig(grazing_margin=False))
    after = dynamic_points(SegmentConfig())
    assert before > 0  # the failure this guards against is present in the scene
    assert after <= 0.1 * before, (before, after)
    if not mirrors:
        # lifted, the walls are the only thing the direct plane sees: none may move
        assert after == 0


@pytest.mark.parametrize("mirrors", [False, True])
def test_a_wall_seen_in_pieces_while_driving_does_not_move(design, mirrors):
    # design/scenes/track-overtaking-robot.toml: the robot drives at 0.3 m/s down a room 3 m
    # wide; a person overtakes it. From scan ~30 its side wall is seen at 60-75 deg in
    # pieces of ~1.3 m, cut off by the lidar's range beyond and by the person in front;
    # with the 1.5 m long-surface rule those pieces kept the plain margin, their rays
    # carved the wall, and the wall became tracks (seed 1, lifted: 2 false tracks, at 2.4
    # and 0.14 m/s). Measured, points on the static world classified dynamic over the 90
    # scans, seeds 0 / 1: lifted 92 / 80 -> 17 / 19, with mirrors 110 / 121 -> 0 / 0.
    # Asserted: at most a third; the person stays dynamic in the scans they are seen. The
    # failure is the segmentation of then (no scan-line links either: they removed a few
    # of those points too, 92 -> 46 in seed 0 lifted with the 1.5 m rule)
    from nodlidar.tracking.simdata import simulate_scans

    def wall_and_person(scans, cfg):
        """Dynamic points on the static world (truth 0) and on the person (1)."""
        seg = OnlineSegmenter(cfg, design.lidar.range_sigma_m)
        out = [(seg.update(s), s) for s in scans]
        return (sum(int(np.sum(o.dynamic & (s.truth_id == 0))) for o, s in out),
                sum(int(np.sum(o.dynamic & (s.truth_id == 1))) for o, s in out))

    for seed in (0, 1):
        scans = simulate_scans(design, 90, mirrors_deployed=mirrors,
                               scene="track-overtaking-robot", seed=seed)
        before, person_before = wall_and_person(scans, SegmentConfig(grazing_min_run_m=1.5,
                                                                     scan_line_sigmas=0.0))
        after, person_after = wall_and_person(scans, SegmentConfig())
        assert before >= 50 and person_before >= 500  # the failure; the person is seen
        assert after <= before / 3, (seed, before, after)
        assert person_after >= 0.95 * person_before, (seed, person_before, person_after)
