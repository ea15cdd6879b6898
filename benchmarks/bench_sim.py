"""Simulated full scans per second, and the simulator's overhead over a bare embree cast.

Scene: the built-in ``room`` (walls, floor, ceiling, three boxes, one moving cylinder);
design: the paper's URG-04LX build, mirrors deployed; each scan is all 682 beams with their
own times, a nod angle per beam (a ramp), mirror reflections, the static world cast and the
mover cast at per-beam times, noise and mm rounding (:meth:`SceneSimulator.scan`).

Baselines measured in the same run:

* real time: the URG-04LX makes 10 scans/s, so ``scans/s / 10`` is the speed-up over real
  time (issue 5 asks for >= 20x);
* a bare ``RayMeshIntersector.intersects_first`` of the same number of rays (682, the
  sensor's world rays of one scan) against the same static scene mesh: the ratio of rays/s
  says what the mirrors, per-beam time, the mover cast, the float64 distances and the noise
  cost on top of embree.

With the mirrors still (the usual case) the head-frame mirror paths are cached between
scans; the second figure is a scan whose mirrors move (a per-beam lift state, here a
lift in progress of 1e-4 of the lift angle: the same geometry to 1e-5 rad), which casts
every beam at the four mirror meshes again (two bounces) - the worst case.

Scaling: the same scan and bare cast in the room with 0..400 extra poles (more scene
triangles), printed as a curve and returned as ``sim.ratio_vs_embree_tris<N>``.

Timing: CPU time of this thread (the simulator and embree run on one thread; on a shared,
loaded machine wall time mostly measures the others), the sides interleaved (A, B, A,
B, ...: a load change hits both) and each ratio the median over rounds of the per-round
ratios.

Compiled kernels (``nodlidar/sim/_kernel.py``, numba ``cache=True``): ``jit_compile_cold_s``
is the first simulated scan (mirrors moving, so every kernel a scan uses is compiled) in a
fresh process with an empty ``NUMBA_CACHE_DIR``, less a second scan's time; ``jit_load_warm_s``
the same in a second fresh process whose cache the first filled.

Run: ``.venv/bin/python benchmarks/bench_sim.py`` or under ``benchmarks/run.py sim``
(figures ``sim.ratio_vs_embree``, ``sim.scans_per_s``, ...).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from nodlidar.sim.raycast import SceneSimulator
from nodlidar.sim.scene import Pole, room_scene
from nodlidar.solver import solve
from nodlidar.spec import load_design

PAPER = Path(__file__).resolve().parents[1] / "design" / "urg04lx-paper.toml"


def rates(fns: dict, min_time: float = 1.0, rounds: int = 7) -> tuple[dict, dict]:
    """Calls per CPU second of each of ``fns`` (name -> callable), measured interleaved:
    ``rounds`` rounds, each running every function in turn for ``min_time / rounds`` [s]
    of this thread's CPU time (after one warm-up call each). Returns ``(median rate per
    name, per-round rates per name)``."""
    for fn in fns.values():
        fn()
    per: dict[str, list[float]] = {k: [] for k in fns}
    for _ in range(rounds):
        for k, fn in fns.items():
            n, t0 = 0, time.thread_time()
            while True:
                for _ in range(5):
                    fn()
                n += 5
                dt = time.thread_time() - t0
                if dt >= min_time / rounds:
                    per[k].append(n / dt)
                    break
    return {k: float(np.median(v)) for k, v in per.items()}, per


def ratio(per: dict, a: str, b: str) -> float:
    """Median over rounds of rate a / rate b (the two measured in the same round)."""
    return float(np.median(np.asarray(per[a]) / np.asarray(per[b])))


_JIT_CHILD = """
import json, time
import numpy as np
from nodlidar.sim.raycast import SceneSimulator
from nodlidar.solver import solve
from nodlidar.spec import load_design
sim = SceneSimulator(solve(load_design({paper!r})), "room")
n = sim.lidar.n_steps
nod, lift = np.linspace(-0.35, 0.35, n), np.linspace(0.0, 1e-4, n)
t = []
for k in range(2):
    t0 = time.perf_counter()
    sim.scan(0.1 * k, nod, lift, lift, noise=True, seed=k)
    t.append(time.perf_counter() - t0)
