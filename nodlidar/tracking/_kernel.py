"""Compiled loops of the tracking's per-scan work, where numpy spends its time in dozens of
passes over one large temporary each.

- :func:`ray_sample_keys`: the voxel keys of the carving samples along every ray
  (:meth:`~nodlidar.tracking.voxels.VoxelMap.free_keys`): ~35 array passes over ~45 k
  samples per scan and a sort of them in numpy, one loop and a bitmap here;
- :func:`pairs_within`: of the pairs of points a Rényi cost draws at random, those within
  its cutoff, with their offsets (:class:`~nodlidar.tracking.motion.RenyiCost`): ~10
  passes over ~320 k drawn pairs, most of them dropped, in numpy;
- :func:`seen_by_both`: which of those pairs both scans could see (the cut lines' test of
  :func:`~nodlidar.tracking.motion._pair_terms`), ~15 passes per line in numpy, and
  :func:`pair_terms`: the per-pair time offsets and weights the cost keeps, with it;
- :func:`linked_labels`: the segmentation's clusters, the connected components of the
  neighbour pairs within their radii (:func:`~nodlidar.tracking.segment.cluster_points`);
- :func:`slot_merge`: the windowed voxel map's index of which kept scans traversed (or
  hit) each voxel, updated in one merge (:class:`~nodlidar.tracking.voxels._SlotIndex`);
- :func:`circle_normal_equations`: one Gauss-Newton step's normal equations of the round
  model (:func:`~nodlidar.tracking.round_motion.fit_moving_circle`), one pass over the
  window's points instead of ~15 numpy passes and a matrix product per step. This one has
  no numpy twin to match bit for bit (its sums run in point order, a matrix product's do
  not): tests/test_round_motion.py checks it against the numpy Jacobian to 1e-9.

Every value is the one the numpy formulas gave: the same float operations in the same
order (numba without fastmath: no reordering, no fused multiply-add), checked bit for bit
against them in tests/test_tracking_kernel.py. numba is imported here only, and this
module only inside the functions that use it (``import nodlidar`` never loads it).
Compiled with ``cache=True`` (the first call in a fresh environment compiles) and
``nogil=True``.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["ray_sample_keys", "pairs_within", "seen_by_both", "pair_terms", "linked_labels",
           "slot_merge", "circle_normal_equations", "circle_start_sums", "circle_residual_stats",
           "warm_up"]

_jit = numba.njit(cache=True, nogil=True)
# inlined at numba's IR level (a call to a separate compiled function costs ~13 ns)
_inline = numba.njit(cache=True, nogil=True, inline="always")


_BOX_BITS_MAX = 1 << 26  # 8 MB of bitmap; a larger box (rays of ~100 m) takes the sort


@_inline
def _index(start: np.ndarray, direction: np.ndarray, r: int, k: int, spacing: float,
           origin: np.ndarray, voxel: float, a: int) -> np.int64:
    """``floor((start[r, a] + (k spacing) direction[r, a] - origin[a]) / voxel)`` with
    numpy's operations in numpy's order."""
    q = direction[r, a] * (k * spacing)
    q += start[r, a]
    q -= origin[a]
    q /= voxel
    f = np.int64(q)  # floor: truncation, and a step down below zero (math.floor is a libm
    if f > q:        # call: ~3x the loop)
        f -= 1
    return f


@_jit
def ray_sample_keys(start: np.ndarray, direction: np.ndarray, cnt: np.ndarray,
                    spacing: float, origin: np.ndarray, voxel: float,
                    off: int) -> np.ndarray:
    """The sorted distinct voxel keys of the samples ``start_r + (k spacing) dir_r``,
    ``k = 0 .. cnt_r - 1``, of every ray ``r``.

    Parameters
    ----------
    start, direction : (n, 3) float64
        Rays [m] (finite).
    cnt : (n,) int64
        Samples per ray (>= 0).
    spacing : float
        Sample spacing [m].
    origin : (3,) float64; voxel : float
        The grid's corner and edge [m].
    off : int
        The key's index offset (each index + ``off`` in 21 bits).

    Returns
    -------
    (m,) int64 sorted distinct keys ``(i + off) << 42 | (j + off) << 21 | (k + off)``,
    ``i = floor((p - origin) / voxel)`` per axis, as computed axis by axis in numpy.

    A scan's ~45 k samples fall in ~1.5 k voxels of a box a few metres wide: each sample
    sets its voxel's bit in a bitmap of the box, and reading the bitmap in order gives the
    keys sorted (the key's order is the box's (i, j, k) order). Sorting the samples' keys
    cost as much as computing them. Indices outside the key's 21 bits, or a box of more
    than ``_BOX_BITS_MAX`` voxels, fall back to a sort.
    """
    # the box: along a ray each index is monotone in k (each float step is), so its ends
    # bound it
    lo = np.full(3, np.iinfo(np.int64).max, np.int64)
    hi = np.full(3, np.iinfo(np.int64).min, np.int64)
    for r in range(len(cnt)):
        if cnt[r] > 0:
            for k in (0, cnt[r] - 1):
                for a in range(3):
                    f = _index(start, direction, r, k, spacing, origin, voxel, a)
                    lo[a] = min(lo[a], f)
                    hi[a] = max(hi[a], f)
    if lo[0] > hi[0]:
        return np.empty(0, np.int64)
    span = hi - lo + 1
    inside = True
    for a in range(3):
        inside = inside and lo[a] + off >= 0 and hi[a] + off < (1 << 21)
    vol = span[0] * span[1] * span[2]
    if not inside or vol > _BOX_BITS_MAX:
        keys = np.empty(int(cnt.sum()), np.int64)
        m = 0
        for r in range(len(cnt)):
            for k in range(cnt[r]):
                key = np.int64(0)
                for a in range(3):
                    f = _index(start, direction, r, k, spacing, origin, voxel, a)
                    key |= (f + off) << (42 - 21 * a)
                keys[m] = key
                m += 1
        keys = np.sort(keys)
        out = np.empty(m, np.int64)
        u = 0
        for t in range(m):
            if u == 0 or keys[t] != out[u - 1]:
                out[u] = keys[t]
                u += 1
        return out[:u]
    words = np.zeros((vol + 63) >> 6, np.uint64)
    u = 0
    for r in range(len(cnt)):
        for k in range(cnt[r]):
            b = 0
            for a in range(3):
                b = b * span[a] + (_index(start, direction, r, k, spacing, origin, voxel, a)
                                   - lo[a])
            w, bit = b >> 6, np.uint64(1) << np.uint64(b & 63)
            if not words[w] & bit:
                words[w] |= bit
                u += 1
    out = np.empty(u, np.int64)
    u = 0
    for w in range(len(words)):
        x = words[w]
        while x:
            low = x & (~x + np.uint64(1))  # the lowest set bit
            b = (w << 6) + _bit_index(low)
            x ^= low
            kk = b % span[2]
            jj = (b // span[2]) % span[1]
            ii = b // (span[1] * span[2])
            out[u] = (((ii + lo[0]) + off) << 42) | (((jj + lo[1]) + off) << 21) \
                | ((kk + lo[2]) + off)
            u += 1
    return out


# de Bruijn's sequence for 64 bits and the bit index of each of its 6-bit windows: the
# index of a word's lowest set bit in one multiply and a lookup
_DEBRUIJN = np.uint64(0x03F79D71B4CB0A89)
_DEBRUIJN_INDEX = np.zeros(64, np.int64)
for _i in range(64):
    _DEBRUIJN_INDEX[(((1 << _i) * 0x03F79D71B4CB0A89) & (2**64 - 1)) >> 58] = _i


@_inline
def _bit_index(low: np.uint64) -> int:
    """The index of the one set bit of ``low``."""
    return _DEBRUIJN_INDEX[np.int64((low * _DEBRUIJN) >> np.uint64(58))]


@_jit
def pairs_within(qx: np.ndarray, qy: np.ndarray, qz: np.ndarray, i: np.ndarray,
                 j: np.ndarray, r2: float, use_z: bool):
    """The pairs ``(i[k], j[k])`` whose points lie within ``sqrt(r2)`` of each other, in
    order, with their offsets ``q_i - q_j`` per axis (z only with ``use_z``; else an empty
    array): ``d2 = dx dx + dy dy (+ dz dz) <= r2`` as numpy evaluates it.

    ``i``, ``j``: int32 or int64 (the draw over all points, or within labels).

    Returns (i, j, dx, dy, dz): (p,) int64 twice, (p,) float64 three times.
    """
    n = len(i)
    oi = np.empty(n, np.int64)
    oj = np.empty(n, np.int64)
    ox = np.empty(n, np.float64)
    oy = np.empty(n, np.float64)
    oz = np.empty(n if use_z else 0, np.float64)
    p = 0
    for k in range(n):
        a, b = i[k], j[k]
        dx = qx[a] - qx[b]
        dy = qy[a] - qy[b]
        d2 = dx * dx + dy * dy
        dz = 0.0
        if use_z:
            dz = qz[a] - qz[b]
            d2 += dz * dz
        if d2 <= r2:
            oi[p] = a
            oj[p] = b
            ox[p] = dx
            oy[p] = dy
            if use_z:
                oz[p] = dz
            p += 1
    return oi[:p].copy(), oj[:p].copy(), ox[:p].copy(), oy[:p].copy(), oz[:p if use_z else 0].copy()


@_jit
def seen_by_both(px: np.ndarray, py: np.ndarray, dt: np.ndarray, edges: np.ndarray,
                 i: np.ndarray, j: np.ndarray, cx: float, cy: float,
                 tol_m: float) -> np.ndarray:
    """(m,) bool: :func:`~nodlidar.tracking.motion._pair_terms`' cut-line test, pair by pair: for
    each cut line ``k`` of the other point (``edges[o, k, :5]`` = anchor x, y, direction
    x, y, seen side; NaN side: no line), the point moved at ``(cx, cy)`` to the other's
    time lies on the seen side within ``tol_m`` [m]."""
    m = len(i)
    n_lines = edges.shape[1]
    # which points have a line at all (most have none: only slices a window's edge cut);
    # the others are skipped, the same answer as testing their NaN lines
    lined = np.zeros(edges.shape[0], np.bool_)
    for o in range(edges.shape[0]):
        for k in range(n_lines):
            if not np.isnan(edges[o, k, 4]):
                lined[o] = True
    seen = np.ones(m, np.bool_)
    for p in range(m):
        ok = True
        for w in range(2):
            if w == 0:
                pm, po, d = i[p], j[p], dt[p]
            else:
                pm, po, d = j[p], i[p], -1.0 * dt[p]
            if not lined[po]:
                continue
            for k in range(n_lines):
                qx = px[pm] + cx * d
                qy = py[pm] + cy * d
                cross = edges[po, k, 2] * (qy - edges[po, k, 1]) \
                    - edges[po, k, 3] * (qx - edges[po, k, 0])
                # no line (a NaN side) compares False: no branch on it (the numpy test
                # computed only the pairs with a line; the same answer)
                ok &= not (edges[po, k, 4] * cross < -tol_m)
        seen[p] = ok
    return seen


@_jit
def pair_terms(i: np.ndarray, j: np.ndarray, t: np.ndarray, wt: np.ndarray, weigh: bool,
               px: np.ndarray, py: np.ndarray, edges: np.ndarray, cut: bool, cx: float,
               cy: float, tol_m: float) -> tuple[np.ndarray, np.ndarray, float]:
    """The per-pair terms a :class:`~nodlidar.tracking.motion.RenyiCost` keeps, in one
    compiled pass over its pairs ``(i, j)`` (m,) int64: ``dt = t[j] - t[i]`` [s] as
    float32; the pair weights ``wt[i] wt[j]`` (with ``weigh``) times :func:`seen_by_both`
    (with ``cut``; the other arguments as there), as float32 (m,) (ones where neither; the
    caller then keeps none); and the longest ``|dt|`` of a pair kept (seen) [s]. The same
    float operations as numpy's gathers, casts and products."""
    m = len(i)
    dt = np.empty(m)
    for k in range(m):
        dt[k] = t[j[k]] - t[i[k]]
    seen = seen_by_both(px, py, dt, edges, i, j, cx, cy, tol_m) if cut else np.ones(m, np.bool_)
    dt32 = np.empty(m, np.float32)
    pw = np.empty(m, np.float32)
    dt_kept = 0.0
    for k in range(m):
        dt32[k] = np.float32(dt[k])
        w = np.float32(wt[i[k]] * wt[j[k]]) if weigh else np.float32(1.0)
        pw[k] = w * np.float32(1.0 if seen[k] else 0.0)
        if seen[k]:
            dt_kept = max(dt_kept, abs(dt[k]))
    return dt32, pw, dt_kept


