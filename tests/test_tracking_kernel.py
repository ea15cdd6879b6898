"""The tracking's compiled loops (nodlidar/tracking/_kernel.py) give, bit for bit, what the
numpy formulas they replace gave: on simulated scans of the paper's sensor and on random
rays and pairs. The carving keys' numpy formula is ``VoxelMap.free_keys(compiled=False)``;
the pair filter's and the cut-line test's are written out here, as they stood."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from nodlidar.tracking._kernel import pairs_within, ray_sample_keys
from nodlidar.tracking.motion import RenyiCost, compensate
from nodlidar.tracking.voxels import VoxelGrid, VoxelMap, unique_keys

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def design():
    from nodlidar.solver import solve
    from nodlidar.spec import load_design

    return solve(load_design(ROOT / "design" / "urg04lx-paper.toml"))


@pytest.mark.parametrize("origin, voxel", [((0.0, 0.0, 0.0), 0.1), ((0.013, -0.27, 1.1), 0.07)])
def test_ray_sample_keys_are_the_numpy_keys(origin, voxel):
    # random rays from around a sensor in every direction (negative indices too), some
    # with no return (nothing carved), some starting exactly on voxel faces: the kernel's
    # keys against free_keys' numpy formula (compiled=False)
    rng = np.random.default_rng(7)
    n = 700
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1)[:, None]
    start = rng.uniform(-2, 2, (n, 3))
    start[:50] = np.round(start[:50] / voxel) * voxel
    r = rng.uniform(0.0, 6.0, n)
    r[::9] = np.nan
    m = VoxelMap(VoxelGrid(voxel, origin), margin_voxels=1.5)
    want = m.free_keys(start, d, r, np.zeros(n), compiled=False)
    assert len(want) > 10_000 and np.array_equal(want, unique_keys(want))
    got = m.free_keys(start, d, r, np.zeros(n))
    assert got.dtype == np.int64 and np.array_equal(got, want)  # sorted, distinct
    # a key equal to every index bit set (index -1 with no offset) takes the sort path:
    # outside the key's bits
    far = ray_sample_keys(np.array([[-0.05, -0.05, -0.05]]), np.array([[1.0, 0, 0]]),
                          np.array([3]), 0.05, np.zeros(3), 0.1, 0)
    assert far.tolist() == [-1]


def test_free_keys_compiled_and_numpy_agree_on_simulated_scans(design):
    # the online segmentation's own carving: every scan of the paper's scenario, both ways
    from nodlidar.tracking.segment import SegmentConfig, grazing_secant
    from nodlidar.tracking.simdata import simulate_scans

    cfg = SegmentConfig()
    m = VoxelMap(VoxelGrid(cfg.voxel_m), margin_voxels=cfg.margin_voxels,
                 range_sigma=design.lidar.range_sigma_m, carve_no_return_m=cfg.carve_no_return_m)
    total = 0
    for scan in simulate_scans(design, 12, mirrors_deployed=True, seed=3):
        args = (scan.ray_start, scan.ray_dir, scan.range_m, scan.ray_offset,
                grazing_secant(scan))
        a = m.free_keys(*args)
        assert np.array_equal(a, m.free_keys(*args, compiled=False))
        assert np.array_equal(a, unique_keys(a))  # sorted, unique
        total += len(a)
    assert total > 10_000


def _within_numpy(qx, qy, qz, i, j, r2, use_z):
    """The numpy pair filter (RenyiCost before the kernel)."""
    dx, dy = qx[i] - qx[j], qy[i] - qy[j]
    d2 = dx * dx + dy * dy
    dz = qz[i] - qz[j] if use_z else None
    if use_z:
        d2 += dz * dz
    k = np.flatnonzero(d2 <= r2)
    return i[k], j[k], dx[k], dy[k], (dz[k] if use_z else np.zeros(0))


@pytest.mark.parametrize("use_z", [False, True])
def test_pairs_within_are_the_numpy_pairs(use_z):
    rng = np.random.default_rng(11)
    n, m = 900, 200_000
    q = rng.normal(scale=0.3, size=(n, 3))
    qx, qy, qz = (np.ascontiguousarray(q[:, k]) for k in range(3))
    i = rng.integers(0, n, m)
    j = rng.integers(0, n - 1, m)
    j += j >= i
    r = 0.1 + 0.08 * 3.7
    got = pairs_within(qx, qy, qz, i, j, r * r, use_z)
    want = _within_numpy(qx, qy, qz, i, j, r * r, use_z)
    assert 0 < len(got[0]) < m
    for g, w in zip(got, want):
        assert g.dtype == w.dtype and np.array_equal(g, w)
    # a pair exactly at the cutoff is kept, as d2 <= r2 keeps it
    one = pairs_within(np.array([0.0, 0.3]), np.array([0.0, 0.4]), np.zeros(2),
                       np.array([0]), np.array([1]), 0.3 * 0.3 + 0.4 * 0.4, False)
    assert len(one[0]) == 1
    # int32 indices (RenyiCost's draw over all points) give the same pairs
    got32 = pairs_within(qx, qy, qz, i.astype(np.int32), j.astype(np.int32), r * r, use_z)
    for g, w in zip(got32, want):
        assert g.dtype == w.dtype and np.array_equal(g, w)


@pytest.mark.parametrize("n", [2, 3, 801, 1024, 1025, 3167, 65537])
def test_int32_draws_are_the_int64_draws(n):
    # RenyiCost draws its pair indices as int32: numpy draws 32 bits for a range below
    # 2^32 whatever the dtype, so the numbers (and the cost) are the int64 draw's
    m = 800 * 799 // 2
    a, b = np.random.default_rng(n), np.random.default_rng(n)
    for hi in (n, n - 1):
        assert np.array_equal(a.integers(0, hi, m), b.integers(0, hi, m, dtype=np.int32))


def test_renyi_cost_of_drawn_pairs_is_unchanged():
    # a cloud larger than max_points: the pairs are drawn and filtered by the kernel; the
    # cost and its pair arrays against the numpy filter applied to the same draw
    rng = np.random.default_rng(2)
    n = 1500
    t = np.sort(rng.uniform(0, 3.0, n))
    p = np.column_stack([rng.normal(scale=0.2, size=(n, 2)) + np.outer(t, [0.3, 0.1]),
                         rng.uniform(0, 1.7, n)])
    cost = RenyiCost(p, t, 3.0, 0.02, [0.3, 0.1], max_dv_m_s=0.08, subsample="pairs")
    q = compensate(np.column_stack([p[:, :2], np.zeros(n)]), t, [0.3, 0.1], 3.0)
    qx, qy, qz = (np.ascontiguousarray(q[:, k]) for k in range(3))
    dr = np.random.default_rng(n)
    mm = 800 * 799 // 2
    i = dr.integers(0, n, mm)
    j = dr.integers(0, n - 1, mm)
    j += j >= i
    r = 5.0 * 0.02 + 0.08 * float(np.ptp(t))
    wi, wj, wx, wy, _ = _within_numpy(qx, qy, qz, i, j, r * r, False)
    assert cost.n_pairs == len(wi)
    assert np.array_equal(cost.dx, wx.astype(np.float32))
    assert np.array_equal(cost.dy, wy.astype(np.float32))
    assert np.array_equal(cost.dt, (t[wj] - t[wi]).astype(np.float32))


def _seen_numpy(p_xy, dt, edges, i, j, c, tol_m=1e-3):
    """The numpy cut-line test (motion._seen_by_both before the kernel)."""
    seen = np.ones(len(i), bool)
    px, py = np.ascontiguousarray(p_xy[:, 0]), np.ascontiguousarray(p_xy[:, 1])
    for k in range(edges.shape[1]):
        has = np.isfinite(edges[:, k, 4])
        if not has.any():
            continue
        ax, ay, ux, uy, side = (np.ascontiguousarray(edges[:, k, col]) for col in range(5))
        for moved, other, sign in ((i, j, 1.0), (j, i, -1.0)):
            sel = np.flatnonzero(has[other])
            if not len(sel):
                continue
            pm, po, d = moved[sel], other[sel], sign * dt[sel]
            qx = px[pm] + c[0] * d
            qy = py[pm] + c[1] * d
            cross = ux[po] * (qy - ay[po]) - uy[po] * (qx - ax[po])
            seen[sel[side[po] * cross < -tol_m]] = False
    return seen


def _cut_lines(rng, n):
    """Random cut lines on a third of ``n`` points (two per point, some with one only),
    both sides: (n, 2, 6) as segment.cut_edges gives them."""
    ang = rng.uniform(0, 2 * np.pi, (n, 2))
    edges = np.full((n, 2, 6), np.nan)
    edges[:, :, 0:2] = rng.uniform(-0.3, 0.3, (n, 2, 2))
    edges[:, :, 2], edges[:, :, 3] = np.cos(ang), np.sin(ang)
    edges[:, :, 4] = rng.choice([-1.0, 1.0], (n, 2))
    edges[rng.random(n) < 0.66, :, 4] = np.nan
    edges[rng.random(n) < 0.2, 1, 4] = np.nan
    return edges


@pytest.mark.parametrize("weighted", [False, True])
@pytest.mark.parametrize("cut", [False, True])
def test_pair_terms_are_the_numpy_terms(weighted, cut):
    # points near random cut lines (within the tolerance too), random pairs: the time
    # offsets, the pair weights times the cut-line test, and the longest offset kept,
    # against the numpy formulas RenyiCost used (as they stood)
    from nodlidar.tracking.motion import _pair_terms

    rng = np.random.default_rng(4)
    n, m = 600, 50_000
    p = rng.uniform(-0.5, 0.5, (n, 2))
    t = rng.uniform(0, 2, n)
    wt = rng.uniform(0.2, 4.0, n) if weighted else None
    edges = _cut_lines(rng, n) if cut else None
    i = rng.integers(0, n, m)
    j = rng.integers(0, n, m)
    c = np.array([0.31, -0.12])
    dt32, pw, dt_kept = _pair_terms(i, j, t, wt, p, edges, c)
    dt = t[j] - t[i]
    assert dt32.dtype == np.float32 and np.array_equal(dt32, dt.astype(np.float32))
    want = np.ones(m, np.float32) if wt is None else (wt[i] * wt[j]).astype(np.float32)
    seen = np.ones(m, bool)
    if cut:
        seen = _seen_numpy(p, dt, edges, i, j, c)
        assert 0.1 < seen.mean() < 0.95  # the test has both answers to get right
        want = seen.astype(np.float32) if wt is None else want * seen
    assert pw.dtype == np.float32 and np.array_equal(pw, want)
    assert dt_kept == float(np.max(np.abs(dt[seen]), initial=0.0))


def _components_numpy(points, eps):
    """cluster_points' graph as numpy built it (before the kernel): the pairs within the
    larger of their two radii, then connected_labels."""
    from scipy.spatial import cKDTree

    from nodlidar.tracking.segment import connected_labels

    pairs = cKDTree(points).query_pairs(float(eps.max()), output_type="ndarray")
    if np.ptp(eps) > 0 and len(pairs):
        d = np.linalg.norm(points[pairs[:, 0]] - points[pairs[:, 1]], axis=1)
        pairs = pairs[d <= np.maximum(eps[pairs[:, 0]], eps[pairs[:, 1]])]
    return connected_labels(len(points), pairs[:, 0], pairs[:, 1]), pairs


@pytest.mark.parametrize("dim", [2, 3])
def test_linked_labels_are_the_numpy_components(dim):
    # clouds of random size and density, radii per point or one for all (no distance
    # check), and pairs at exactly a point's radius: the kernel's labels against numpy's
    from scipy.spatial import cKDTree

    from nodlidar.tracking._kernel import linked_labels

    rng = np.random.default_rng(dim)
    checked = 0
    for trial in range(60):
        n = int(rng.integers(1, 1500))
        pts = rng.random((n, dim)) * rng.uniform(0.3, 4.0)
        eps = rng.uniform(0.02, 0.12, n) if trial % 3 else np.full(n, 0.07)
        if n > 1 and trial % 3:
            eps[0] = eps[1] = float(np.linalg.norm(pts[0] - pts[1]))  # on the boundary
        want, kept = _components_numpy(pts, eps)
        pairs = cKDTree(pts).query_pairs(float(eps.max()), output_type="ndarray")
        got = linked_labels(pts, np.ascontiguousarray(pairs[:, 0], np.int64),
                            np.ascontiguousarray(pairs[:, 1], np.int64), eps,
                            bool(np.ptp(eps) > 0))
        assert got.dtype == np.int64 and np.array_equal(got, want), trial
        checked += len(pairs) - len(kept)
    assert checked > 1000  # the distance check dropped pairs


def test_slot_index_merge_is_the_numpy_index():
    # a window's scans coming and going (slots reused, empty scans, repeated keys): the
    # compiled merge's index against the numpy search-and-insert, after every put
    from nodlidar.tracking.voxels import _SlotIndex

    rng = np.random.default_rng(5)
    merged, numpy_ = _SlotIndex(), _SlotIndex(compiled=False)
    for _ in range(2000):
        slot = int(rng.integers(0, 64))
        keys = np.unique(rng.integers(-5000, 20000, int(rng.choice([0, 1, 7, 300, 3000]))))
        merged.put(slot, keys)
        numpy_.put(slot, keys)
        assert np.array_equal(merged.keys, numpy_.keys)
        assert np.array_equal(merged.mask, numpy_.mask)
        assert merged.keys.dtype == np.int64 and merged.mask.dtype == np.uint64
    assert len(merged.keys) > 10_000


def test_warm_up_compiles_what_tracking_calls(design, monkeypatch):
    # after warm_up, tracking a scene (mirrors: cut lines and drawn pairs) compiles nothing
    # more: the live loop never waits for numba
    from nodlidar.tracking import _kernel
    from nodlidar.tracking.segment import OnlineSegmenter, warm_up
    from nodlidar.tracking.simdata import simulate_scans
    from nodlidar.tracking.tracker import Tracker, TrackerConfig

    warm_up()
    names = ("ray_sample_keys", "pairs_within", "pair_terms", "linked_labels", "slot_merge")
    kernels = [getattr(_kernel, n) for n in names]
    before = [list(k.signatures) for k in kernels]
    calls = dict.fromkeys(names, 0)

    def counted(name, kernel):
        def call(*args):
            calls[name] += 1
            return kernel(*args)
        return call

    for n, k in zip(names, kernels):  # the callers import them from the module at each call
        monkeypatch.setattr(_kernel, n, counted(n, k))
    seg = OnlineSegmenter(range_sigma=design.lidar.range_sigma_m)
    trk = Tracker(TrackerConfig())
    for scan in simulate_scans(design, 45, mirrors_deployed=True, seed=0):
        trk.update(seg.update(scan))
    assert min(calls.values()) > 0, calls  # every kernel ran
    assert [list(k.signatures) for k in kernels] == before
