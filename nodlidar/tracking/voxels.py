"""Voxel map with free-space carving: which space was seen free, which occupied, and when.

The paper (Section V-A) segments moving objects by *inconsistent measurements*: space a ray
passed through at one time and that returned a hit at another. :class:`VoxelMap` keeps, per
voxel of a regular world-frame grid, how often and in which scans (first and last) it was
hit and traversed; :meth:`VoxelMap.inconsistent` answers, for points observed in scan ``k``,
whether their voxel was traversed in a different scan (at least ``min_scan_gap`` away):
"observed free and later occupied" (traversed before) or "occupied and later traversed"
(traversed after).

Carving is vectorised over rays: every ray is sampled at a sub-voxel spacing (half a voxel by
default: a sample in every voxel the ray crosses except corner clips shorter than that), from
its start to ``range - margin``. The margin keeps a ray from carving the voxel of its own end
point and of its neighbours' end points on the same surface: ``margin = margin_voxels * voxel
+ 3 sigma(r)`` with the lidar's range sigma (range noise would otherwise carve static
surfaces), so static surfaces are not marked free by their own noise. The voxel part may be
scaled per ray (``margin_scale``): the segmentation measures it off long surfaces seen at
grazing incidence (:func:`nodlidar.tracking.segment.grazing_secant`).

Voxel keys pack ``(i, j, k)`` (21 bits each, offset 2**20) into one int64.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import require

__all__ = ["VoxelGrid", "VoxelMap", "WindowVoxelMap", "carve_samples", "unique_keys"]

_OFF = 1 << 20
_MASK = (1 << 21) - 1


@dataclass(frozen=True)
class VoxelGrid:
    """A regular grid: voxel ``floor((p - origin) / size)``.

    Attributes
    ----------
    voxel_m : float
        Edge length [m].
    origin_m : (3,) float
        A grid corner [m].
    """

    voxel_m: float = 0.1
    origin_m: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        require(self.voxel_m > 0, "voxel_m", self.voxel_m, "> 0 m")
        object.__setattr__(self, "origin_m", tuple(float(x) for x in self.origin_m))

    def index(self, points: np.ndarray) -> np.ndarray:
        """(n, 3) points [m] -> (n, 3) int64 voxel indices."""
        q = np.subtract(np.asarray(points, float), self.origin_m)  # a new array: in place below
        q /= self.voxel_m
        return np.floor(q, out=q).astype(np.int64)

    def keys(self, points: np.ndarray) -> np.ndarray:
        """(n, 3) points [m] -> (n,) int64 voxel keys."""
        return key_from_index(self.index(points))

    def centers(self, keys: np.ndarray) -> np.ndarray:
        """(n,) keys -> (n, 3) voxel centres [m]."""
        return (index_from_key(keys) + 0.5) * self.voxel_m + np.asarray(self.origin_m)


def key_from_index(ijk: np.ndarray) -> np.ndarray:
    """(n, 3) int voxel indices -> (n,) int64 keys (each index within +-2**20)."""
    ijk = np.asarray(ijk, dtype=np.int64) + _OFF
    return (ijk[:, 0] << 42) | (ijk[:, 1] << 21) | ijk[:, 2]


def unique_keys(keys: np.ndarray) -> np.ndarray:
    """Sorted unique values of a 1D integer array (voxel keys), as ``np.unique(keys)``.

    One sort and a comparison of neighbours: numpy 2's ``np.unique`` hashes, and on a
    scan's ~40 k carved keys with ~3 k distinct values that takes ~4x as long."""
    k = np.sort(np.asarray(keys).ravel())
    if len(k) < 2:
        return k
    return k[np.flatnonzero(np.concatenate(([True], k[1:] != k[:-1])))]


def index_from_key(keys: np.ndarray) -> np.ndarray:
    """Inverse of :func:`key_from_index`."""
    k = np.asarray(keys, dtype=np.int64)
    return np.stack([(k >> 42) & _MASK, (k >> 21) & _MASK, k & _MASK], -1) - _OFF


def carve_samples(start: np.ndarray, direction: np.ndarray, length: np.ndarray,
                  spacing: float) -> np.ndarray:
    """Points sampled along rays ``start + s dir`` for ``s`` in ``[0, length)`` every ``spacing``.

    Parameters
    ----------
    start, direction : (n, 3) float
    length : (n,) float
        Free length of each ray [m] (<= 0 or NaN: nothing).
    spacing : float
        Sample spacing [m].

    Returns
    -------
    (m, 3) float sample points, vectorised (one repeat + one multiply-add).
    """
    length = np.nan_to_num(np.asarray(length, float), nan=0.0)
    cnt = np.maximum(np.ceil(length / spacing).astype(np.int64), 0)
    if cnt.sum() == 0:
        return np.zeros((0, 3))
    out = np.repeat(np.asarray(direction, float), cnt, axis=0)  # start + s dir, in place
    out *= _ray_params(cnt, spacing)[:, None]
    out += np.repeat(np.asarray(start, float), cnt, axis=0)
    return out