@_jit
def slot_merge(keys: np.ndarray, mask: np.ndarray, bit: np.uint64,
               new: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:meth:`~nodlidar.tracking.voxels._SlotIndex.put` in one merge pass: ``bit`` leaves
    every mask of the sorted unique ``keys`` (int64) and ``mask`` (uint64), the keys left
    in no slot go, and the sorted unique ``new`` keys join with ``bit`` (or'd into a kept
    key's mask). Returns the new (keys, mask), sorted; numpy took a search, two inserts
    and ~6 further passes over the index."""
    off = ~bit
    out_k = np.empty(len(keys) + len(new), np.int64)
    out_m = np.empty(len(keys) + len(new), np.uint64)
    a = 0
    b = 0
    p = 0
    while a < len(keys) or b < len(new):
        if b == len(new) or (a < len(keys) and keys[a] < new[b]):
            m = mask[a] & off
            if m != 0:
                out_k[p] = keys[a]
                out_m[p] = m
                p += 1
            a += 1
        elif a == len(keys) or new[b] < keys[a]:
            out_k[p] = new[b]
            out_m[p] = bit
            p += 1
            b += 1
        else:  # the same key: kept, with this slot's bit
            out_k[p] = keys[a]
            out_m[p] = (mask[a] & off) | bit
            p += 1
            a += 1
            b += 1
    return out_k[:p].copy(), out_m[:p].copy()


@_inline
def _root(parent: np.ndarray, a: int) -> int:
    """The root of ``a``, halving the path on the way (each node then points two up)."""
    while parent[a] != a:
        parent[a] = parent[parent[a]]
        a = parent[a]
    return a


@_jit
def linked_labels(points: np.ndarray, a: np.ndarray, b: np.ndarray, eps: np.ndarray,
                  check: bool) -> np.ndarray:
    """Connected components of the graph on the ``n`` rows of ``points`` (n, d) whose edges
    are the pairs ``(a[k], b[k])`` - with ``check``, only those whose points lie within the
    larger of their two ``eps`` (n,) [m], the distance as numpy's
    ``np.linalg.norm(points[a] - points[b], axis=1)`` rounds it. (n,) int64 labels numbered
    in the order of each component's smallest node, as
    :func:`~nodlidar.tracking.segment.connected_labels` numbers them: union by the smaller
    root keeps every root its component's smallest node."""
    n = points.shape[0]
    parent = np.arange(n)
    for k in range(len(a)):
        i, j = a[k], b[k]
        if check:
            d2 = 0.0
            for c in range(points.shape[1]):
                x = points[i, c] - points[j, c]
                d2 += x * x
            if not np.sqrt(d2) <= max(eps[i], eps[j]):
                continue
        ri, rj = _root(parent, i), _root(parent, j)
        if ri < rj:
            parent[rj] = ri
        elif rj < ri:
            parent[ri] = rj
    lab = np.empty(n, np.int64)
    c = 0
    for i in range(n):
        r = _root(parent, i)
        if r == i:
            lab[i] = c
            c += 1
        else:
            lab[i] = lab[r]  # r < i: labelled already
    return lab


@_jit
def circle_normal_equations(p: np.ndarray, dt: np.ndarray, sig: np.ndarray, k: np.ndarray,
                            c: np.ndarray, v: np.ndarray, radius: float, huber: float,
                            A: np.ndarray, g: np.ndarray) -> None:
    """The moving circle's normal equations at centres ``c`` (K, 2) [m], velocity ``v``
    (2,) [m/s] and ``radius`` [m], per window: ``A[kk]`` (5, 5) and ``g[kk]`` (5,) over
    the points of window ``kk`` (``k`` (n,) int) of ``p`` (n, 2) [m] at ``dt`` (n,) [s]
    from the reference time, each residual ``(|p - c - v dt| - radius) / sig`` weighted by
    Huber at ``huber``; the parameters per row: that window's centre (2), ``v`` (2),
    ``radius``. ``A`` and ``g`` are zeroed and filled in place."""
    A[:] = 0.0
    g[:] = 0.0
    j = np.empty(5)
    for i in range(p.shape[0]):
        kk = k[i]
        dx = p[i, 0] - c[kk, 0] - v[0] * dt[i]
        dy = p[i, 1] - c[kk, 1] - v[1] * dt[i]
        dist = np.sqrt(dx * dx + dy * dy)  # not hypot: a libm call, and no overflow here
        inv = 1.0 / max(dist, 1e-9)
        ux, uy = dx * inv, dy * inv
        s = 1.0 / sig[i]
        r = (dist - radius) * s
        ar = abs(r)
        w = 1.0 if ar <= huber else huber / max(ar, 1e-12)
        j[0] = -ux * s
        j[1] = -uy * s
        j[2] = -ux * dt[i] * s
        j[3] = -uy * dt[i] * s
        j[4] = -s
        for a in range(5):
            wa = w * j[a]
            g[kk, a] += wa * r
            for b in range(a, 5):  # the upper triangle; the lower is its mirror
                A[kk, a, b] += wa * j[b]
    for kk in range(A.shape[0]):
        for a in range(1, 5):
            for b in range(a):
                A[kk, a, b] = A[kk, b, a]


@_jit
def circle_start_sums(p: np.ndarray, dt: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The algebraic (Kasa) circle's normal equations for the points ``p`` (n, 2) [m] moved
    back to the reference time at ``v`` (2,) [m/s] (``dt`` (n,) [s]), about the first
    moved point (conditioning): (9,) = n, sum x, sum y, sum xx, sum xy, sum yy, sum xz,
    sum yz, sum z with ``z = x^2 + y^2``, in one pass."""
    out = np.zeros(9)
    if p.shape[0] == 0:
        return out
    x0 = p[0, 0] - v[0] * dt[0]
    y0 = p[0, 1] - v[1] * dt[0]
    for i in range(p.shape[0]):
        x = p[i, 0] - v[0] * dt[i] - x0
        y = p[i, 1] - v[1] * dt[i] - y0
        z = x * x + y * y
        out[0] += 1.0
        out[1] += x
        out[2] += y
        out[3] += x * x
        out[4] += x * y
        out[5] += y * y
        out[6] += x * z
        out[7] += y * z
        out[8] += z
    return out


@_jit
def circle_residual_stats(p: np.ndarray, dt: np.ndarray, sig: np.ndarray, k: np.ndarray,
                          c: np.ndarray, v: np.ndarray, radius: float,
                          scan: np.ndarray) -> tuple[float, float, int]:
    """The moving circle's normalised residuals ``r_i = (|p_i - c_k(i) - v dt_i| - radius)
    / sig_i`` (arguments as :func:`circle_normal_equations`; ``scan`` (n,) int each point's
    scan): ``sum r^2``, and over consecutive points of one scan and window ``sum r_i
    r_{i+1}`` and their count, in one pass."""
    rr = 0.0
    rs = 0.0
    m = 0
    prev = 0.0
    for i in range(p.shape[0]):
        kk = k[i]
        dx = p[i, 0] - c[kk, 0] - v[0] * dt[i]
        dy = p[i, 1] - c[kk, 1] - v[1] * dt[i]
        r = (np.sqrt(dx * dx + dy * dy) - radius) / sig[i]
        rr += r * r
        if i > 0 and scan[i] == scan[i - 1] and kk == k[i - 1]:
            rs += prev * r
            m += 1
        prev = r
    return rr, rs, m


def warm_up() -> None:
    """Compile (or load from numba's cache) every loop here now, with the argument types
    the tracking passes, not at the first scan: a first compile takes ~1-3 s (~0.2 s to
    load from the cache), which inside a live capture's callback would stall it."""
    z = np.zeros((1, 3))
    ray_sample_keys(z, z, np.ones(1, np.int64), 0.05, np.zeros(3), 0.1, 1 << 20)
    one, idx = np.zeros(1), np.zeros(1, np.int64)
    pairs_within(one, one, one, idx, idx, 1.0, False)  # pairs drawn within labels
    idx32 = np.zeros(1, np.int32)
    pairs_within(one, one, one, idx32, idx32, 1.0, False)  # pairs drawn over all points
    seen_by_both(one, one, one, np.zeros((1, 2, 5)), idx, idx, 0.0, 0.0, 1e-3)
    pair_terms(idx, idx, one, one, True, one, one, np.zeros((1, 2, 5)), True, 0.0, 0.0, 1e-3)
    slot_merge(np.zeros(1, np.int64), np.ones(1, np.uint64), np.uint64(1), np.zeros(1, np.int64))
    for d in (2, 3):  # the segmentation's points in the plane and in 3D
        linked_labels(np.zeros((1, d)), idx, idx, one, True)
    circle_normal_equations(np.zeros((1, 2)), one, np.ones(1), idx, np.zeros((1, 2)),
                            np.zeros(2), 0.1, 2.0, np.zeros((1, 5, 5)), np.zeros((1, 5)))
    circle_start_sums(np.zeros((1, 2)), one, np.zeros(2))
    circle_residual_stats(np.zeros((1, 2)), one, np.ones(1), idx, np.zeros((1, 2)),
                          np.zeros(2), 0.1, idx)
