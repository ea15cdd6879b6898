"""Monte Carlo tolerance analysis: the fused kernel against today's, memory, Dask's break-even.

``python benchmarks/bench_tolerance.py [--quick]``; under ``benchmarks/run.py tolerance``
``main()`` returns the figures. On a shared, loaded machine only figures measured in one
process and run are comparable, so:

1. **in process, new / v0** (``ratio_vs_v0``, issue 16's ">= 3x today"): the frozen
   baseline ``benchmarks/baselines/tolerance_v0.py`` (the kernel before issue 16) and
   ``monte_carlo(workers=0)`` run the same spec alternately (v0, new, v0, new, ...), timed
   in thread CPU time (both are single-threaded numpy); the ratio is the median of the
   per-pair ratios. ``samples_per_s`` is the new in-process rate (median, CPU time);
   ``wall_samples_per_s`` the same in wall time.
2. **peak RSS in a fresh process** (``peak_rss_mib_1e4`` ... ``_1e6``): a subprocess per
   sample count runs ``monte_carlo(..., keep_samples=False, workers=0)`` (what ``nodlidar
   tolerance`` does) and reports its own ``ru_maxrss``; ``peak_rss_mib_import`` is the same
   process with 0 samples (numpy, nodlidar, the solved design) and
   ``peak_rss_mib_kept_1e5`` keeps every sample (``keep_samples=True``). The paper build,
   one arc (2 m) to keep the 1e6 run short: memory per sample does not depend on the arcs
   for the summary, and is 4 x mirrors x (4 x arcs + 2) bytes when kept.
3. **Dask's break-even**: the start-up of a local cluster of 2 worker processes
   (``dask_startup_s``, until the problem is scattered and tasks submitted) and the rate
   of those 2 workers once running (``dask2_samples_per_s``); ``break_even_samples`` is
   where ``N / in-process rate = start-up + N / Dask rate`` - the measurement behind
   ``tolerance.DASK_MIN_SAMPLES``.
"""

from __future__ import annotations

import json
import math
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

PAPER = ROOT / "design" / "urg04lx-paper.toml"


def _design():
    from nodlidar.solver import solve
    from nodlidar.spec import load_design

    return solve(load_design(PAPER))


def _status_kib(key: str) -> int:
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith(key + ":"))