print(json.dumps(t))
"""


def jit_times() -> tuple[float, float]:
    """(first-scan overhead with an empty numba cache, with the cache it filled) [s], each
    in a fresh process: first scan's wall time less the second's."""
    import json
    import os
    import subprocess
    import sys
    import tempfile

    out = []
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache)
        for _ in range(2):
            r = subprocess.run([sys.executable, "-c", _JIT_CHILD.format(paper=str(PAPER))],
                               env=env, capture_output=True, text=True, check=True)
            first, second = json.loads(r.stdout.strip().splitlines()[-1])
            out.append(first - second)
    return out[0], out[1]


def with_poles(k: int):
    """The room with ``k`` extra poles on a grid (more static triangles)."""
    import dataclasses

    room = room_scene()
    side = int(np.ceil(np.sqrt(k))) if k else 0
    poles = [Pole((-3.0 + 6.0 * (i % side) / side, -2.0 + 4.0 * (i // side) / side), 0.03, 1.0,
                  name=f"pole{i}") for i in range(k)]
    return dataclasses.replace(room, statics=room.statics + tuple(poles))


def ratio_in(design, scene, nod, min_time: float) -> tuple[int, float, float, float]:
    """(static triangles, scans/s, bare embree casts/s, median per-round ratio) of one scene."""
    sim = SceneSimulator(design, scene)
    lid = design.lidar
    s0 = sim.scan(0.0, nod, noise=False)
    o_h, d_h, *_ = sim.head_rays(lid.steps)
    o_w, d_w = sim.to_world(o_h, d_h, nod, s0.t_s)
    bare = sim._static.intersector
    k = [0]

    def one_scan() -> None:
        k[0] += 1
        sim.scan(k[0] * lid.scan_period_s, nod, noise=True, seed=k[0])

    med, per = rates({"scan": one_scan, "bare": lambda: bare.intersects_first(o_w, d_w)},
                     min_time)
    return len(sim._static.mesh.faces), med["scan"], med["bare"], ratio(per, "scan", "bare")


def main() -> dict[str, float]:
    design = solve(load_design(PAPER))
    sim = SceneSimulator(design, "room")
    lid = design.lidar
    n = lid.n_steps
    nod = np.linspace(-0.35, 0.35, n)  # a nod ramp across the scan
    k = [0]

    def one_scan() -> None:
        t = k[0] * lid.scan_period_s
        k[0] += 1
        s = sim.scan(t, nod, noise=True, seed=k[0])
        assert s.range_m.shape == (n,)

    # the same world rays as one simulated scan, cast bare against the static mesh
    s0 = sim.scan(0.0, nod, noise=False)
    o_h, d_h, *_ = sim.head_rays(lid.steps)
    o_w, d_w = sim.to_world(o_h, d_h, nod, s0.t_s)
    bare = sim._static.intersector  # the same RayMeshIntersector the simulator uses

    def bare_cast() -> None:
        bare.intersects_first(o_w, d_w)

    lifting = np.linspace(0.0, 1e-4, n)  # per-beam lift fractions: no cache

    def one_scan_mirrors_moving() -> None:
        t = k[0] * lid.scan_period_s
        k[0] += 1
        s = sim.scan(t, nod, lifting, lifting, noise=True, seed=k[0])
        assert s.range_m.shape == (n,)

    def ten_scans() -> None:  # SceneSimulator.scans: ten scans' rays in one cast per mesh
        k[0] += 10
        sim.scans(10, t0_s=k[0] * lid.scan_period_s, nod=lambda t: nod, seed=k[0])

    hits = np.isfinite(s0.true_range_m).mean()
    reflected = (s0.mirror >= 0).mean()
    med, per = rates({"scan": one_scan, "bare": bare_cast, "moving": one_scan_mirrors_moving,
                      "batch10": ten_scans}, min_time=4.0)
    r_sim, r_moving, r_bare = med["scan"], med["moving"], med["bare"]
    r_batch = 10 * med["batch10"]
    real = 1.0 / lid.scan_period_s
    cold, warm = jit_times()
    print(f"room scene ({len(sim.part_names)} static parts, {len(sim.scene.movers)} mover), "
          f"{n} beams/scan, {reflected:.0%} reflected, {hits:.0%} returns")
    print(f"  simulated full scans        : {r_sim:10.0f} scans/s  "
          f"({r_sim / real:6.1f}x real time at {real:g} scans/s; need >= 20x)")
    print(f"  ... mirrors moving (uncached): {r_moving:10.0f} scans/s  "
          f"({r_moving / real:6.1f}x real time)")
    print(f"  full pipeline               : {r_sim * n:10.0f} rays/s")
    print(f"  bare embree intersects_first: {r_bare * n:10.0f} rays/s (same {n} rays, static mesh)")
    print(f"  ratio pipeline / bare embree: {ratio(per, 'scan', 'bare'):10.2f}  (goal >= 0.5)")
    print(f"  scans(10), batched casts    : {r_batch:10.0f} scans/s  "
          f"(ratio to bare embree {10 * ratio(per, 'batch10', 'bare'):.2f})")
    print(f"  kernels' first scan         : {cold:10.2f} s compiling (empty cache), "
          f"{warm:.2f} s loading (warm cache)")
    figures = {"ratio_vs_embree": ratio(per, "scan", "bare"), "scans_per_s": r_sim,
               "realtime_x": r_sim / real, "moving_scans_per_s": r_moving,
               "ratio_moving_vs_embree": ratio(per, "moving", "bare"),
               "batch10_ratio_vs_embree": 10 * ratio(per, "batch10", "bare"),
               "jit_compile_cold_s": cold, "jit_load_warm_s": warm}
    print("  scaling with scene triangles (room + poles):")
    print(f"  {'triangles':>10} {'scans/s':>10} {'bare casts/s':>13} {'ratio':>7}")
    for poles in (0, 25, 100, 400):
        tris, rs, rb, rr = ratio_in(design, with_poles(poles), nod, 1.0)
        print(f"  {tris:10d} {rs:10.0f} {rb:13.0f} {rr:7.2f}")
        figures[f"ratio_vs_embree_tris{tris}"] = rr
    return figures


if __name__ == "__main__":
    main()
