"""Dynamic-point segmentation: voxel inconsistency, then Euclidean clusters (paper Section V-A).

Per scan, every returned beam off the ground is clustered (cKDTree pairs within
``cluster_radius_m``, connected components). A cluster is *dynamic* when enough of its points
are **inconsistent** (:meth:`VoxelMap.inconsistent`: their voxel was traversed by a ray in a
different scan). The cluster step is the paper's "neighbourhood classification": a moving
object is only partly inconsistent in any one scan (the middle of its front face can stay
occupied for seconds), so the inconsistent points seed the object and the cluster carries the
label to the rest of it.

The ground (a flat floor at ``ground_z_m`` in the world frame: the robot drives on it) is
removed first, within ``ground_clearance_m``: grazing beams carve floor voxels that other beams
hit, which would otherwise make the whole floor inconsistent. This is a ground model, not a
threshold that decides what moves.

Two modes: :func:`segment_batch` (a recording: evidence from every scan, both "free then
occupied" and "occupied then traversed") and :class:`OnlineSegmenter` (scan by scan, evidence so
far only).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import cast

import numpy as np
from scipy.spatial import cKDTree

from ..errors import require
from .scans import ScanPoints
from .voxels import VoxelGrid, VoxelMap, WindowVoxelMap, carve_samples, unique_keys

__all__ = ["SegmentConfig", "Segmented", "cluster_points", "segment_batch",
           "OnlineSegmenter", "window_cut", "cut_edges", "grazing_secant", "seen_apart",
           "hidden_between",
           "seen_through", "behind_or_through", "column_rays", "silhouette_ends",
           "connected_labels", "warm_up"]


@dataclass(frozen=True)
class SegmentConfig:
    """Parameters of the dynamic-point segmentation.

    Attributes
    ----------
    voxel_m : float
        Voxel edge of the inconsistency map [m].
    margin_voxels : float
        Carving stops this many voxels (+ 3 sigma of range noise) before each end point.
    min_scan_gap : int
        A traversal counts against a hit only this many scans or more apart.
    ground_z_m, ground_clearance_m : float
        Floor height in the world [m] and the band above it removed as ground [m].
    cluster_radius_m : float
        Largest linking distance of the clustering [m], and how far a fragment smaller than
        ``min_cluster_points`` may be from a cluster to join it (``cluster_plane=False``: the
        fixed 3D radius, the paper's Euclidean clustering).
    cluster_plane : bool
        Cluster the ground-plane projection (x, y) with a range-adaptive linking distance
        (default): ``eps = clip(cluster_beams * range * beam step, cluster_min_m,
        cluster_radius_m)`` per point, two points linked when closer than the larger of
        their two. Objects stand on the floor, so an object's slices at different heights
        (different nod angles, different mirror windows) overlap in the top view, while two
        objects side by side are apart there; the linking distance follows the beam spacing,
        which grows with range, instead of one radius for every range.
    cluster_min_m : float
        Smallest linking distance [m] (the default 0.05 m: below the 6-9 cm gap between two
        people side by side, above the 1-2 cm beam spacing on a surface at 2-3 m).
    cluster_beams : float
        Linking distance in beam spacings at the point's range.
    beam_step_rad : float
        Angle between neighbouring beams [rad] (URG-04LX: 2 pi / 1024).
    min_cluster_points : int
        Smaller clusters are ignored (noise).
    min_inconsistent_points : int
        A dynamic cluster has at least this many inconsistent points ...
    min_inconsistent_fraction : float
        ... and at least this fraction of its points inconsistent.
    fraction_per_window : bool
        The two tests above also pass for a cluster when they pass on its points of any one
        mirror window alone (the direct window or one reflected window; ``scan.mirror``). A
        window is a view of its own: how much of an object it sees as inconsistent depends
        on the angle from which it sees the motion, so mixing the windows' points dilutes
        one window's evidence with another's (measured on a cylinder receding along the
        line of sight at 0.6 m/s: 8 of 52 direct points inconsistent, 15 %, but 21 of the
        171 points of all five windows, 12 %: lifted finds it, mirrors deployed do not).
        With one window (lifted) it is the cluster's test, unchanged. Off by default: it
        finds movers sooner in time, but measured over the scenes it also breaks an
        identity and delays convergence counted in scans with the object (docs/tracking.md,
        "Along the line of sight"). Re-measured with the adaptive pairs: the identity is
        kept with ``TrackerConfig.reacquire_speed_m_s``, but the paper case and four other
        movers still become later than lifted by count (docs/tracking.md, "Per-window
        segmentation and re-acquisition").
    carve_no_return_m : float
        A beam with no return carves this far [m]. The URG reports "nothing within range"
        (DMAX 5.6 m) as an error code, so the space in front is free; the default stays
        short of DMAX by the noise at that range. 0 turns it off (e.g. for dark targets).
    static_speed_m_s : float
        Online segmentation only (:class:`OnlineSegmenter`): a point whose voxel was also hit
        at least ``voxel_m / static_speed_m_s`` earlier (2 s by default) is consistent -
        whatever is there moves slower than this speed (static support,
        :class:`~nodlidar.tracking.voxels.WindowVoxelMap`). Without it, static things that
        rays pass beside within one voxel - a pole, a table's edge, a door frame, a person
        standing still - are inconsistent in every nod cycle and become tracks (measured in
        a furnished room: 1.5 false dynamic clusters per scan with mirrors, 4.7 lifted,
        before; none after the first nod cycle, docs/tracking.md "Furniture"). The default
        is the issue's slowest mover (0.05 m/s), which is still found. 0 turns it off.
    grazing_margin, grazing_min_run_m : bool, float
        The carving margin is measured off the surface, not along the ray, on long surfaces
        (:func:`grazing_secant`): a ray that meets a surface at incidence ``a`` stops
        ``margin / cos a`` before its end point, where that surface runs on for
        ``grazing_min_run_m`` [m] or more in the scan line. Along the ray, a grazing ray
        crossed the voxels its neighbours' hits on the wall fill, and the wall was "free,
        then occupied" one scan later: static support judges it only after 2 s, and a
        moving robot sees new wall all the time. Measured, seeds 0-7, false tracks lifted /
        with mirrors, before -> after: a corridor 2 m wide 69 / 69 -> 1 / 7, driving down it
        at 0.3 m/s 73 / 24 (4 seeds) -> 0 / 1, a wall 1 m behind the sensor 49 / 0 ->
        4 / 0, the three furnished rooms 87-90 / 21-27 -> 42-45 / 21-27; every mover's
        convergence, purity and identity unchanged in all 45 scenes (docs/tracking.md
        "Walls at grazing incidence"). Short surfaces keep the
        plain margin: applied to every surface it also found boxes later (a 0.13 m/s box,
        its leading side at 68 deg: scan 25 -> 29.5 with mirrors, 16 seeds), because the
        evidence of a face moving along its normal is the space just in front of it.
        0.8 m (1.5 m until 2026-12-06): above the longest side of the movers the tracker is
        built for (people, the issue's boxes up to 0.6 m), and short enough for a wall seen
        in pieces - cut off by the lidar's range at one end and by a person or furniture in
        front at the other (a robot driving along a room saw 1.3 m of its side wall, the
        rays carved it, and the wall became a track). Measured, seeds 0-7, every scene and
        the issue's grid (736 runs): every mover's convergence, identity, purity and final
        velocity identical; false tracks with mirrors / lifted 27 / 53 -> 12 / 33. A mover
        with a side of 0.8 m or more is found later (a 1.2 x 0.5 m cart: scan 11.5 -> 25
        with mirrors; docs/tracking.md "Ninth session").
        Rays to the floor keep the plain margin (the ground model: the floor's hits are
        not in the map, and those rays carve the space where people walk; without this a
        0.05 m/s walker converged 4 scans later with mirrors).
    split_seen_apart_beams : float
        A dynamic cluster whose top-view extent is within ``split_extent_m`` is clustered
        again with this finer linking distance (in beam spacings; its floor scaled alike),
        and split into the parts the scan saw apart (:func:`seen_apart`: a ray through the
        gap, or one jump in depth from one to the other). Beyond ~2.5 m, 4 beam spacings
        bridge the 6 cm gap between two people 0.42 m apart, and a young track that took
        the pair got its first velocity from their joint centroid and went on with the
        other person (side by side near the sensor, mirrors, seed 6). The finer distance
        alone splits surfaces at grazing incidence (3 beam spacings everywhere: measured,
        not kept, docs/tracking.md "Linking distance"); seeing the gap is the evidence.
        0 turns it off.
    split_extent_m : (float, float)
        Top-view extents [m] (diagonal of the bounding box) of the clusters tried: more
        than one person, less than a wall.
    scan_line_sigmas : float
        Neighbouring beams of one window's scan line are one surface when their points are
        within the linking distance plus this many standard deviations of the difference
        of their two ranges' noise (``sqrt 2`` times the lidar's range sigma at that range;
        :func:`scan_line_links`, :func:`cluster_points`'s ``links``). The range noise moves
        each point along its ray, and on a surface seen obliquely it opens steps between
        neighbours larger than the linking distance: a 1.2 m cart's face came apart into
        two to four clusters, two tracks followed its two ends and its identity switched
        between them scan by scan, and static surfaces broken into small pieces kept
        enough inconsistent points to pass for movers (docs/tracking.md "Tenth session").
        0 turns it off.
    """

    voxel_m: float = 0.1
    margin_voxels: float = 1.5
    min_scan_gap: int = 1
    ground_z_m: float = 0.0
    ground_clearance_m: float = 0.06
    cluster_radius_m: float = 0.15
    cluster_plane: bool = True
    cluster_min_m: float = 0.05
    cluster_beams: float = 4.0
    beam_step_rad: float = 2 * np.pi / 1024
    min_cluster_points: int = 5
    min_inconsistent_points: int = 3
    min_inconsistent_fraction: float = 0.15
    fraction_per_window: bool = False
    carve_no_return_m: float = 5.0
    static_speed_m_s: float = 0.05
    grazing_margin: bool = True
    grazing_min_run_m: float = 0.8
    split_seen_apart_beams: float = 3.0
    split_extent_m: tuple[float, float] = (0.45, 1.5)
    scan_line_sigmas: float = 2.0

    def __post_init__(self) -> None:
        require(self.voxel_m > 0, "voxel_m", self.voxel_m, "> 0 m")
        require(self.cluster_radius_m > 0, "cluster_radius_m", self.cluster_radius_m, "> 0 m")
        require(0 < self.cluster_min_m <= self.cluster_radius_m, "cluster_min_m",
                self.cluster_min_m, f"> 0 m and <= cluster_radius_m ({self.cluster_radius_m} m)")
        require(self.cluster_beams > 0, "cluster_beams", self.cluster_beams, "> 0")
        require(0 <= self.min_inconsistent_fraction <= 1, "min_inconsistent_fraction",
                self.min_inconsistent_fraction, "0..1")
        require(self.min_scan_gap >= 1, "min_scan_gap", self.min_scan_gap, ">= 1")
        require(self.static_speed_m_s >= 0, "static_speed_m_s", self.static_speed_m_s,
                ">= 0 m/s (0: no static support)")
        require(self.scan_line_sigmas >= 0, "scan_line_sigmas", self.scan_line_sigmas,
                ">= 0 (0: off)")
        require(self.grazing_min_run_m >= 0, "grazing_min_run_m", self.grazing_min_run_m,
                ">= 0 m")
        require(0 <= self.split_seen_apart_beams < self.cluster_beams, "split_seen_apart_beams",
                self.split_seen_apart_beams, f"0 (off) .. < cluster_beams ({self.cluster_beams})")
        lo, hi = self.split_extent_m
        require(0 <= lo <= hi, "split_extent_m", self.split_extent_m, "0 <= lo <= hi [m]")

    @property
    def static_age_s(self) -> float:
        """Age [s] of a hit that gives a voxel static support (0: off)."""
        return self.voxel_m / self.static_speed_m_s if self.static_speed_m_s > 0 else 0.0


@dataclass(frozen=True, eq=False)
class Segmented:
    """Segmentation of one scan; arrays over the scan's beams ``(n,)``.

    Attributes
    ----------
    scan : ScanPoints
    ground : bool
    inconsistent : bool
    cluster : int
        Cluster label (-1: none / ground / no return).
    dynamic : bool
        The beam belongs to a dynamic cluster.
    supported : bool or None
        The beam belongs to a cluster that is dynamic only without static support
        (``SegmentConfig.static_speed_m_s``): it is where something was 2 s ago as well -
        a static thing rays pass beside, or a mover back on its own path (a person pacing,
        a robot reversing). Not dynamic; a track already following a mover may take it
        (``TrackerConfig.follow_supported_m_s``). None: no static support applied.
    """

    scan: ScanPoints
    ground: np.ndarray
    inconsistent: np.ndarray
    cluster: np.ndarray
    dynamic: np.ndarray
    supported: np.ndarray | None = None

    def objects(self) -> list[np.ndarray]:
        """Beam indices of each dynamic cluster."""
        return self._clusters(self.dynamic)

    def supported_objects(self) -> list[np.ndarray]:
        """Beam indices of each cluster that is dynamic only without static support."""
        return [] if self.supported is None else self._clusters(self.supported)

    def _clusters(self, mask: np.ndarray) -> list[np.ndarray]:
        labs = np.unique(self.cluster[mask])
        return [np.flatnonzero(mask & (self.cluster == c)) for c in labs]


def connected_labels(n: int, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Connected components of the undirected graph on nodes ``0..n-1`` with edges
    ``(a[k], b[k])``: (n,) int labels numbered in the order of each component's smallest
    node (the labels of ``scipy.sparse.csgraph.connected_components``).

    Union by the smaller root and pointer jumping, vectorised over the edges: a few passes
    for the graphs of one scan, where building a sparse matrix for scipy costs ~0.3 ms of
    checks per call (measured on the segmentation's own graphs: half the time).
    """
    parent = np.arange(n)
    a, b = np.asarray(a, np.intp), np.asarray(b, np.intp)
    while len(a):
        ra, rb = parent[a], parent[b]  # roots: the parents are compressed below
        apart = ra != rb
        if not apart.any():
            break
        # an edge within one tree stays so: only the others go on
        a, b, ra, rb = a[apart], b[apart], ra[apart], rb[apart]
        np.minimum.at(parent, np.maximum(ra, rb), np.minimum(ra, rb))  # parent <= node
        while True:
            up = parent[parent]
            if np.array_equal(up, parent):
                break
            parent = up
    return np.unique(parent, return_inverse=True)[1]


def cluster_points(points: np.ndarray, radius_m: float | np.ndarray, min_points: int = 1,
                   attach_m: float = 0.0, links: np.ndarray | None = None) -> np.ndarray:
    """Euclidean clustering: connected components of the neighbour graph.

    Parameters
    ----------
    points : (n, 3) or (n, 2) float
    radius_m : float or (n,) float
        Linking distance [m]; per point, two points are linked when closer than the larger
        of their two distances.
    min_points : int
        Components smaller than this get label -1 ...
    attach_m : float
        ... unless a point of a kept component is within ``attach_m`` [m]: then they join
        the nearest one's cluster (DBSCAN's border points: the sparse silhouette edge of an
        object, where beams graze its surface, joins the object instead of being lost).
    links : (k, 2) int, optional
        Further pairs of points (indices into ``points``; :func:`scan_line_links`) that
        connect their components whatever their distance. Components of ``min_points`` or
        more that they connect, directly or through smaller ones that are runs of the scan
        line, become one cluster with those of two points or more: the pieces of one
        surface come together (a person's edge that the noise cut off joins that person,
        not - by distance - the person beside, across the gap). A small component that is
        not a run passes no link on (two people's edge points linked across the gap
        between them in the top view would join the two). Single points stay what the
        linking distance made them (``-1``, or attached): the sparse points of a side face
        seen at grazing incidence, which the noise moves most, do not join an object
        because they follow it along the scan line (measured: linked into a low robot's
        cluster, they bent its heading by 10 deg; the incidence weights give them up to 4
        times the mass of a point facing the sensor).

    Returns
    -------
    (n,) int labels 0..c-1 (-1 for small components).
    """
    n = len(points)
    if n == 0:
        return np.zeros(0, int)
    eps = np.broadcast_to(np.asarray(radius_m, float), (n,))
    pairs = cKDTree(points).query_pairs(float(eps.max()), output_type="ndarray")
    # the pairs within the larger of their two radii, and the components they link: one
    # compiled pass (numpy's distances, then connected_labels' numbering; ~10 array passes
    # and a few union rounds in numpy)
    from ._kernel import linked_labels  # numba: loaded when first used

    lab = linked_labels(np.ascontiguousarray(points, float),
                        np.ascontiguousarray(pairs[:, 0], np.int64),
                        np.ascontiguousarray(pairs[:, 1], np.int64),
                        np.array(eps, float), bool(np.ptp(eps) > 0))  # writable: one signature
    sizes = np.bincount(lab)
    keep = sizes[lab] >= min_points
    if links is not None and len(links):
        links = np.asarray(links, np.int64)
        a, b = lab[links[:, 0]], lab[links[:, 1]]
        nc = len(sizes)
        # a small component passes links on only if it is a run of the scan line (its
        # points linked one after the other): not two people's edge points, linked across
        # the gap between them in the top view
        run = np.bincount(a[a == b], minlength=nc) == sizes - 1
        part = run | (sizes >= min_points)
        ok = (a != b) & part[a] & part[b]
        if ok.any():
            grp = connected_labels(nc, a[ok], b[ok])
            has_kept = np.zeros(int(grp.max()) + 1, bool)
            has_kept[grp[sizes >= min_points]] = True
            # kept components take their linked group's label, and so do the small ones of
            # two or more points (a piece of surface the noise cut off) in a group with a
            # kept one; single points keep theirs (dropped or attached below), having only
            # passed the links on
            keep = keep | ((sizes[lab] >= 2) & has_kept[grp[lab]])
            lab = np.where(keep, grp[lab], lab)
    # relabel kept components 0..c-1
    uniq, lab2 = np.unique(np.where(keep, lab, -1), return_inverse=True)
    lab2 = np.where(keep, lab2 - (1 if uniq[0] == -1 else 0), -1)
    small = np.flatnonzero(~keep)
    if attach_m > 0 and len(small) and keep.any():
        kept = np.flatnonzero(keep)
        d, j = cKDTree(points[kept]).query(points[small], distance_upper_bound=attach_m)
        near = np.isfinite(d)
        lab2[small[near]] = lab2[kept[j[near]]]
    return lab2


def scan_line_links(scan: ScanPoints, idx: np.ndarray, eps_m: np.ndarray | float,
                    noise_m: np.ndarray | float = 0.0) -> np.ndarray:
    """Pairs of neighbouring beams of one window's scan line that are close enough, with
    the range noise allowed for, to lie on one surface.

    Two beams of one window with consecutive steps are linked when their points are within
    the larger of their two linking distances plus noise allowances in the top view. The
    linking distance alone (4 beam spacings, 5-6 cm at 2.3 m) is below the steps the
    URG's range noise (1 % of the range) opens between neighbours on a face seen
    obliquely - 0.1 m now and then, as the noise moves each point along its own ray: a
    1.2 m cart's face came apart into two to four clusters, two of them tracks, and static
    surfaces broken by noise into small pieces kept enough inconsistent points to pass for
    movers (docs/tracking.md "Tenth session"). Only consecutive beams are linked: the
    allowance does not reach across a ray that went between two objects (its end point
    lies between them), and two people one partly behind the other stay apart where the
    depth step between them is larger than the allowance.

    Parameters
    ----------
    scan : ScanPoints
    idx : (m,) int
        The beams to link (valid, not ground).
    eps_m : (m,) float or float
        Their linking distances [m].
    noise_m : (m,) float or float
        Allowance for range noise per beam [m], added to ``eps_m``.

    Returns
    -------
    (k, 2) int
        Pairs of positions into ``idx``.
    """
    m = len(idx)
    if m < 2:
        return np.zeros((0, 2), np.int64)
    order = np.lexsort((scan.steps[idx], scan.mirror[idx]))
    beam = idx[order]
    adj = (np.diff(scan.steps[beam]) == 1) & (np.diff(scan.mirror[beam]) == 0)
    xy = scan.points[beam, :2]
    d = np.hypot(*(xy[1:] - xy[:-1]).T)
    e = (np.broadcast_to(np.asarray(eps_m, float), (m,))
         + np.broadcast_to(np.asarray(noise_m, float), (m,)))[order]
    i = np.flatnonzero(adj & (d <= np.maximum(e[1:], e[:-1])))
    return np.stack([order[i], order[i + 1]], axis=1).astype(np.int64)


def window_cut(scan: ScanPoints, idx: np.ndarray, reach_m: float = 0.0,
               occluders: bool = False, max_walk: int = 64,
               floor_z_m: float = -np.inf) -> np.ndarray:
    """Which of a cluster's points belong to a slice of it cut off by its window's edge
    (or, with ``occluders``, by a nearer return).

    In one scan each mirror window sees an object as one slice, a run of beams. The slice
    is *cut* where the beam next to one of its ends (the step before or after, outside
    the cluster) belongs to another window or to none (a window's edge, or the field of
    view's; a beam the assembly dropped). Such an end is a line fixed in the sensor, not
    the object's silhouette: as the object moves, it stays put, and an entropy over the
    slices pulls the motion towards standing still (measured: a person 2 m away entering
    three mirror windows at once read 0.016 m/s slow and 2 deg off over 16 scans,
    noise-free; -0.002 m/s and 0.1 deg without its cut slices; docs/tracking.md "Slices
    cut by a window's edge"). The narrow mirror windows cut objects often. A beam with no
    return, or a farther one, beside the slice is the silhouette's edge, not a cut.

    With ``reach_m > 0`` each end is first followed outwards, within its window, through
    the beams whose points lie within ``reach_m`` of the previous one in the top view: the
    same surface, left out of the cluster (a part the segmentation judged static, or
    another cluster), so the test applies where the object's slice really ends. With
    ``occluders`` a nearer return there (by more than ``reach_m``) is a cut too: an
    occluder's edge, fixed to the occluder rather than to the object (measured: a walker
    at 0.95 m/s coming out from behind a slower one, lifted, noise-free, read 0.031 m/s
    slow over scans 28-36, 0.002 m/s fast without the occluded slices;
    ``test_slices_cut_by_an_occluder_bias_the_motion``). With ``floor_z_m`` a return
    below that height beside an end is a cut too: where the nodding scan line meets the
    floor it leaves the object at its foot, a line fixed in the sensor for that scan
    (beyond it the beams reach the floor before the object). Measured: a person walking
    away at 0.3 m/s into the mirrors' view read 0.284 m/s, noise-free, over a window
    whose last scans met the floor at its foot, 0.292 without those scans
    (``design/scenes/track-entering-view.toml``, scan 21). The defaults (0, False,
    -inf) are the end test alone, with the cluster's own ends.

    Parameters
    ----------
    scan : ScanPoints
    idx : (k,) int
        The cluster's beam indices in ``scan``.
    reach_m : float
        Largest top-view gap [m] between neighbouring beams of one surface (0: no walk).
    occluders : bool
        Count a nearer return beside an end as a cut.
    max_walk : int
        At most this many beams followed from each end.
    floor_z_m : float
        Returns below this height [m] (world frame) are the floor (-inf: none is).

    Returns
    -------
    (k,) bool: True for the points of every (cluster, window) slice with a cut end.
    """
    idx = np.asarray(idx, np.int64)
    cut = np.zeros(len(idx), bool)
    win = scan.mirror[idx]
    for m in _slice_cut_ends(scan, idx, reach_m, occluders, max_walk, floor_z_m):
        cut |= win == m
    return cut


def cut_edges(scan: ScanPoints, idx: np.ndarray, reach_m: float = 0.0,
              occluders: bool = False, max_walk: int = 64,
              floor_z_m: float = -np.inf) -> np.ndarray:
    """The lines in the top view where a cluster's slices are cut (:func:`window_cut`):
    the ray of the last beam of the slice's surface at each cut end (where the floor cut
    it: the line where the scan meets the floor's height ``floor_z_m``, through the
    crossings of that beam and the next), and the side of it the slice lies on. Beyond
    that line the scan could not see the object, whatever its shape: an entropy
    comparing two scans should only compare what both could see
    (:class:`~nodlidar.tracking.motion.RenyiCost`, ``edges``).

    Parameters are those of :func:`window_cut`.

    Returns
    -------
    (k, 2, 6) float: per point, up to two lines of its slice ``(a_x, a_y, d_x, d_y,
    side, occluder)``: a point ``a`` on the ray [m], its unit direction ``d`` in the top
    view, ``side`` = +1 / -1 where the slice lies to the left / right of ``d`` (``d x (p -
    a)`` has that sign), and ``occluder`` 1 where a nearer return cut it, 0 where a
    window's or the view's edge or the floor did. NaN rows: no such cut. A point is in
    a cut slice exactly where :func:`window_cut` says so (``isfinite(out[:, 0, 0])``).
    """
    idx = np.asarray(idx, np.int64)
    out = np.full((len(idx), 2, 6), np.nan)
    win = scan.mirror[idx]
    for m, ends in _slice_cut_ends(scan, idx, reach_m, occluders, max_walk,
                                   floor_z_m).items():
        sel = win == m
        c = scan.points[idx[sel], :2].mean(axis=0)
        for k, (e, kind, nxt) in enumerate(ends[:2]):
            line = _floor_line(scan, e, nxt, floor_z_m) if kind == 2 else None
            if line is None:
                a = scan.ray_start[e, :2]
                d = scan.ray_dir[e, :2] / np.hypot(*scan.ray_dir[e, :2])
            else:
                a, d = line
            side = np.sign(d[0] * (c[1] - a[1]) - d[1] * (c[0] - a[0])) or 1.0
            out[sel, k] = (a[0], a[1], d[0], d[1], side, float(kind == 1))
    return out


def _floor_line(scan: ScanPoints, e: int, nxt: int, floor_z_m: float
                ) -> tuple[np.ndarray, np.ndarray] | None:
    """The top-view line where the scan meets the height ``floor_z_m`` between beams ``e``
    and ``nxt``: a point on it and its unit direction, from where each beam's ray crosses
    that height (exact ray geometry, no range noise). None where a ray does not descend
    to it or the crossings coincide."""
    q = []
    for b in (e, nxt):
        dz = scan.ray_dir[b, 2]
        if dz >= 0:
            return None
        q.append(scan.ray_start[b, :2] + (floor_z_m - scan.ray_start[b, 2]) / dz
                 * scan.ray_dir[b, :2])
    d = q[1] - q[0]
    n = float(np.hypot(*d))
    return (q[1], d / n) if n > 0 else None


def _slice_cut_ends(scan: ScanPoints, idx: np.ndarray, reach_m: float, occluders: bool,
                    max_walk: int, floor_z_m: float = -np.inf
                    ) -> dict[int, list[tuple[int, int, int]]]:
    """Per mirror window whose slice of the cluster ``idx`` is cut (:func:`window_cut`),
    per cut end the beam index (into ``scan``) of the slice's surface's last beam, what
    cut it (0: a window's or the view's edge, 1: an occluder, 2: the floor) and the next
    beam's index beyond it (-1: none)."""
    ends: dict[int, list[tuple[int, int, int]]] = {}
    if not len(idx):
        return ends
    steps, mirror = scan.steps, scan.mirror
    lut, base = _beam_lut(steps)
    win = mirror[idx]
    ends_cut = np.zeros(len(idx), bool)  # per point: the next step is in another window
    for off in (-1, 1):
        nb = lut[steps[idx] + off - base]
        ends_cut |= (nb < 0) | (mirror[nb] != win)
    for m in np.unique(win[ends_cut]).tolist():
        at = idx[(win == m) & ends_cut]
        st = steps[at]
        ends[int(m)] = [(e, 0, -1) for e in sorted({int(at[np.argmin(st)]),
                                                     int(at[np.argmax(st)])})]
    if reach_m > 0 or occluders or floor_z_m > -np.inf:
        for m in np.unique(win):
            st = steps[idx[win == m]]
            for first, off in ((int(lut[st.min() - base]), -1), (int(lut[st.max() - base]), 1)):
                if any(e == first for e, _, _ in ends.get(int(m), ())):
                    continue  # this end is at the window's edge already
                cur, kind = _walk_out(scan, lut, base, first, off, reach_m, max_walk,
                                      floor_z_m)
                nxt = int(lut[int(steps[cur]) + off - base])
                if kind == "edge":
                    ends.setdefault(int(m), []).append((cur, 0, nxt))  # the window's (view's)
                elif kind == "floor":
                    ends.setdefault(int(m), []).append((cur, 2, nxt))
                elif kind == "nearer" and occluders:
                    ends.setdefault(int(m), []).append((cur, 1, nxt))  # an occluder's edge
    return ends


def _beam_lut(steps: np.ndarray) -> tuple[np.ndarray, int]:
    """Beam index by step (``lut[step - base]``, -1: no such beam), one slot of margin
    either side; returns ``(lut, base)``."""
    base = int(steps.min()) - 1
    lut = np.full(int(steps.max()) - base + 2, -1, np.int64)
    lut[steps - base] = np.arange(len(steps))
    return lut, base


def _walk_out(scan: ScanPoints, lut: np.ndarray, base: int, cur: int, off: int,
              reach_m: float, max_walk: int, floor_z_m: float = -np.inf) -> tuple[int, str]:
    """From a slice's end beam ``cur`` outwards (step ``off`` = -1 or 1) within its window,
    through the beams whose points lie within ``reach_m`` [m] of the previous one in the top
    view (the same surface); returns the last beam of that surface and what lies beyond it:
    ``"edge"`` (another window's beam or none: a window's or the view's edge), ``"none"``
    (no return), ``"nearer"`` / ``"farther"`` (a return nearer / farther by more than
    ``reach_m``), ``"beside"`` (another return at about the same range), ``"floor"`` (a
    return below ``floor_z_m`` not farther than ``reach_m``: the beam met the floor
    before the object; a farther one is ``"farther"``, the beam passed beside it) or
    ``"long"`` (the surface goes on for ``max_walk`` beams)."""
    steps, m = scan.steps, scan.mirror[cur]
    for _ in range(max_walk):
        nxt = int(lut[int(steps[cur]) + off - base])
        if nxt < 0 or scan.mirror[nxt] != m:
            return cur, "edge"
        if not np.isfinite(scan.range_m[nxt]):  # (scan.valid builds the whole mask)
            return cur, "none"
        if (scan.points[nxt, 2] < floor_z_m
                and scan.range_m[nxt] - scan.range_m[cur] <= reach_m):
            return cur, "floor"  # farther, the beam passed beside the object: its outline
        if float(np.hypot(*(scan.points[nxt, :2] - scan.points[cur, :2]))) <= reach_m:
            cur = nxt  # the same surface outside the cluster: go on
            continue
        dr = float(scan.range_m[nxt] - scan.range_m[cur])
        return cur, "nearer" if dr < -reach_m else "farther" if dr > reach_m else "beside"
    return cur, "long"


def silhouette_ends(scan: ScanPoints, idx: np.ndarray, reach_m: float = 0.05,
                    max_walk: int = 64, floor_z_m: float = -np.inf) -> np.ndarray:
    """Per slice of the cluster (one per mirror window), its two ends where they are the
    object's outline: followed outwards through the same surface (:func:`window_cut`'s
    ``reach_m``), the next beam has no return or a farther one, not on the floor (below
    ``floor_z_m`` [m]: there the scan line left the object at its foot, a place that moves
    with the nod). Not an end at a window's or the view's edge, nor one a nearer return
    hides.

    idx : (k,) int, the cluster's beam indices. Returns (w, 2) int: per window, the beam
    index (into ``scan``) of the slice's low-step and high-step end, -1 where that end is
    not the outline.
    """
    idx = np.asarray(idx, np.int64)
    if not len(idx):
        return np.zeros((0, 2), np.int64)
    lut, base = _beam_lut(scan.steps)
    win = scan.mirror[idx]
    out = []
    for m in np.unique(win):
        st = scan.steps[idx[win == m]]
        row = []
        for first, off in ((int(lut[st.min() - base]), -1), (int(lut[st.max() - base]), 1)):
            cur, kind = _walk_out(scan, lut, base, first, off, reach_m, max_walk)
            if kind == "farther":
                nxt = int(lut[int(scan.steps[cur]) + off - base])
                kind = "floor" if scan.points[nxt, 2] < floor_z_m else kind
            row.append(cur if kind in ("none", "farther") else -1)
        out.append(row)
    return np.asarray(out, np.int64)


def seen_through(scan: ScanPoints, idx: np.ndarray, keys: np.ndarray, grid: VoxelGrid,
                 margin_m: float | np.ndarray, reach_m: float) -> np.ndarray:
    """Which beams pass, shortly before their end point, through voxels in ``keys``.

    The evidence "occupied, then seen through" for one object: ``keys`` are the voxels an
    object's earlier points filled; a beam that now crosses one of them within ``reach_m``
    before its own end point (and more than ``margin_m`` before it: its own surface's
    voxel) sees the space that object left, and ends just behind it. A person walking
    straight away from the sensor shows no other evidence of moving: the space its back
    moves into was behind it, never seen free ("free, then occupied" is blind to it), but
    the rays now pass through where its back was.

    Parameters
    ----------
    scan : ScanPoints
    idx : (k,) int
        Beam indices to test (beams without a return test False).
    keys : (m,) int64
        Voxel keys (``grid.keys``) of the object's earlier points; need not be sorted.
    grid : VoxelGrid
    margin_m : float or (k,) float
        Nothing within this of a beam's end point counts [m] (the carving margin).
    reach_m : float
        Only this much of each beam before its end point is tested [m].

    Returns
    -------
    (k,) bool
    """
    idx = np.asarray(idx, np.int64)
    out = np.zeros(len(idx), bool)
    keys = unique_keys(np.asarray(keys, np.int64))
    if not len(idx) or not len(keys):
        return out
    length = np.nan_to_num(scan.range_m[idx] - scan.ray_offset[idx], nan=0.0)  # [m]
    s0 = np.maximum(length - reach_m, 0.0)  # where the tested part of each ray starts
    free = length - margin_m - s0  # its length (<= 0: nothing; no return: 0)
    step = grid.voxel_m / 2  # a sample in every voxel the part crosses
    d = scan.ray_dir[idx]
    pts = carve_samples(scan.ray_start[idx] + s0[:, None] * d, d, free, step)
    if not len(pts):
        return out
    cnt = np.maximum(np.ceil(np.maximum(free, 0.0) / step).astype(np.int64), 0)
    k = grid.keys(pts)
    i = np.minimum(np.searchsorted(keys, k), len(keys) - 1)
    return np.bincount(np.repeat(np.arange(len(idx)), cnt), weights=keys[i] == k,
                       minlength=len(idx)) > 0


def column_rays(scan: ScanPoints, center_xy: np.ndarray, radius_m: float,
                z_m: tuple[float, float], margin_m: float,
                beams: np.ndarray | None = None) -> tuple[np.ndarray, int, int]:
    """How the scan's beams meet a vertical column where an object is predicted to be.

    The column is a cylinder of ``radius_m`` about ``center_xy`` between heights ``z_m``.
    A beam whose ray enters it (at a height within ``z_m``) either ends more than
    ``margin_m`` before it - something nearer hides whatever is there - or more than
    ``margin_m`` beyond it - the column is free: nothing is there. Beams that end inside
    (the object's own surface, or something at its place) are counted apart; beams
    without a return count as none of these.

    Parameters
    ----------
    scan : ScanPoints
    center_xy : (2,) float
        Column axis, ground plane [m].
    radius_m : float
        Column radius [m].
    z_m : (2,) float
        Lowest and highest height of the column [m].
    margin_m : float
        [m].
    beams : (k,) int, optional
        Only these beams (indices into the scan); default all.

    Returns
    -------
    hidden : (h,) int
        Indices of the beams that end in front of the column.
    n_through : int
        Beams that pass through it.
    n_inside : int
        Beams that end inside it, within ``margin_m``: something is there.
    """
    ok = np.arange(len(scan.range_m)) if beams is None else np.asarray(beams, np.int64)
    rng = scan.range_m[ok] - scan.ray_offset[ok]
    ok, length = ok[np.isfinite(rng)], rng[np.isfinite(rng)]
    p0, d = scan.ray_start[ok], scan.ray_dir[ok]
    dxy2 = np.einsum("ij,ij->i", d[:, :2], d[:, :2])
    ok2 = dxy2 > 1e-6  # a (near) vertical ray meets no column side on
    ok, p0, d, length, dxy2 = ok[ok2], p0[ok2], d[ok2], length[ok2], dxy2[ok2]
    rel = np.asarray(center_xy, float) - p0[:, :2]
    s_mid = np.einsum("ij,ij->i", rel, d[:, :2]) / dxy2  # path length of closest approach
    miss2 = np.einsum("ij,ij->i", rel, rel) - s_mid ** 2 * dxy2  # squared distance there
    half = np.sqrt(np.maximum(radius_m ** 2 - miss2, 0.0) / dxy2)
    z = p0[:, 2] + s_mid * d[:, 2]
    meets = (miss2 <= radius_m ** 2) & (s_mid > 0) & (z >= z_m[0]) & (z <= z_m[1])
    hidden = meets & (length < s_mid - half - margin_m)
    through = meets & (length > s_mid + half + margin_m)
    return ok[hidden], int(through.sum()), int(np.count_nonzero(meets & ~hidden & ~through))


def behind_or_through(scan: ScanPoints, center_xy: np.ndarray, radius_m: float,
                      z_m: tuple[float, float], margin_m: float,
                      beams: np.ndarray | None = None) -> tuple[np.ndarray, int]:
    """:func:`column_rays` without the beams that end inside: (hidden, n_through)."""
    hidden, n_through, _ = column_rays(scan, center_xy, radius_m, z_m, margin_m, beams)
    return hidden, n_through


def seen_apart(scan: ScanPoints, a: np.ndarray, b: np.ndarray, beyond_m: float = 0.1,
               middle: float = 0.6, z_tol_m: float = 0.0, no_return_m: float = 5.0) -> bool:
    """Whether the scan saw two clusters apart: a ray that passes between them, or a single
    jump in depth from one to the other along a window's scan line (one partly behind the
    other's edge, :func:`_occluded_between`).

    Two clusters of one scan can be two pieces of one object (its faces seen through
    different mirror windows, or parts the segmentation split) or two objects side by
    side; how far apart their centroids are does not tell (two people 0.42 m apart seen
    obliquely, a 0.6 m cart). The free space does. ``p`` and ``q`` are the closest pair of
    points of the two in the top view; a ray *passes between* them when, in the top view,
    it crosses the middle ``middle`` of the segment ``p``-``q`` between the lowest and the
    highest point of the two (within ``z_tol_m``) and ends ``beyond_m`` or more past the
    crossing (a beam with no return: at ``no_return_m``), on neither cluster. The segment
    between two points of one convex object lies inside it, where no ray at its height
    goes; a beam through the gap between two people does.

    Parameters
    ----------
    scan : ScanPoints
    a, b : (k,) int
        Beam indices of the two clusters in ``scan``.
    beyond_m : float
        How far past the crossing the ray must end [m] (more than the range noise, so a ray
        ending on the far cluster's own surface does not count).
    middle : float
        Share of the segment, centred, that the ray must cross (0..1): a ray that grazes
        one cluster's noisy edge crosses the segment near its end.
    z_tol_m : float
        Margin [m] on the clusters' heights (lowest to highest point of either). 0 by
        default: a ray just over an object's top is no evidence of a gap (measured with
        0.1 m: a 0.5 m tall box's front and side faces, 0.42-0.45 m high, were "seen
        apart" by rays passing over its top, and a second track took the box). Not only
        the heights where *both* have points: one tilted scan line sees two people side by
        side at slightly different ranges, so at heights that overlap by millimetres, and
        the beams through the gap between them missed that overlap.
    no_return_m : float
        Length [m] of a beam with no return (it went through).

    Returns
    -------
    bool
    """
    a, b = np.asarray(a, np.int64), np.asarray(b, np.int64)
    if not len(a) or not len(b):
        return False
    pa, pb = scan.points[a], scan.points[b]
    d, j = cKDTree(pb[:, :2]).query(pa[:, :2])
    i = int(np.argmin(d))
    p, q = pa[i, :2], pb[j[i], :2]
    e = q - p
    if float(np.hypot(*e)) <= 0:
        return False
    # heights where the clusters have points: a ray within them that crosses the chord of
    # one convex object in the top view would have hit it; above the highest point (over a
    # box's top) it is no evidence
    z0 = min(float(pa[:, 2].min()), float(pb[:, 2].min())) - z_tol_m
    z1 = max(float(pa[:, 2].max()), float(pb[:, 2].max())) + z_tol_m
    s3, d3 = scan.ray_start, scan.ray_dir
    length = np.where(scan.valid, scan.range_m - scan.ray_offset, no_return_m)
    # top view: s + t d = p + u e (t: path length along the 3D unit direction)
    den = d3[:, 0] * e[1] - d3[:, 1] * e[0]
    ok = np.abs(den) > 1e-12
    den = np.where(ok, den, 1.0)
    w = p - s3[:, :2]
    t = (w[:, 0] * e[1] - w[:, 1] * e[0]) / den
    u = (w[:, 0] * d3[:, 1] - w[:, 1] * d3[:, 0]) / den
    z = s3[:, 2] + t * d3[:, 2]
    lo = 0.5 - middle / 2
    hit = ok & (t > 0) & (u >= lo) & (u <= 1 - lo) & (z >= z0) & (z <= z1) & \
        (length >= t + beyond_m)
    # a ray that ends on one of the two went into it, not between them (a noisy face:
    # a point 5 cm in front of a box's face and a beam 8 cm behind it, through the chord
    # between two of the face's points)
    hit[a] = False
    hit[b] = False
    return bool(hit.any()) or _occluded_between(scan, a, b)


def _scan_line_between(scan: ScanPoints, a: np.ndarray, b: np.ndarray,
                       inside: int = 0) -> Iterator[np.ndarray]:
    """For each window that sees clusters ``a`` and ``b`` (beam indices) one after the other
    along its scan line (not interleaved): the window's beams from the first cluster's last
    beam to the second's first, with up to ``inside`` more beams inside each, in step order.
    Only when those are consecutive steps that all returned (a gap in the window, or a beam
    through to nothing, is no scan line between the two)."""
    steps, mirror, r = scan.steps, scan.mirror, scan.range_m
    for m in np.intersect1d(mirror[a], mirror[b]):
        sa, sb = np.sort(steps[a][mirror[a] == m]), np.sort(steps[b][mirror[b] == m])
        if sa[-1] < sb[0]:
            first, second = sa, sb
        elif sb[-1] < sa[0]:
            first, second = sb, sa
        else:
            continue  # interleaved in this window
        lo, hi = max(first[-1] - inside, first[0]), min(second[0] + inside, second[-1])
        w = np.flatnonzero((mirror == m) & (steps >= lo) & (steps <= hi))
        w = w[np.argsort(steps[w])]
        if len(w) < 2 or np.any(np.diff(steps[w]) != 1) or not np.all(np.isfinite(r[w])):
            continue
        yield w


def _occluded_between(scan: ScanPoints, a: np.ndarray, b: np.ndarray, jump_m: float = 0.15,
                      ratio: float = 3.0) -> bool:
    """Whether, in a window that sees both clusters one after the other, the scan line
    from one to the other jumps in depth: one object partly behind the other (an
    occlusion boundary), not one surface. The largest step between consecutive beams,
    from three beams inside one cluster to three inside the other, must exceed ``jump_m``
    [m] and ``ratio`` times the median of the three steps beyond it on its far side (a
    person behind another's edge: the far surface is smooth; a face seen at grazing
    incidence past a box's corner recedes by a similar step at every beam; the median, as
    the URG's range noise makes single steps of 0.1 m at 2.3 m), and exceed by ``jump_m``
    the larger of the two steps before it on its near side that go the same way (such a
    face recedes into the step too; with one or two beams beyond the step, noise can make
    the far side's steps small: ``design/scenes/track-two-boxes.toml``, mirrors, seed 2,
    scan 73, 0.09 and 0.12 m, then 0.155 m, then -0.03 and 0.07 m). It must be the only
    step above ``jump_m`` there: two are a third object in between (a pole in front of one
    person, whose two sides are then two clusters of that person)."""
    r = scan.range_m
    # up to three beams inside each cluster (their surfaces' own steps) - and none beyond
    # them: a cluster with fewer beams here must not lend the jump at its outer edge (to
    # the background) to the test between the two (measured: a box's far corner, two beams
    # at grazing incidence next to its face, was "seen apart" from the face by the corner's
    # own silhouette jump, and a second track took the box). A gap in the window or a beam
    # with no return is the ray test's case
    for w in _scan_line_between(scan, a, b, inside=3):
        dr = np.diff(r[w])
        if int(np.sum(np.abs(dr) > jump_m)) != 1:
            continue  # a third object between them (a pole in front of one person), or none
        k = int(np.argmax(np.abs(dr)))
        # the far side's own steps (the surface behind the jump): small for a person
        # behind another's edge, as large as the jump for a face seen at grazing incidence
        # beyond a box's corner
        far = np.abs(dr[k + 1:k + 4] if dr[k] > 0 else dr[max(k - 3, 0):k])
        # the near side's own steps the same way (a face at grazing incidence recedes
        # into the jump, and the jump is no more than its next step; noise can hide that
        # on a far side of two beams): the jump must stand out of them too
        near = dr[max(k - 2, 0):k] if dr[k] > 0 else dr[k + 1:k + 3]
        lead = float(np.max(np.abs(near[np.sign(near) == np.sign(dr[k])]), initial=0.0))
        if abs(dr[k]) > jump_m and len(far) and abs(dr[k]) > ratio * float(np.median(far)) \
                and abs(dr[k]) - lead > jump_m:
            return True
    return False


def hidden_between(scan: ScanPoints, a: np.ndarray, b: np.ndarray, jump_m: float = 0.15,
                   max_gap_m: float = 0.6) -> bool:
    """Whether two clusters may be one surface continuing behind a nearer object: in a
    window that sees both one after the other, every beam between the first's last and the
    second's first ended ``jump_m`` [m] or more in front of both (an occluder, and nothing
    else, hides the gap), and in the top view those two end points are within
    ``max_gap_m`` [m].

    The converse of :func:`seen_apart`: there the scan saw free space, or one jump, between
    the two; here it saw nothing of the gap at all. A box walking behind a person's shadow
    is cut into two pieces 0.4-0.45 m apart (``design/scenes/track-side-by-side-box.toml``),
    beyond ``TrackerConfig.merge_m``; nothing the scan saw says they are two objects.

    Parameters
    ----------
    scan : ScanPoints
    a, b : (k,) int
        Beam indices of the two clusters in ``scan``.
    jump_m : float
        How far in front of both ends every beam between them must have ended [m] (more
        than the range noise).
    max_gap_m : float
        Largest top-view distance [m] between the two ends across the hidden gap.

    Returns
    -------
    bool
    """
    a, b = np.asarray(a, np.int64), np.asarray(b, np.int64)
    r = scan.range_m
    for w in _scan_line_between(scan, a, b):
        if len(w) < 3:
            continue  # adjacent on the scan line: nothing between them to hide
        ends = w[[0, -1]]
        if float(np.max(r[w[1:-1]])) > float(np.min(r[ends])) - jump_m:
            continue  # a beam between them ended near or beyond them: not hidden
        if float(np.hypot(*(scan.points[ends[0], :2] - scan.points[ends[1], :2]))) <= max_gap_m:
            return True
    return False


def _split_seen_apart(scan: ScanPoints, lab: np.ndarray, candidates: np.ndarray, cfg: SegmentConfig) -> bool:
    """Split clusters ``candidates`` (labels in ``lab``, over the scan's beams; changed in
    place, new parts get new labels) into the objects the scan saw apart; whether any was.

    A cluster whose top-view extent is within ``cfg.split_extent_m`` (more than one person,
    less than a wall) is clustered again with the finer linking distance of
    ``cfg.split_seen_apart_beams`` beam spacings; its parts of at least
    ``min_cluster_points`` points, largest first, join the nearest group already formed
    unless :func:`seen_apart` says the scan saw the two apart, and start a group of their
    own if it does; smaller fragments join the nearest group. The finer linking distance
    alone would split objects seen at grazing incidence into pieces (measured: 3 beam
    spacings everywhere cost identities and added ghosts, docs/tracking.md "Linking
    distance"); seen apart is the evidence that the pieces are two objects.
    """
    changed = False
    nxt = int(lab.max()) + 1
    lo, hi = cfg.split_extent_m
    for c in candidates:
        beams = np.flatnonzero(lab == c)
        if len(beams) < 2 * cfg.min_cluster_points:
            continue
        xy = scan.points[beams, :2]
        ext = float(np.hypot(*np.ptp(xy, axis=0)))
        if not lo <= ext <= hi:
            continue
        # the clustering's linking distance, scaled down by the ratio of beam spacings
        # (its floor too: at close range every distance is the floor)
        f = cfg.split_seen_apart_beams / cfg.cluster_beams
        eps = np.clip(f * cfg.cluster_beams * scan.range_m[beams] * cfg.beam_step_rad,
                      f * cfg.cluster_min_m, cfg.cluster_radius_m)
        sub = cluster_points(xy, eps, 1)
        sizes = np.bincount(sub)
        big = [k for k in np.argsort(-sizes, kind="stable") if sizes[k] >= cfg.min_cluster_points]
        if len(big) < 2:
            continue
        groups: list[list[int]] = [[int(big[0])]]
        for k in big[1:]:
            part = beams[sub == k]
            gb = [beams[np.isin(sub, g)] for g in groups]
            dist = [float(cKDTree(scan.points[g, :2]).query(scan.points[part, :2])[0].min())
                    for g in gb]
            near = int(np.argmin(dist))
            if seen_apart(scan, part, gb[near]):
                groups.append([int(k)])
            else:
                groups[near].append(int(k))
        if len(groups) < 2:
            continue
        # every part (small fragments too) to the group of its nearest grouped point
        gid = np.full(len(sizes), -1)
        for g, members in enumerate(groups):
            gid[members] = g
        grouped = gid[sub] >= 0
        if not grouped.all():
            _, j = cKDTree(xy[grouped]).query(xy[~grouped])
            gsub = gid[sub]
            gsub[~grouped] = gsub[grouped][j]
        else:
            gsub = gid[sub]
        for g in range(1, len(groups)):
            lab[beams[gsub == g]] = nxt
            nxt += 1
        changed = True
    return changed


def new_map(cfg: SegmentConfig,
            range_sigma: Callable[[np.ndarray], np.ndarray | float] | None = None) -> VoxelMap:
    """An empty :class:`VoxelMap` for ``cfg``."""
    return VoxelMap(VoxelGrid(cfg.voxel_m), margin_voxels=cfg.margin_voxels, range_sigma=range_sigma,
                    carve_no_return_m=cfg.carve_no_return_m)


def _ground(scan: ScanPoints, cfg: SegmentConfig) -> np.ndarray:
    return scan.valid & (scan.points[:, 2] < cfg.ground_z_m + cfg.ground_clearance_m)


def grazing_secant(scan: ScanPoints, max_secant: float = 10.0, beams: int = 5,
                   beam_step_rad: float = 2 * np.pi / 1024, min_run_m: float = 0.0,
                   jump_m: float = 0.15) -> np.ndarray:
    """(n,) ``1 / cos a`` (at most ``max_secant``), ``a`` the angle between each beam's ray
    and its surface's normal at the end point.

    A ray that stops ``m`` short of its end point along itself stays only ``m cos a`` off the
    surface; at grazing incidence (a wall seen along a corridor, or beside the sensor) it
    carves the voxels that the same surface's other hits occupy, and the wall becomes
    "inconsistent" until static support can judge it. Scaled by ``1 / cos a`` the margin is
    the same distance off the surface at every incidence.

    ``a`` is estimated in the scan line: a surface seen at incidence ``a`` changes range as
    ``dr / dtheta = r tan a``. The slope is a least-squares line of range against beam angle
    over ``2 beams + 1`` consecutive beams centred on the beam, all of one window, with a
    return and no depth jump between neighbours (more than ``jump_m`` plus the step of a
    surface at ``max_secant``'s incidence). Where that span is broken (an object's edge, the
    end of a window), the line over ``beams + 1`` beams on either side that is whole, the
    flatter of the two. A slope over several beams, not the chord to the next one: the
    URG's range noise (1 % of the range) is the size of the beam spacing at 2-3 m. The scan
    line lies in the surface, so ``cos a`` is an upper bound (the surface may also be
    inclined across the line). Beams without a whole line keep 1.

    With ``min_run_m`` > 0 only *long* surfaces count: beams on a run of beams (linked as
    above) whose ends are less than ``min_run_m`` apart keep 1. A wall or a corridor is
    long; a moving box's side is not, and there the margin must stay: the evidence of a
    face moving along its normal is the space just in front of it seen free (measured, a
    0.13 m/s box 2 m ahead, its leading side at 68 deg: found 4 scans later with mirrors
    over 16 seeds without this rule).

    Parameters
    ----------
    scan : ScanPoints
    max_secant : float
        The largest value returned (``cos a`` -> 0 along a surface).
    beams : int
        Beam steps spanned by each side's line (the centred line spans twice as many).
    beam_step_rad : float
        Angle between neighbouring beams [rad].
    min_run_m : float
        Shortest surface [m] whose beams get more than 1 (0: every surface).
    jump_m : float
        Depth jump [m] that ends a surface, beyond a grazing surface's own step.
    """
    n = len(scan.range_m)
    k = int(beams)
    out = np.ones(n)
    if n <= k:
        return out
    r = np.where(scan.valid, scan.range_m, 0.0)
    # cont g: beams g and g+1 are neighbours of one window, both with a return, on one
    # surface (their ranges differ by less than a jump)
    step = np.minimum(r[:-1], r[1:]) * beam_step_rad * np.sqrt(max_secant ** 2 - 1.0)
    cont = (scan.valid[:-1] & scan.valid[1:] & (np.diff(scan.steps) == 1)
            & (scan.mirror[:-1] == scan.mirror[1:]) & (np.abs(np.diff(r)) <= jump_m + step))
    breaks = np.concatenate([[0], np.cumsum(~cont)])  # breaks before each beam
    g = np.arange(n, dtype=float)
    cr = np.concatenate([[0.0], np.cumsum(r)])
    cgr = np.concatenate([[0.0], np.cumsum(g * r)])

    def tan_a(m: int) -> np.ndarray:
        """(n - m,) tan a of the line over beams [a, a + m] (inf where not whole)."""
        a = np.arange(n - m)
        sr = cr[a + m + 1] - cr[a]
        # least-squares slope per step: sum (g - centre) r / sum (g - centre)^2; tan a =
        # (dr / dtheta) / r, both at the line's middle
        slope = np.abs(cgr[a + m + 1] - cgr[a] - (a + m / 2.0) * sr) / (m * (m + 1) * (m + 2) / 12.0)
        return np.where(breaks[a + m] == breaks[a],
                        slope / beam_step_rad / np.maximum(sr / (m + 1), 1e-9), np.inf)

    t = np.full(n, np.inf)
    if n > 2 * k:
        t[k:n - k] = tan_a(2 * k)
    side = tan_a(k)
    flat = np.full(n, np.inf)
    flat[:n - k] = side  # the line that starts at the beam ...
    flat[k:] = np.minimum(flat[k:], side)  # ... and the one that ends at it
    t = np.where(np.isfinite(t), t, flat)
    ok = np.isfinite(t) & scan.valid
    out[ok] = np.minimum(np.sqrt(1.0 + t[ok] ** 2), max_secant)
    if min_run_m > 0:
        # a run: the beams with the same count of breaks before them (runs 0, 1, ...)
        first = np.flatnonzero(np.diff(breaks, prepend=-1))
        last = np.append(first[1:] - 1, n - 1)
        p = np.nan_to_num(scan.points)
        extent = np.linalg.norm(p[last] - p[first], axis=1)
        out[extent[breaks] < min_run_m] = 1.0
    return out


def integrate(vmap: VoxelMap, scan: ScanPoints, cfg: SegmentConfig) -> None:
    """Add ``scan`` to ``vmap`` (hits off the ground, every ray carved; each ray's margin
    grown at grazing incidence, :func:`grazing_secant`)."""
    ground = _ground(scan, cfg)
    keep = scan.valid & ~ground
    # the scan's time only to a map with static support (other maps keep their signature)
    kw: dict = {"t_s": scan.t_mid_s} if getattr(vmap, "static_age_s", 0.0) > 0 else {}
    if cfg.grazing_margin:
        # rays to the floor keep the plain margin: the floor's hits are not in the map (the
        # ground model), and those rays carve the space where people walk
        kw["margin_scale"] = np.where(ground, 1.0, grazing_secant(
            scan, beam_step_rad=cfg.beam_step_rad, min_run_m=cfg.grazing_min_run_m))
    vmap.integrate(scan.scan, scan.points[keep], scan.ray_start, scan.ray_dir, scan.range_m,
                   scan.ray_offset, **kw)


def classify(vmap: VoxelMap, scan: ScanPoints, cfg: SegmentConfig) -> Segmented:
    """Segment one scan against the evidence in ``vmap``."""
    n = len(scan.range_m)
    ground = _ground(scan, cfg)
    use = scan.valid & ~ground
    idx = np.flatnonzero(use)
    inc = np.zeros(n, bool)
    lab = np.full(n, -1)
    dyn = np.zeros(n, bool)
    support = isinstance(vmap, WindowVoxelMap) and vmap.static_age_s > 0
    raw = np.zeros(n, bool)  # inconsistent before static support
    sup = None
    if len(idx):
        p = scan.points[idx]
        raw[idx] = vmap.inconsistent(p, scan.scan, cfg.min_scan_gap)
        inc[:] = raw
        if support and raw.any():
            j = np.flatnonzero(raw)
            inc[j] = ~cast(WindowVoxelMap, vmap).static_support(scan.points[j], scan.t_mid_s)
        if cfg.cluster_plane:
            eps = np.clip(cfg.cluster_beams * scan.range_m[idx] * cfg.beam_step_rad,
                          cfg.cluster_min_m, cfg.cluster_radius_m)
            links = None
            if cfg.scan_line_sigmas > 0:
                # neighbours on the scan line: the noise of the two ranges allowed for
                rs = getattr(vmap, "range_sigma", None)  # a map without a noise model: 0
                sig = np.asarray(rs(scan.range_m[idx]), float) if rs is not None else 0.0
                links = scan_line_links(scan, idx, eps, cfg.scan_line_sigmas * np.sqrt(2) * sig)
            lab[idx] = cluster_points(p[:, :2], eps, cfg.min_cluster_points,
                                      attach_m=cfg.cluster_radius_m, links=links)
        else:
            lab[idx] = cluster_points(p, cfg.cluster_radius_m, cfg.min_cluster_points)
        ok = lab >= 0
        if ok.any():
            size = np.bincount(lab[ok])

            def dynamic_clusters(incons: np.ndarray) -> np.ndarray:
                ninc = np.bincount(lab[ok & incons], minlength=len(size))
                return (ninc >= cfg.min_inconsistent_points) & \
                    (ninc >= cfg.min_inconsistent_fraction * size)

            is_dyn = dynamic_clusters(inc)
            if cfg.split_seen_apart_beams > 0 and is_dyn.any():
                # two people side by side in one cluster: split it where the scan saw its
                # parts apart (SegmentConfig.split_seen_apart_beams)
                if _split_seen_apart(scan, lab, np.flatnonzero(is_dyn), cfg):
                    size = np.bincount(lab[ok])
                    is_dyn = dynamic_clusters(inc)
            if cfg.fraction_per_window:
                # the same tests on each (cluster, window) part (SegmentConfig)
                _, win = np.unique(scan.mirror, return_inverse=True)
                nw = int(win.max()) + 1
                key = lab[ok] * nw + win[ok]
                wsize = np.bincount(key, minlength=len(size) * nw)
                wninc = np.bincount(key[inc[ok]], minlength=len(size) * nw)
                wdyn = (wninc >= cfg.min_inconsistent_points) & \
                    (wninc >= cfg.min_inconsistent_fraction * wsize)
                is_dyn |= wdyn.reshape(len(size), nw).any(axis=1)
            dyn = ok & is_dyn[np.maximum(lab, 0)]
            if support:
                sup = ok & (dynamic_clusters(raw) & ~is_dyn)[np.maximum(lab, 0)]
    if support and sup is None:
        sup = np.zeros(n, bool)
    return Segmented(scan, ground, inc, lab, dyn, sup)


def segment_batch(scans: list[ScanPoints], cfg: SegmentConfig = SegmentConfig(),
                  range_sigma: Callable[[np.ndarray], np.ndarray | float] | None = None) -> list[Segmented]:
    """Segment a whole recording: the map holds every scan's evidence before classifying."""
    vmap = new_map(cfg, range_sigma)
    for s in scans:
        integrate(vmap, s, cfg)
    return [classify(vmap, s, cfg) for s in scans]


def warm_up() -> None:
    """Compile the tracking's loops (:mod:`nodlidar.tracking._kernel`: this module's carving,
    the tracker's Rényi pairs) now: a live run calls this before streaming, as
    :func:`nodlidar.runtime.assembly.warm_up` for the assembly, so that the first scan's
    compile does not stall the capture."""
    from ._kernel import warm_up as compile_kernels

    compile_kernels()


class OnlineSegmenter:
    """Scan-by-scan segmentation with the evidence gathered so far.

    ``update(scan)`` integrates the scan, then classifies it (a voxel hit now and traversed in an
    earlier scan is inconsistent; one traversed only later is not known yet). The map keeps
    the last ``window_scans`` scans (:class:`~nodlidar.tracking.voxels.WindowVoxelMap`;
    ``None``: every scan, a :class:`~nodlidar.tracking.voxels.VoxelMap` whose merge
    re-sorts all of it). Static support (``SegmentConfig.static_speed_m_s``) needs the
    window map's hits and applies with it only.
    """

    def __init__(self, cfg: SegmentConfig = SegmentConfig(),
                 range_sigma: Callable[[np.ndarray], np.ndarray | float] | None = None,
                 window_scans: int | None = 60) -> None:
        self.cfg = cfg
        if window_scans is None:
            self.map = new_map(cfg, range_sigma)
        else:
            # bounded map: the last window_scans scans' traversals (real time: the cost per
            # scan does not grow with the explored area)
            self.map = WindowVoxelMap(VoxelGrid(cfg.voxel_m), window_scans=window_scans,
                                      margin_voxels=cfg.margin_voxels, range_sigma=range_sigma,
                                      carve_no_return_m=cfg.carve_no_return_m,
                                      static_age_s=cfg.static_age_s)

    def update(self, scan: ScanPoints) -> Segmented:
        integrate(self.map, scan, self.cfg)
        return classify(self.map, scan, self.cfg)
