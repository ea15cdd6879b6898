"""Monte Carlo tolerance analysis: samples/s in process, on a local Dask cluster of 1 and
of 2 worker processes (ratio 2 vs 1), and peak memory (psutil, this process + workers).

``python benchmarks/bench_tolerance.py [samples]`` (default 40 000; chunks of 1000).
Ratios are the stable numbers on shared machines; absolute rates are printed too.
"""

from __future__ import annotations

import sys
import threading
import time
from pathlib import Path

import numpy as np
import psutil

from nodlidar.analysis.tolerance import monte_carlo
from nodlidar.solver import solve
from nodlidar.spec import load_design

ROOT = Path(__file__).resolve().parents[1]


class PeakRSS:
    """Samples the summed RSS of this process and its children every 20 ms."""

    def __init__(self) -> None:
        self.peak = 0
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._run, daemon=True)

    def _rss(self) -> int:
        me = psutil.Process()
        total = me.memory_info().rss
        for c in me.children(recursive=True):
            try:
                total += c.memory_info().rss
            except psutil.Error:
                pass
        return total

    def _run(self) -> None:
        while not self._stop.is_set():
            self.peak = max(self.peak, self._rss())
            time.sleep(0.02)

    def __enter__(self):
        self._t.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._t.join()


def run(design, samples: int, **kw):
    with PeakRSS() as mem:
        t0 = time.perf_counter()
        res = monte_carlo(design, samples=samples, chunk_size=1000, seed=1, **kw)
        dt = time.perf_counter() - t0
    return res, samples / dt, dt, mem.peak


def main() -> dict[str, float]:
    # numeric arguments only: under ``benchmarks/run.py tolerance`` argv holds benchmark names
    counts = [a for a in sys.argv[1:] if a.isdigit()]
    samples = int(counts[0]) if counts else 40_000
    design = solve(load_design(ROOT / "design" / "urg04lx-paper.toml"))
    beams = sum(len(m.steps) for m in design.mirrors)
    print(f"{samples} samples x {beams} reflected beams x 4 ranges, chunks of 1000; "
          f"{psutil.cpu_count()} CPUs")
    base_rss = psutil.Process().memory_info().rss
    ref, rate0, dt0, peak0 = run(design, samples, workers=0)
    print(f"in process      : {rate0:9.0f} samples/s ({dt0:5.2f} s), peak RSS {peak0 / 2**20:7.1f} MiB "
          f"(+{(peak0 - base_rss) / 2**20:.1f})")
    rates = {}
    for n in (1, 2):
        res, rate, dt, peak = run(design, samples, workers=n)
        same = all(np.array_equal(getattr(ref, k), getattr(res, k))
                   for k in ("bearing_error_max", "range_error_max", "elevation_max", "edge_misses"))
        rates[n] = rate
        print(f"dask {n} worker(s): {rate:9.0f} samples/s ({dt:5.2f} s incl. cluster start-up), "
              f"peak RSS incl. workers {peak / 2**20:7.1f} MiB; identical to in-process: {same}")
    print(f"ratio 2 workers / 1 worker: {rates[2] / rates[1]:.2f}x")
    per_sample = sum(a.nbytes for a in (ref.bearing_error_max, ref.bearing_error_mean,
                                        ref.range_error_max, ref.height_max, ref.elevation_max,
                                        ref.edge_misses)) / samples
    print(f"result storage: {per_sample:.0f} bytes per sample "
          f"({per_sample * 1e6 / 2**20:.0f} MiB for 10^6 samples)")
    return {"samples_per_s": rate0, "ratio_dask2_vs_dask1": rates[2] / rates[1],  # run.py
            "in_process_peak_rss_mib": peak0 / 2**20}


if __name__ == "__main__":
    main()