def _ray_params(cnt: np.ndarray, spacing: float) -> np.ndarray:
    """Distances ``0, spacing, ..., (cnt_i - 1) spacing`` along each ray, concatenated."""
    first = np.cumsum(cnt) - cnt
    return (np.arange(cnt.sum()) - np.repeat(first, cnt)) * spacing


class _Stats:
    """Per-voxel count and first/last scan, as sorted key arrays (merge by np.unique)."""

    def __init__(self) -> None:
        self.keys = np.zeros(0, np.int64)
        self.count = np.zeros(0, np.int64)
        self.first = np.zeros(0, np.int64)
        self.last = np.zeros(0, np.int64)

    def add(self, keys: np.ndarray, scan: int) -> None:
        u, c = np.unique(keys, return_counts=True)
        allk = np.concatenate([self.keys, u])
        uk, inv = np.unique(allk, return_inverse=True)
        cnt = np.zeros(len(uk), np.int64)
        np.add.at(cnt, inv, np.concatenate([self.count, c]))
        first = np.full(len(uk), np.iinfo(np.int64).max)
        last = np.full(len(uk), np.iinfo(np.int64).min)
        np.minimum.at(first, inv, np.concatenate([self.first, np.full(len(u), scan)]))
        np.maximum.at(last, inv, np.concatenate([self.last, np.full(len(u), scan)]))
        self.keys, self.count, self.first, self.last = uk, cnt, first, last

    def lookup(self, keys: np.ndarray):
        """(found (n,) bool, count, first, last) for ``keys``."""
        i = np.searchsorted(self.keys, keys)
        i = np.clip(i, 0, max(len(self.keys) - 1, 0))
        found = (len(self.keys) > 0) & (self.keys[i] == keys) if len(self.keys) else np.zeros(len(keys), bool)
        if not len(self.keys):
            z = np.zeros(len(keys), np.int64)
            return found, z, z, z
        return found, np.where(found, self.count[i], 0), self.first[i], self.last[i]