def rss_child(samples: int, keep: bool) -> None:
    """``--rss N keep|summary``: one run in this fresh process; as JSON its RSS before the
    run and its peak during it (Linux: the high-water mark reset through
    ``/proc/self/clear_refs`` after the imports and the solve, whose own peak would hide
    the run's; elsewhere ``ru_maxrss``) [MiB]."""
    from nodlidar.analysis.tolerance import monte_carlo, tolerance_spec

    design = _design()
    tol = tolerance_spec(design.spec).replace(samples=max(samples, 1), ranges_m=(2.0,))
    try:
        before = _status_kib("VmRSS") / 2**10
        Path("/proc/self/clear_refs").write_text("5")
        def peak() -> float:
            return _status_kib("VmHWM") / 2**10
    except OSError:
        before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**10
        def peak() -> float:
            return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**10
    t0, c0 = time.perf_counter(), time.process_time()
    if samples:
        monte_carlo(design, tol, workers=0, keep_samples=keep)
    print(json.dumps({"rss_before_mib": before, "rss_mib": peak(),
                      "wall_s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0}))


def fresh_rss(samples: int, keep: bool = False) -> dict[str, float]:
    out = subprocess.run([sys.executable, __file__, "--rss", str(samples),
                          "keep" if keep else "summary"], capture_output=True, text=True,
                         check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def interleaved(design, samples: int, reps: int) -> dict[str, float]:
    """v0 and the new in-process Monte Carlo, alternately, on the same spec."""
    from baselines.tolerance_v0 import run_v0

    from nodlidar.analysis.tolerance import monte_carlo, tolerance_spec

    tol = tolerance_spec(design.spec).replace(samples=samples, chunk_size=1000, seed=1)
    ref = run_v0(design, tol)
    new = monte_carlo(design, tol, workers=0)
    # same model: float32 samples equal but for 1-ulp roundings (tests/test_tolerance_regression.py)
    for k, v in ref.items():
        got = getattr(new, k)
        if v.dtype.kind == "f":
            assert np.allclose(got, v, rtol=2e-7, atol=1e-12, equal_nan=True), k
        else:
            assert np.array_equal(got, v), k
    cpu0, cpu1, wall1 = [], [], []
    for _ in range(reps):
        t = time.thread_time()
        run_v0(design, tol)
        cpu0.append(time.thread_time() - t)
        t, w = time.thread_time(), time.perf_counter()
        monte_carlo(design, tol, workers=0)
        cpu1.append(time.thread_time() - t)
        wall1.append(time.perf_counter() - w)
    ratios = [a / b for a, b in zip(cpu0, cpu1, strict=True)]
    print(f"in process, {samples} samples x {reps} (CPU time, min / median): "
          f"v0 {min(cpu0):.2f} / {statistics.median(cpu0):.2f} s, "
          f"new {min(cpu1):.3f} / {statistics.median(cpu1):.3f} s; "
          f"ratio per pair min {min(ratios):.2f}, median {statistics.median(ratios):.2f}")
    return {"samples_per_s": samples / statistics.median(cpu1),
            "wall_samples_per_s": samples / statistics.median(wall1),
            "v0_samples_per_s": samples / statistics.median(cpu0),
            "ratio_vs_v0": statistics.median(ratios), "ratio_vs_v0_min": min(ratios)}


def dask_break_even(design, samples: int, in_process_rate: float) -> dict[str, float]:
    """Start-up and running rate of a local cluster of 2 worker processes."""
    from nodlidar.analysis.tolerance import monte_carlo, tolerance_spec

    tol = tolerance_spec(design.spec).replace(samples=samples, chunk_size=1000, seed=1)
    seen: list[float] = []
    res = monte_carlo(design, tol, workers=2, keep_samples=False,
                      progress=lambda done, total: seen.append(time.perf_counter()))
    # the running rate: from the first chunk back to the last (excludes start-up and close)
    run_rate = (samples - 1000) / (seen[-1] - seen[0]) if len(seen) > 1 else math.nan
    startup = res.startup_s
    # N / r0 = S + N / r2  ->  N = S r0 r2 / (r2 - r0)  (never, if Dask is not faster)
    be = (startup * in_process_rate * run_rate / (run_rate - in_process_rate)
          if run_rate > in_process_rate else math.inf)
    print(f"dask, 2 worker processes: start-up {startup:.2f} s, then {run_rate:.0f} samples/s "
          f"(in process {in_process_rate:.0f}/s wall); whole run {res.wall_s:.2f} s for "
          f"{samples}; break-even {be:.3g} samples")
    return {"dask_startup_s": startup, "dask2_samples_per_s": run_rate,
            "break_even_samples": be if math.isfinite(be) else 1e12}


def main() -> dict[str, float]:
    quick = "--quick" in sys.argv
    design = _design()
    figs = interleaved(design, 2000, 3)
    print("fresh process per count, paper build, one arc (2 m), keep_samples=False; "
          "peak RSS during the run [MiB] (RSS before it: imports, solved design):")
    for exp in (4, 5) if quick else (4, 5, 6):
        r = fresh_rss(10**exp)
        figs[f"peak_rss_mib_1e{exp}"] = r["rss_mib"]
        figs[f"rss_growth_mib_1e{exp}"] = r["rss_mib"] - r["rss_before_mib"]
        print(f"  1e{exp} samples: {r['rss_mib']:.1f} (before {r['rss_before_mib']:.1f}, "
              f"+{r['rss_mib'] - r['rss_before_mib']:.1f}), {r['cpu_s']:.1f} s CPU")
    r = fresh_rss(10**5, keep=True)
    figs["peak_rss_mib_kept_1e5"] = r["rss_mib"]
    figs["rss_growth_mib_kept_1e5"] = r["rss_mib"] - r["rss_before_mib"]
    print(f"  1e5 samples, every sample kept: {r['rss_mib']:.1f} "
          f"(+{r['rss_mib'] - r['rss_before_mib']:.1f})")
    figs.update(dask_break_even(design, 10_000, figs["wall_samples_per_s"]))
    return figs


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--rss":
        rss_child(int(sys.argv[2]), sys.argv[3] == "keep")
    else:
        print(json.dumps(main(), indent=1))
