"""Assembly throughput: nodlidar.runtime.assembly.assemble (full URG-04LX scans with the
paper's four mirrors, per-beam time and nod interpolation, mirror state per side, world
frame from interpolated robot poses) vs a bare polar -> xyz conversion of the same number
of points (the baseline: ``r cos(theta), r sin(theta), 0``, no nod, no mirrors).

Prints points/s of each and the ratio (the cost of the full pipeline per point).
Run: ``.venv/bin/python benchmarks/bench_assembly.py``.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from nodlidar.runtime.assembly import AssemblyModel, PoseTrack, ScanBatch, assemble
from nodlidar.solver import solve
from nodlidar.spec import load_design

DESIGN = Path(__file__).resolve().parents[1] / "design" / "urg04lx-paper.toml"
N_SCANS = 100  # 10 s of URG-04LX scans, 68 200 beams


def rate(fn, n_points: int, min_time: float = 1.0) -> float:
    fn()  # warm up
    n, t0 = 0, time.perf_counter()
    while True:
        fn()
        n += 1
        dt = time.perf_counter() - t0
        if dt >= min_time:
            return n * n_points / dt


def main() -> dict[str, float]:
    design = solve(load_design(DESIGN))
    lidar = design.lidar
    model = AssemblyModel.from_design(design)
    rng = np.random.default_rng(0)
    ranges = rng.uniform(0.3, 5.0, (N_SCANS, lidar.n_steps))
    ranges[rng.random(ranges.shape) < 0.03] = np.nan  # error codes
    t_scan = np.arange(N_SCANS) * lidar.scan_period_s
    batch = ScanBatch.from_arrays(lidar.steps, ranges, t_scan)
    t_nod = np.arange(-0.1, t_scan[-1] + 0.3, 0.004)  # nod servo sampled at 250 Hz
    nod = (t_nod, 0.35 * np.sin(t_nod))
    mirrors = (np.array([-1.0, 100.0]), np.zeros(2))  # deployed all along
    t_pose = np.arange(-0.1, t_scan[-1] + 0.3, 0.05)
    poses = np.tile(np.eye(4), (len(t_pose), 1, 1))
    poses[:, 0, 3] = 0.5 * t_pose  # driving at 0.5 m/s while turning
    c, s = np.cos(0.2 * t_pose), np.sin(0.2 * t_pose)
    poses[:, 0, 0], poses[:, 0, 1], poses[:, 1, 0], poses[:, 1, 1] = c, -s, s, c
    track = PoseTrack(t_pose, poses)
    r2s = np.eye(4)
    r2s[:3, 3] = (0.2, 0.0, 0.4)
    n_points = batch.ranges_m.size

    def full():
        return assemble(model, batch, nod, mirror_left=mirrors, mirror_right=mirrors,
                        frame="world", robot_from_sensor=r2s, world_from_robot=track)

    theta = lidar.bearing_from_step(batch.steps)
    r = batch.ranges_m

    def bare():
        return np.stack([r * np.cos(theta), r * np.sin(theta), np.zeros_like(r)], -1)

    pc = full()
    r_full = rate(full, n_points)
    r_bare = rate(bare, n_points)
    print(f"{N_SCANS} URG-04LX scans = {n_points} beams ({len(pc)} valid points; "
          f"{int((pc.mirror >= 0).sum())} via mirrors)")
    print(f"  bare polar -> xyz            : {r_bare / 1e6:8.2f} M points/s")
    print(f"  assemble (nod, mirrors, world): {r_full / 1e6:8.2f} M points/s")
    print(f"  ratio (assemble / bare)       : {r_full / r_bare:8.3f}  "
          f"({r_bare / r_full:.1f}x slower per point)")
    return {"ratio_vs_bare": r_full / r_bare, "points_per_s": r_full}  # for benchmarks/run.py


if __name__ == "__main__":
    main()