class VoxelMap:
    """Hits and free-space traversals per voxel, with the scans they happened in.

    Parameters
    ----------
    grid : VoxelGrid
    margin_voxels : float
        Carving stops ``margin_voxels * voxel + 3 sigma(r)`` before each end point.
    sample_fraction : float
        Carving sample spacing as a fraction of the voxel.
    range_sigma : callable, optional
        ``sigma(range_m) -> [m]`` (e.g. ``LidarModel.range_sigma_m``); default 0.
    carve_no_return_m : float
        Beams with no return carve this far (0: not at all; a missing return can also be a
        dark or specular surface).
    """

    def __init__(self, grid: VoxelGrid, *, margin_voxels: float = 1.5, sample_fraction: float = 0.5,
                 range_sigma: Callable[[np.ndarray], np.ndarray | float] | None = None,
                 carve_no_return_m: float = 0.0) -> None:
        require(0 < sample_fraction <= 1, "sample_fraction", sample_fraction, "0 < f <= 1")
        self.grid = grid
        self.margin_voxels = float(margin_voxels)
        self.spacing = grid.voxel_m * sample_fraction
        self.range_sigma = range_sigma
        self.carve_no_return_m = float(carve_no_return_m)
        self.hits = _Stats()
        self.free = _Stats()

    def free_length(self, range_m: np.ndarray, offset_m: np.ndarray,
                    margin_scale: np.ndarray | float = 1.0) -> np.ndarray:
        """Length [m] of each outgoing ray that is carved (see the module docstring).

        ``margin_scale`` (scalar or (n,), >= 1) multiplies each ray's voxel margin: a ray
        that meets its surface at grazing incidence must stop further back along itself to
        stay as far off the surface (:func:`~nodlidar.tracking.segment.grazing_secant`)."""
        r = np.asarray(range_m, float)
        sig = self.range_sigma(np.nan_to_num(r)) if self.range_sigma is not None else 0.0
        free = r - offset_m - self.margin_voxels * self.grid.voxel_m * margin_scale - 3.0 * sig
        return np.where(np.isfinite(r), free, self.carve_no_return_m)

    def free_keys(self, start: np.ndarray, direction: np.ndarray, range_m: np.ndarray,
                  offset_m: np.ndarray, margin_scale: np.ndarray | float = 1.0,
                  compiled: bool = True) -> np.ndarray:
        """Unique keys of the voxels the rays traverse (before the margin, times
        ``margin_scale``: :meth:`free_length`).

        The keys of :func:`carve_samples`' points (``grid.keys``), with the same float
        operations: in one compiled loop over the samples
        (:func:`~nodlidar.tracking._kernel.ray_sample_keys`; this is the online
        segmentation's largest cost, ~50 k samples per scan), or with ``compiled=False``
        (and for rays that are not finite) axis by axis on 1D arrays in numpy (the (m, 3)
        sample array is never made). Both give the same keys.
        """
        length = np.nan_to_num(np.asarray(self.free_length(range_m, offset_m, margin_scale),
                                          float), nan=0.0)
        cnt = np.maximum(np.ceil(length / self.spacing).astype(np.int64), 0)
        if cnt.sum() == 0:
            return np.zeros(0, np.int64)
        start, direction = np.asarray(start, float), np.asarray(direction, float)
        if compiled and np.isfinite(start).all() and np.isfinite(direction).all():
            from ._kernel import ray_sample_keys  # numba: loaded when first carving

            return ray_sample_keys(  # sorted distinct keys
                np.ascontiguousarray(start), np.ascontiguousarray(direction), cnt,
                self.spacing, np.asarray(self.grid.origin_m, float), self.grid.voxel_m,
                _OFF)
        s = _ray_params(cnt, self.spacing)
        k = np.zeros(len(s), np.int64)
        for a, shift in ((0, 42), (1, 21), (2, 0)):
            q = np.repeat(direction[:, a], cnt)
            q *= s
            q += np.repeat(start[:, a], cnt)
            q -= self.grid.origin_m[a]
            q /= self.grid.voxel_m
            idx = np.floor(q, out=q).astype(np.int64)
            idx += _OFF
            idx <<= shift
            k |= idx
        # samples are half a voxel apart along each ray, so consecutive samples mostly share
        # a voxel: dropping the repeats first halves the sort (same unique keys)
        if len(k) > 1:
            k = k[np.flatnonzero(np.concatenate([[True], k[1:] != k[:-1]]))]
        return unique_keys(k)

    def integrate(self, scan: int, points: np.ndarray, start: np.ndarray, direction: np.ndarray,
                  range_m: np.ndarray, offset_m: np.ndarray, t_s: float = np.nan,
                  margin_scale: np.ndarray | float = 1.0) -> None:
        """Add one scan: hits from ``points`` (rows with NaN ignored) and the carved rays
        (``t_s``, the scan's time, is used by :class:`WindowVoxelMap`'s static support only).

        Parameters
        ----------
        scan : int
        points : (m, 3) float
            Hit points to record [m] (may be a subset of the beams, e.g. without ground).
        start, direction : (n, 3) float; range_m, offset_m : (n,) float
            Every beam's outgoing ray, measured range [m] and path offset [m].
        margin_scale : float or (n,) float
            Each ray's voxel margin factor (:meth:`free_length`).
        """
        p = np.asarray(points, float)
        p = p[np.all(np.isfinite(p), axis=1)]
        if len(p):
            self.hits.add(self.grid.keys(p), scan)
        fk = self.free_keys(start, direction, range_m, offset_m, margin_scale)
        if len(fk):
            self.free.add(fk, scan)

    def inconsistent(self, points: np.ndarray, scan: int | np.ndarray,
                     min_scan_gap: int = 1, t_s: float = np.nan) -> np.ndarray:
        """(n,) bool: the voxel of each point (observed in ``scan``) was traversed in a scan at
        least ``min_scan_gap`` before or after it (``t_s``: see :class:`WindowVoxelMap`)."""
        keys = self.grid.keys(points)
        found, _, first, last = self.free.lookup(keys)
        k = np.asarray(scan)
        return found & ((first <= k - min_scan_gap) | (last >= k + min_scan_gap))

    def free_count(self, points: np.ndarray) -> np.ndarray:
        """(n,) int: how many scans traversed each point's voxel."""
        return self.free.lookup(self.grid.keys(points))[1]


