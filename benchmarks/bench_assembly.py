"""Assembly throughput: nodlidar.runtime.assembly.assemble (full URG-04LX scans with the
paper's four mirrors, per-beam time and nod interpolation, mirror state per side, world
frame from interpolated robot poses) vs a bare polar -> xyz conversion of the same number
of points (the baseline: ``r cos(theta), r sin(theta), 0``, no nod, no mirrors).

The two sides are timed interleaved in one process (A, B, A, B, ...), by the process's CPU
time (``time.process_time``: every thread of the process, so a multithreaded BLAS call
would be counted in full, yet other processes on a loaded machine are not); the ratio is
taken per adjacent pair and the median reported. Figures (for benchmarks/run.py):

* ``ratio_vs_bare``, ``points_per_s``: 100 scans (10 s of URG-04LX data, 68 200 beams);
* ``ratio_vs_bare_scans<N>``, ``points_per_s_scans<N>``: the scaling curve, N = 1, 10,
  100, 1000 scans in one call;
* the compiled kernel's one-off costs, each in a fresh process (wall time, what a user
  waits for): ``jit_import_s`` (importing numba and the kernel module),
  ``jit_compile_cold_s`` (the first ``assemble`` with ``NUMBA_CACHE_DIR`` a new empty
  directory: numba compiles and writes its cache) and ``jit_load_warm_s`` (the first
  ``assemble`` in the next process with that cache: numba loads the compiled kernel);
  ``jit_steady_s`` is a later call of the same 100 scans in those processes, for scale.

Run: ``.venv/bin/python benchmarks/bench_assembly.py``.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from nodlidar.runtime.assembly import AssemblyModel, PoseTrack, ScanBatch, assemble
from nodlidar.solver import solve
from nodlidar.spec import load_design

DESIGN = Path(__file__).resolve().parents[1] / "design" / "urg04lx-paper.toml"
N_SCANS = 100  # 10 s of URG-04LX scans, 68 200 beams
SCALING = (1, 10, 100, 1000)


def interleaved(a: Callable[[], object], b: Callable[[], object], min_cpu_s: float = 1.0,
                min_rounds: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """CPU seconds per call of ``a`` and of ``b``, alternating (after one warm-up each),
    for at least ``min_cpu_s`` of the two together and ``min_rounds`` pairs."""
    a()
    b()
    ta, tb = [], []
    while len(ta) < min_rounds or sum(ta) + sum(tb) < min_cpu_s:
        for fn, out in ((a, ta), (b, tb)):
            t0 = time.process_time()
            fn()
            out.append(time.process_time() - t0)
    return np.array(ta), np.array(tb)


def setup(model: AssemblyModel, n_scans: int, seed: int = 0):
    """The benchmark's ``full`` and ``bare`` callables on ``n_scans`` scans, and the
    number of beams."""
    lidar = model.lidar
    rng = np.random.default_rng(seed)
    ranges = rng.uniform(0.3, 5.0, (n_scans, lidar.n_steps))
    ranges[rng.random(ranges.shape) < 0.03] = np.nan  # error codes
    t_scan = np.arange(n_scans) * lidar.scan_period_s
    batch = ScanBatch.from_arrays(lidar.steps, ranges, t_scan)
    t_nod = np.arange(-0.1, t_scan[-1] + 0.3, 0.004)  # nod servo sampled at 250 Hz
    nod = (t_nod, 0.35 * np.sin(t_nod))
    mirrors = (np.array([-1.0, 1000.0]), np.zeros(2))  # deployed all along
    t_pose = np.arange(-0.1, t_scan[-1] + 0.3, 0.05)
    poses = np.tile(np.eye(4), (len(t_pose), 1, 1))
    poses[:, 0, 3] = 0.5 * t_pose  # driving at 0.5 m/s while turning
    c, s = np.cos(0.2 * t_pose), np.sin(0.2 * t_pose)
    poses[:, 0, 0], poses[:, 0, 1], poses[:, 1, 0], poses[:, 1, 1] = c, -s, s, c
    track = PoseTrack(t_pose, poses)
    r2s = np.eye(4)
    r2s[:3, 3] = (0.2, 0.0, 0.4)

    def full():
        return assemble(model, batch, nod, mirror_left=mirrors, mirror_right=mirrors,
                        frame="world", robot_from_sensor=r2s, world_from_robot=track)

    theta = lidar.bearing_from_step(batch.steps)
    r = batch.ranges_m

    def bare():
        return np.stack([r * np.cos(theta), r * np.sin(theta), np.zeros_like(r)], -1)

    return full, bare, batch.ranges_m.size


# run in a fresh interpreter by jit_first_call(): the first assemble after the imports
_FIRST_CALL = """
import json, sys, time
sys.path.insert(0, {here!r})
import bench_assembly as B
from nodlidar.runtime.assembly import AssemblyModel
from nodlidar.solver import solve
from nodlidar.spec import load_design
import scipy.spatial.transform  # PoseTrack's keyframe table: assembly's import, not numba's
model = AssemblyModel.from_design(solve(load_design(B.DESIGN)))
full, _, _ = B.setup(model, B.N_SCANS)
t0 = time.perf_counter()
import nodlidar.runtime._assembly_kernel
t1 = time.perf_counter()
full()
t2 = time.perf_counter()
full()
t3 = time.perf_counter()
print(json.dumps({{"import": t1 - t0, "first": t2 - t1, "steady": t3 - t2}}))
"""


def jit_first_call(cache_dir: str) -> dict[str, float]:
    """Seconds to import the kernel module, for the first and for a second ``assemble``
    of 100 scans, in a fresh interpreter whose numba cache is ``cache_dir``."""
    env = dict(os.environ, NUMBA_CACHE_DIR=cache_dir)
    code = _FIRST_CALL.format(here=str(Path(__file__).resolve().parent))
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       env=env, timeout=600, check=True)
    return json.loads(p.stdout.strip().splitlines()[-1])


def main() -> dict[str, float]:
    design = solve(load_design(DESIGN))
    model = AssemblyModel.from_design(design)
    full, bare, n_points = setup(model, N_SCANS)
    pc = full()
    t_full, t_bare = interleaved(full, bare, min_cpu_s=3.0)
    ratio = t_bare / t_full  # per adjacent pair: same points, so the points/s ratio
    pps = n_points / np.median(t_full)
    print(f"{N_SCANS} URG-04LX scans = {n_points} beams ({len(pc)} valid points; "
          f"{int((pc.mirror >= 0).sum())} via mirrors); CPU time, interleaved, "
          f"{len(t_full)} pairs, min / median")
    print(f"  bare polar -> xyz             : {t_bare.min() * 1e3:7.2f} / "
          f"{np.median(t_bare) * 1e3:7.2f} ms")
    print(f"  assemble (nod, mirrors, world): {t_full.min() * 1e3:7.2f} / "
          f"{np.median(t_full) * 1e3:7.2f} ms  ({pps / 1e6:.2f} M points/s)")
    print(f"  ratio (assemble / bare)       : {ratio.min():7.3f} / {np.median(ratio):7.3f}")
    out = {"ratio_vs_bare": float(np.median(ratio)), "points_per_s": float(pps)}

    print("scaling (scans per call: points/s of assemble, ratio vs bare, median):")
    for n in SCALING:
        f, b, npts = setup(model, n, seed=n)
        tf, tb = interleaved(f, b, min_cpu_s=1.0 if n < 1000 else 3.0, min_rounds=5)
        rr = float(np.median(tb / tf))
        p = float(npts / np.median(tf))
        print(f"  {n:5d} scans ({npts:7d} beams): {p / 1e6:6.2f} M points/s, ratio {rr:.3f}")
        out[f"ratio_vs_bare_scans{n}"] = rr
        out[f"points_per_s_scans{n}"] = p

    with tempfile.TemporaryDirectory(prefix="numba-cache-") as cache:
        cold = jit_first_call(cache)  # empty cache: compiles, writes the cache
        warm = jit_first_call(cache)  # the next process: loads it
    print("compiled kernel, fresh process each (wall time): import numba + kernel "
          f"{cold['import']:.2f} / {warm['import']:.2f} s; first assemble: cold cache "
          f"{cold['first']:.2f} s, warm cache {warm['first']:.3f} s; a later call "
          f"{warm['steady'] * 1e3:.1f} ms")
    out.update(jit_import_s=warm["import"], jit_compile_cold_s=cold["first"],
               jit_load_warm_s=warm["first"], jit_steady_s=warm["steady"])
    return out  # for benchmarks/run.py


if __name__ == "__main__":
    main()
