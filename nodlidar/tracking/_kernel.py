"""Compiled loops of the tracking's per-scan work, where numpy spends its time in dozens of
passes over one large temporary each.

- :func:`ray_sample_keys`: the voxel keys of the carving samples along every ray
  (:meth:`~nodlidar.tracking.voxels.VoxelMap.free_keys`): ~35 array passes over ~45 k
  samples per scan and a sort of them in numpy, one loop and a hash set here;
- :func:`pairs_within`: of the pairs of points a Rényi cost draws at random, those within
  its cutoff, with their offsets (:class:`~nodlidar.tracking.motion.RenyiCost`): ~10
  passes over ~320 k drawn pairs, most of them dropped, in numpy;
- :func:`seen_by_both`: which of those pairs both scans could see (the cut lines' test of
  :func:`~nodlidar.tracking.motion._seen_by_both`), ~15 passes per line in numpy.

Every value is the one the numpy formulas gave: the same float64 operations in the same
order (numba without fastmath: no reordering, no fused multiply-add), checked bit for bit
against them in tests/test_tracking_kernel.py. numba is imported here only, and this
module only inside the functions that use it (``import nodlidar`` never loads it).
Compiled with ``cache=True`` (the first call in a fresh environment compiles) and
``nogil=True``.
"""

from __future__ import annotations

import math

import numba
import numpy as np

__all__ = ["ray_sample_keys", "pairs_within", "seen_by_both", "warm_up"]

_jit = numba.njit(cache=True, nogil=True)


_HASH_MUL = np.uint64(0x9E3779B97F4A7C15)  # Fibonacci hashing: 2**64 / golden ratio


@_jit
def _insert(table: np.ndarray, bits: int, key: np.int64) -> bool:
    """Put ``key`` (not -1) in the open-addressing set ``table`` (-1: empty slot; size
    ``2**bits``); True if it was not there."""
    mask = (1 << bits) - 1
    h = np.int64((np.uint64(key) * _HASH_MUL) >> np.uint64(64 - bits))
    while True:
        v = table[h]
        if v == key:
            return False
        if v == -1:
            table[h] = key
            return True
        h = (h + 1) & mask


@_jit
def ray_sample_keys(start: np.ndarray, direction: np.ndarray, cnt: np.ndarray,
                    spacing: float, origin: np.ndarray, voxel: float,
                    off: int) -> np.ndarray:
    """The distinct voxel keys of the samples ``start_r + (k spacing) dir_r``,
    ``k = 0 .. cnt_r - 1``, of every ray ``r`` (in no particular order).

    Parameters
    ----------
    start, direction : (n, 3) float64
        Rays [m].
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
    (m,) int64 distinct keys ``(i + off) << 42 | (j + off) << 21 | (k + off)``,
    ``i = floor((p - origin) / voxel)`` per axis, as computed axis by axis in numpy. A
    scan's ~45 k samples fall in ~1.5 k voxels: a hash set keeps each once (sorting all
    of them cost as much as computing them).
    """
    bits = 12
    table = np.full(1 << bits, -1, np.int64)
    n_in = 0
    minus_one = False  # the empty slot's marker as a key (an index far off the grid)
    prev = np.int64(0)
    started = False
    for r in range(len(cnt)):
        for k in range(cnt[r]):
            s = k * spacing
            key = np.int64(0)
            for a in range(3):
                q = direction[r, a] * s
                q += start[r, a]
                q -= origin[a]
                q /= voxel
                key |= (np.int64(math.floor(q)) + off) << (42 - 21 * a)
            if started and key == prev:  # along a ray most samples share the previous voxel
                continue
            prev, started = key, True
            if key == -1:
                minus_one = True
                continue
            if _insert(table, bits, key):
                n_in += 1
                if 2 * n_in > len(table):  # load 1/2: twice the size, keys put again
                    old = table
                    bits += 1
                    table = np.full(1 << bits, -1, np.int64)
                    for v in old:
                        if v != -1:
                            _insert(table, bits, v)
    out = np.empty(n_in + (1 if minus_one else 0), np.int64)
    m = 0
    for v in table:
        if v != -1:
            out[m] = v
            m += 1
    if minus_one:
        out[m] = -1
    return out


@_jit
def pairs_within(qx: np.ndarray, qy: np.ndarray, qz: np.ndarray, i: np.ndarray,
                 j: np.ndarray, r2: float, use_z: bool):
    """The pairs ``(i[k], j[k])`` whose points lie within ``sqrt(r2)`` of each other, in
    order, with their offsets ``q_i - q_j`` per axis (z only with ``use_z``; else an empty
    array): ``d2 = dx dx + dy dy (+ dz dz) <= r2`` as numpy evaluates it.

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
    """(m,) bool: :func:`~nodlidar.tracking.motion._seen_by_both`'s test, pair by pair: for
    each cut line ``k`` of the other point (``edges[o, k, :5]`` = anchor x, y, direction
    x, y, seen side; NaN side: no line), the point moved at ``(cx, cy)`` to the other's
    time lies on the seen side within ``tol_m`` [m]."""
    m = len(i)
    seen = np.ones(m, np.bool_)
    for p in range(m):
        ok = True
        for k in range(edges.shape[1]):
            for w in range(2):
                if w == 0:
                    pm, po, d = i[p], j[p], dt[p]
                else:
                    pm, po, d = j[p], i[p], -1.0 * dt[p]
                qx = px[pm] + cx * d
                qy = py[pm] + cy * d
                cross = edges[po, k, 2] * (qy - edges[po, k, 1]) \
                    - edges[po, k, 3] * (qx - edges[po, k, 0])
                # no line (a NaN side) compares False: no branch on it (the numpy test
                # computed only the pairs with a line; the same answer)
                ok &= not (edges[po, k, 4] * cross < -tol_m)
        seen[p] = ok
    return seen


def warm_up() -> None:
    """Compile (or load from numba's cache) every loop here now, with the argument types
    the tracking passes, not at the first scan: a first compile takes ~1-3 s (~0.2 s to
    load from the cache), which inside a live capture's callback would stall it."""
    z = np.zeros((1, 3))
    ray_sample_keys(z, z, np.ones(1, np.int64), 0.05, np.zeros(3), 0.1, 1 << 20)
    one, idx = np.zeros(1), np.zeros(1, np.int64)
    pairs_within(one, one, one, idx, idx, 1.0, False)
    seen_by_both(one, one, one, np.zeros((1, 2, 5)), idx, idx, 0.0, 0.0, 1e-3)