class _SlotIndex:
    """Sorted unique voxel keys and, per key, a ``uint64`` bit mask of the ring slots (kept
    scans, at most 64) whose key set holds it: one binary search answers for every kept
    scan at once, where a search per kept scan costs ~60 numpy calls per query.

    ``put(slot, keys)`` replaces the slot's set (sorted unique keys); ``lookup(keys)`` gives
    each key's mask (0: in no slot). Work per ``put``: a few passes over the index, whose
    size is the number of distinct voxels in the window (not the scans times their keys):
    one compiled merge (:func:`~nodlidar.tracking._kernel.slot_merge`), or with
    ``compiled=False`` a search and two inserts in numpy (the same index).
    """

    def __init__(self, compiled: bool = True) -> None:
        self.keys = np.zeros(0, np.int64)
        self.mask = np.zeros(0, np.uint64)
        self.compiled = compiled

    def put(self, slot: int, keys: np.ndarray) -> None:
        bit = np.uint64(1) << np.uint64(slot)
        if self.compiled:
            from ._kernel import slot_merge  # numba: loaded when first used

            self.keys, self.mask = slot_merge(self.keys, self.mask, bit,
                                              np.ascontiguousarray(keys, np.int64))
            return
        if len(self.keys):
            self.mask &= ~bit  # the slot's previous scan leaves
            live = self.mask != 0
            if not live.all():
                self.keys, self.mask = self.keys[live], self.mask[live]
        if not len(keys):
            return
        i = np.searchsorted(self.keys, keys)
        found = np.zeros(len(keys), bool)
        if len(self.keys):
            found = self.keys[np.minimum(i, len(self.keys) - 1)] == keys
            self.mask[i[found]] |= bit
        new = ~found
        # sorted new keys at non-decreasing positions: the result stays sorted
        self.keys = np.insert(self.keys, i[new], keys[new])
        self.mask = np.insert(self.mask, i[new], bit)

    def lookup(self, keys: np.ndarray) -> np.ndarray:
        """(n,) uint64 slot mask of each key (0 where no slot holds it)."""
        out = np.zeros(len(keys), np.uint64)
        if not len(self.keys) or not len(keys):
            return out
        i = np.minimum(np.searchsorted(self.keys, keys), len(self.keys) - 1)
        hit = self.keys[i] == keys
        out[hit] = self.mask[i[hit]]
        return out


