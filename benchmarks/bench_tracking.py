"""Tracking cost: update time per scan against the 100 ms scan period, and one entropy
evaluation as accumulated scans grow.

1. Per-scan update (online segmentation: carve + classify + cluster; tracker: associate,
   coarse motion, Rényi refinement) on the simulated paper scenario with mirrors deployed
   (60 scans: two nod sweeps). Reported as a percentage of the URG-04LX scan period (the
   baseline, 100 ms): the aim is <= 10 %.
2. One entropy evaluation (voxel eq. 12 and Rényi) on the object's accumulated cloud of
   k = 1, 5, 10, 20 scans, as a ratio to k = 1 measured in the same run. The Rényi pair list
   is built once per refinement (also timed, as "renyi setup").

Run: ``.venv/bin/python benchmarks/bench_tracking.py``.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from nodlidar.solver import solve
from nodlidar.spec import load_design
from nodlidar.tracking.motion import RenyiCost, _voxel_entropy_fast, compensate
from nodlidar.tracking.segment import OnlineSegmenter, SegmentConfig, segment_batch
from nodlidar.tracking.simdata import simulate_scans
from nodlidar.tracking.tracker import Tracker, TrackerConfig

ROOT = Path(__file__).resolve().parents[1]


def per_call(fn, min_time: float = 0.3) -> float:
    n, t0 = 0, time.perf_counter()
    while True:
        fn()
        n += 1
        dt = time.perf_counter() - t0
        if dt >= min_time:
            return dt / n


def time_entropies(P, T, vel) -> tuple[float, float, float]:
    """Seconds per voxel evaluation, per Rényi evaluation, per Rényi pair-list setup."""
    t_ref = float(T.max())
    tv = per_call(lambda: _voxel_entropy_fast(compensate(P, T, vel, t_ref)[:, :2], 0.03))
    cost = RenyiCost(P, T, t_ref, 0.02, vel, max_dv_m_s=0.08)
    tr = per_call(lambda: cost(vel))
    ts = per_call(lambda: RenyiCost(P, T, t_ref, 0.02, vel, max_dv_m_s=0.08))
    return tv, tr, ts


def main() -> None:
    design = solve(load_design(ROOT / "design" / "urg04lx-paper.toml"))
    period = design.lidar.scan_period_s
    scans = simulate_scans(design, 60, mirrors_deployed=True, seed=0)
    for ent in ("renyi", "voxel"):
        seg = OnlineSegmenter(SegmentConfig(), design.lidar.range_sigma_m)
        trk = Tracker(TrackerConfig(entropy=ent))
        dts = []
        for s in scans:
            t0 = time.perf_counter()
            trk.update(seg.update(s))
            dts.append(time.perf_counter() - t0)
        dts = np.array(dts)
        print(f"update per scan ({ent:5s}): median {np.median(dts) * 1e3:6.1f} ms "
              f"= {np.median(dts) / period:6.1%} of the {period * 1e3:.0f} ms period; "
              f"max {dts.max() * 1e3:6.1f} ms = {dts.max() / period:6.1%}")

    segs = segment_batch(scans[:38], SegmentConfig(), design.lidar.range_sigma_m)
    trk = Tracker(TrackerConfig())
    for s in segs:
        trk.update(s)
    best = max(trk.all_tracks(), key=lambda tr: len(tr.scans))
    vel = best.motion.velocity
    base = {}
    print(f"{'scans':>5} {'points':>6} {'voxel':>10} {'ratio':>6} {'renyi':>10} {'ratio':>6} "
          f"{'renyi setup':>12}")
    for k in (1, 5, 10, 20):
        if k > len(best.points):
            break
        P = np.concatenate(best.points[:k])
        T = np.concatenate(best.times[:k])
        tv, tr, ts = time_entropies(P, T, vel)
        base.setdefault("v", tv)
        base.setdefault("r", tr)
        print(f"{k:5d} {len(P):6d} {tv * 1e6:8.0f}us {tv / base['v']:6.1f} {tr * 1e6:8.0f}us "
              f"{tr / base['r']:6.1f} {ts * 1e3:10.2f}ms")


if __name__ == "__main__":
    main()
