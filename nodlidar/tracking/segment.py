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

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from ..errors import require
from .simdata import ScanPoints
from .voxels import VoxelGrid, VoxelMap

__all__ = ["SegmentConfig", "Segmented", "cluster_points", "segment_batch", "OnlineSegmenter"]


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
        Points closer than this join one cluster [m].
    min_cluster_points : int
        Smaller clusters are ignored (noise).
    min_inconsistent_points : int
        A dynamic cluster has at least this many inconsistent points ...
    min_inconsistent_fraction : float
        ... and at least this fraction of its points inconsistent.
    carve_no_return_m : float
        A beam with no return carves this far [m]. The URG reports "nothing within range"
        (DMAX 5.6 m) as an error code, so the space in front is free; the default stays
        short of DMAX by the noise at that range. 0 turns it off (e.g. for dark targets).
    """

    voxel_m: float = 0.1
    margin_voxels: float = 1.5
    min_scan_gap: int = 1
    ground_z_m: float = 0.0
    ground_clearance_m: float = 0.06
    cluster_radius_m: float = 0.15
    min_cluster_points: int = 5
    min_inconsistent_points: int = 3
    min_inconsistent_fraction: float = 0.15
    carve_no_return_m: float = 5.0

    def __post_init__(self) -> None:
        require(self.voxel_m > 0, "voxel_m", self.voxel_m, "> 0 m")
        require(self.cluster_radius_m > 0, "cluster_radius_m", self.cluster_radius_m, "> 0 m")
        require(0 <= self.min_inconsistent_fraction <= 1, "min_inconsistent_fraction",
                self.min_inconsistent_fraction, "0..1")
        require(self.min_scan_gap >= 1, "min_scan_gap", self.min_scan_gap, ">= 1")


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
    """

    scan: ScanPoints
    ground: np.ndarray
    inconsistent: np.ndarray
    cluster: np.ndarray
    dynamic: np.ndarray

    def objects(self) -> list[np.ndarray]:
        """Beam indices of each dynamic cluster."""
        labs = np.unique(self.cluster[self.dynamic])
        return [np.flatnonzero(self.dynamic & (self.cluster == c)) for c in labs]


def cluster_points(points: np.ndarray, radius_m: float, min_points: int = 1) -> np.ndarray:
    """Euclidean clustering: connected components of the ``radius_m`` neighbour graph.

    Parameters
    ----------
    points : (n, 3) float
    radius_m : float
    min_points : int
        Components smaller than this get label -1.

    Returns
    -------
    (n,) int labels 0..c-1 (-1 for small components).
    """
    n = len(points)
    if n == 0:
        return np.zeros(0, int)
    pairs = cKDTree(points).query_pairs(radius_m, output_type="ndarray")
    g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, lab = connected_components(g, directed=False)
    sizes = np.bincount(lab)
    keep = sizes[lab] >= min_points
    # relabel kept components 0..c-1
    uniq, lab2 = np.unique(np.where(keep, lab, -1), return_inverse=True)
    lab2 = lab2 - (1 if uniq[0] == -1 else 0)
    return np.where(keep, lab2, -1)


def new_map(cfg: SegmentConfig, range_sigma=None) -> VoxelMap:
    """An empty :class:`VoxelMap` for ``cfg``."""
    return VoxelMap(VoxelGrid(cfg.voxel_m), margin_voxels=cfg.margin_voxels, range_sigma=range_sigma,
                    carve_no_return_m=cfg.carve_no_return_m)


def _ground(scan: ScanPoints, cfg: SegmentConfig) -> np.ndarray:
    return scan.valid & (scan.points[:, 2] < cfg.ground_z_m + cfg.ground_clearance_m)


def integrate(vmap: VoxelMap, scan: ScanPoints, cfg: SegmentConfig) -> None:
    """Add ``scan`` to ``vmap`` (hits off the ground, every ray carved)."""
    keep = scan.valid & ~_ground(scan, cfg)
    vmap.integrate(scan.scan, scan.points[keep], scan.ray_start, scan.ray_dir, scan.range_m,
                   scan.ray_offset)


def classify(vmap: VoxelMap, scan: ScanPoints, cfg: SegmentConfig) -> Segmented:
    """Segment one scan against the evidence in ``vmap``."""
    n = len(scan.range_m)
    ground = _ground(scan, cfg)
    use = scan.valid & ~ground
    idx = np.flatnonzero(use)
    inc = np.zeros(n, bool)
    lab = np.full(n, -1)
    dyn = np.zeros(n, bool)
    if len(idx):
        p = scan.points[idx]
        inc[idx] = vmap.inconsistent(p, scan.scan, cfg.min_scan_gap)
        lab[idx] = cluster_points(p, cfg.cluster_radius_m, cfg.min_cluster_points)
        ok = lab >= 0
        if ok.any():
            size = np.bincount(lab[ok])
            ninc = np.bincount(lab[ok & inc], minlength=len(size))
            is_dyn = (ninc >= cfg.min_inconsistent_points) & (ninc >= cfg.min_inconsistent_fraction * size)
            dyn = ok & is_dyn[np.maximum(lab, 0)]
    return Segmented(scan, ground, inc, lab, dyn)


def segment_batch(scans: list[ScanPoints], cfg: SegmentConfig = SegmentConfig(),
                  range_sigma=None) -> list[Segmented]:
    """Segment a whole recording: the map holds every scan's evidence before classifying."""
    vmap = new_map(cfg, range_sigma)
    for s in scans:
        integrate(vmap, s, cfg)
    return [classify(vmap, s, cfg) for s in scans]


class OnlineSegmenter:
    """Scan-by-scan segmentation with the evidence gathered so far.

    ``update(scan)`` integrates the scan, then classifies it (a voxel hit now and traversed in an
    earlier scan is inconsistent; one traversed only later is not known yet).
    """

    def __init__(self, cfg: SegmentConfig = SegmentConfig(), range_sigma=None) -> None:
        self.cfg = cfg
        self.map = new_map(cfg, range_sigma)

    def update(self, scan: ScanPoints) -> Segmented:
        integrate(self.map, scan, self.cfg)
        return classify(self.map, scan, self.cfg)