class WindowVoxelMap(VoxelMap):
    """A :class:`VoxelMap` for online use whose size and per-scan cost are bounded: it keeps
    the traversed voxels of the last ``window_scans`` scans only, one sorted key array per
    scan (a ring), instead of one map of everything ever seen.

    Adding a scan costs its own sort, O(new keys log new keys), and an update of an index
    of the window's distinct voxels, each with a bit per kept scan that traversed it
    (``_SlotIndex``; a few passes over it, whose size the window bounds); dropping the
    oldest scan clears its bit. The cost does not grow with the explored area. A query is
    one binary search in the index for every kept scan at once (a window of more than 64
    scans: one search per kept scan). Evidence older
    than the window is forgotten: a voxel traversed more than ``window_scans`` scans ago and
    occupied now is not inconsistent - the window must outlast the nod's period (every
    height is swept again within one nod cycle; the default 60 scans is 6 s).

    **Static support** (``static_age_s`` > 0): a point is *not* inconsistent when its voxel
    was also hit at least ``static_age_s`` before (within the window). Whatever occupies the
    voxel now was there that long ago, so it moves slower than ``voxel / static_age_s``.
    This is what keeps thin or edged static things (poles, table edges, door frames, a
    person standing still) out of the dynamic set: rays pass *beside* them through the part
    of their voxel they do not fill, so their voxels are traversed in every nod cycle, and
    without this rule their points are inconsistent in every scan. A voxel's hits are kept
    as one sorted key array per scan, like the traversals.
    """

    def __init__(self, grid: VoxelGrid, *, window_scans: int = 60, static_age_s: float = 0.0,
                 **kw: Any) -> None:
        super().__init__(grid, **kw)
        require(window_scans >= 1, "window_scans", window_scans, ">= 1")
        require(static_age_s >= 0, "static_age_s", static_age_s, ">= 0 s (0: off)")
        self.window_scans = int(window_scans)
        self.static_age_s = float(static_age_s)
        self._scans: list[int] = []
        self._keys: list[np.ndarray] = []
        self._hit_keys: list[np.ndarray] = []  # per kept scan, sorted unique hit keys
        self._t_s: list[float] = []  # per kept scan, its time [s]
        # the same sets indexed by ring slot, one bit per kept scan (a window of more than
        # 64 scans searches scan by scan)
        self._slots: list[int] = []  # per kept scan, its slot
        self._free_index = _SlotIndex() if self.window_scans <= 64 else None
        self._hit_index = _SlotIndex() if self.window_scans <= 64 else None

    @property
    def n_keys(self) -> int:
        """Traversed (scan, voxel) entries kept."""
        return int(sum(len(k) for k in self._keys))

    def integrate(self, scan: int, points: np.ndarray, start: np.ndarray, direction: np.ndarray,
                  range_m: np.ndarray, offset_m: np.ndarray, t_s: float = np.nan,
                  margin_scale: np.ndarray | float = 1.0) -> None:
        """As :meth:`VoxelMap.integrate`; ``t_s`` is the scan's time [s] (static support)."""
        fk = self.free_keys(start, direction, range_m, offset_m, margin_scale)  # sorted, unique
        # the slot of the scan that leaves the window now, else the next unused one
        slot = self._slots[0] if len(self._scans) >= self.window_scans else len(self._slots)
        self._scans.append(int(scan))
        self._keys.append(fk)
        self._slots.append(slot)
        if self._free_index is not None:
            self._free_index.put(slot, fk)
        if self.static_age_s > 0:
            p = np.asarray(points, float)
            p = p[np.all(np.isfinite(p), axis=1)]
            hk = unique_keys(self.grid.keys(p))
            self._hit_keys.append(hk)
            self._t_s.append(float(t_s))
            if self._hit_index is not None:
                self._hit_index.put(slot, hk)
        while len(self._scans) > self.window_scans:
            self._scans.pop(0)
            self._keys.pop(0)
            self._slots.pop(0)
            if self._hit_keys:
                self._hit_keys.pop(0)
                self._t_s.pop(0)

    def _bits(self, use: list[bool]) -> np.uint64:
        """The OR of the slot bits of the kept scans where ``use`` (per kept scan) holds."""
        b = 0
        for slot, u in zip(self._slots, use):
            if u:
                b |= 1 << slot
        return np.uint64(b)

    def static_support(self, points: np.ndarray, t_s: float) -> np.ndarray:
        """(n,) bool: each point's voxel was hit in a kept scan at least ``static_age_s``
        before ``t_s`` [s] (all False when static support is off)."""
        keys = self.grid.keys(points)
        out = np.zeros(len(keys), bool)
        if self.static_age_s <= 0 or not np.isfinite(t_s):
            return out
        if self._hit_index is not None:
            bits = self._bits([ts <= t_s - self.static_age_s for ts in self._t_s])
            return out if bits == 0 else (self._hit_index.lookup(keys) & bits) != 0
        for ts, hk in zip(self._t_s, self._hit_keys):
            if not len(hk) or not ts <= t_s - self.static_age_s:
                continue
            i = np.minimum(np.searchsorted(hk, keys), len(hk) - 1)
            out |= hk[i] == keys
        return out

    def inconsistent(self, points: np.ndarray, scan: int | np.ndarray,
                     min_scan_gap: int = 1, t_s: float = np.nan) -> np.ndarray:
        """As :meth:`VoxelMap.inconsistent`, without the points that have static support at
        the scan's time ``t_s`` [s] (class docstring; NaN: no static support applied)."""
        keys = self.grid.keys(points)
        k = np.asarray(scan)
        scalar = k.ndim == 0  # one scan's points (the online case): the test per kept scan
        inv = None
        if scalar and self._free_index is not None:
            # every kept scan at once: the bits of those far enough from this one
            kk = int(k)
            bits = self._bits([s <= kk - min_scan_gap or s >= kk + min_scan_gap
                               for s in self._scans])
            out = (self._free_index.lookup(keys) & bits) != 0
            if out.any() and self.static_age_s > 0 and np.isfinite(t_s):
                out &= ~self.static_support(points, t_s)
            return out
        if scalar and len(keys) > 1:
            # each voxel once, in order: the ~60 searches below run over fewer keys, sorted
            # (same answer per point)
            keys, inv = np.unique(keys, return_inverse=True)
        out = np.zeros(len(keys), bool)
        for s, fk in zip(self._scans, self._keys):
            if not len(fk):
                continue
            far = (s <= k - min_scan_gap) | (s >= k + min_scan_gap)
            if not (far if scalar else np.any(far)):
                continue
            i = np.searchsorted(fk, keys)
            np.minimum(i, len(fk) - 1, out=i)
            if scalar:
                out |= fk[i] == keys
            else:
                out |= far & (fk[i] == keys)
        if inv is not None:
            out = out[inv]
        if out.any() and self.static_age_s > 0 and np.isfinite(t_s):
            out &= ~self.static_support(points, t_s)
        return out

    def free_count(self, points: np.ndarray) -> np.ndarray:
        keys = self.grid.keys(points)
        n = np.zeros(len(keys), np.int64)
        for fk in self._keys:
            if len(fk):
                i = np.minimum(np.searchsorted(fk, keys), len(fk) - 1)
                n += fk[i] == keys
        return n
