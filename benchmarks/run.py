"""Run the benchmarks (``benchmarks/bench_*.py``), each in a fresh process: ``make bench``.

Usage::

    python benchmarks/run.py [--json FILE] [--repeat N] [names...]

Every benchmark runs in its own subprocess of this interpreter (the venv's python), so
one benchmark's imports (cadquery, dask, ...) and allocations do not count against the
next: peak RSS is the child's own ``ru_maxrss``. A benchmark's ``main()`` may return a
dict of named figures (ratios against a baseline measured in the same run, because
absolute times drift on shared machines); they are recorded as ``<name>.<figure>``, e.g.
``sim.ratio_vs_embree``, next to ``<name>.peak_rss_mib`` and ``<name>.wall_s``.

``--repeat N`` runs the whole set N times (one fresh process per benchmark and run) and
reports the min and median of every figure; ``--json FILE`` writes them (with every run's
value) to FILE. Names select a subset: ``python benchmarks/run.py sim scip``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import runpy
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent

# the goals of issues 16 and 13 (figure -> (comparison, bound)); printed next to the results
GOALS = {
    "assembly.ratio_vs_bare": (">=", 0.33),
    "scip.ratio_vs_hokuyolx": (">=", 50.0),
    "sim.ratio_vs_embree": (">=", 0.5),
    "cli.help_s": ("<=", 0.25),
    "cli.design_s": ("<=", 0.6),
    "cad.export_s": ("<=", 3.0),
    "tolerance.ratio_vs_v0": (">=", 3.0),   # samples/s vs the frozen pre-issue-16 kernel
    # issue 13: update (segmentation + tracker) per scan over the scan period, steady state
    "tracking.renyi_update_cpu_median_over_period": ("<=", 0.10),
    "tracking.renyi_update_cpu_max_over_period": ("<=", 0.20),
    "tracking.voxel_update_cpu_median_over_period": ("<=", 0.10),
    "tracking.voxel_update_cpu_max_over_period": ("<=", 0.20),
    # and a window map merge flat from 30 k to 3 M explored voxels (1.5: no growth beyond
    # the noise of a 0.5 ms figure)
    "tracking.window_merge_3M_over_30k": ("<=", 1.5),
}


def available(where: Path = HERE) -> list[str]:
    return [p.stem.removeprefix("bench_") for p in sorted(where.glob("bench_*.py"))]


def child(name: str, out: str, where: Path = HERE) -> None:
    """Run one benchmark in this (fresh) process and write its figures to ``out``."""
    sys.path.insert(0, str(where))
    t0 = time.perf_counter()
    module = runpy.run_path(str(where / f"bench_{name}.py"), run_name=f"bench_{name}")
    figures = module["main"]() or {}
    wall = time.perf_counter() - t0
    # ru_maxrss is in KiB on Linux (bytes on macOS)
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    rss_mib = rss / 2**20 if sys.platform == "darwin" else rss / 2**10
    res = {f"{name}.{k}": float(v) for k, v in figures.items()}
    res[f"{name}.peak_rss_mib"] = rss_mib
    res[f"{name}.wall_s"] = wall
    Path(out).write_text(json.dumps(res))


def run_one(name: str, where: Path = HERE) -> dict[str, float]:
    """One benchmark in a fresh subprocess; its stdout/stderr pass through."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "result.json"
        env = dict(os.environ, MPLBACKEND=os.environ.get("MPLBACKEND", "Agg"))
        proc = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--child", name,
                               str(out), str(where)], env=env)
        if proc.returncode != 0 or not out.exists():
            print(f"benchmark {name} failed (exit {proc.returncode})", file=sys.stderr)
            return {f"{name}.failed": 1.0}
        return json.loads(out.read_text())


def summarise(runs: list[dict[str, float]]) -> dict[str, dict]:
    keys = sorted({k for r in runs for k in r})
    out = {}
    for k in keys:
        vals = [r[k] for r in runs if k in r]
        out[k] = {"min": min(vals), "median": statistics.median(vals), "runs": vals}
        if k in GOALS:
            op, bound = GOALS[k]
            # the goal is judged on the median of the runs
            med = out[k]["median"]
            out[k]["goal"] = f"{op} {bound:g}"
            out[k]["goal_met"] = bool(med >= bound if op == ">=" else med <= bound)
    return out


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["--child"]:
        child(argv[1], argv[2], Path(argv[3]))
        return 0
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("names", nargs="*", help=f"benchmarks to run (default all: {available()})")
    ap.add_argument("--json", metavar="FILE", help="write min/median/runs of every figure")
    ap.add_argument("--repeat", type=int, default=1, metavar="N", help="runs of the set (>= 1)")
    ap.add_argument("--dir", type=Path, default=HERE, help=argparse.SUPPRESS)  # tests
    args = ap.parse_args(argv)
    names = args.names or available(args.dir)
    unknown = [n for n in names if n not in available(args.dir)]
    if unknown or args.repeat < 1:
        print(f"run.py: unknown benchmark(s) {unknown}; choose from {available(args.dir)}"
              if unknown else f"run.py: --repeat {args.repeat}: must be >= 1", file=sys.stderr)
        return 2
    runs: list[dict[str, float]] = []
    for i in range(args.repeat):
        res: dict[str, float] = {}
        for name in names:
            print(f"=== {name} (run {i + 1}/{args.repeat}) ===", flush=True)
            res.update(run_one(name, args.dir))
        runs.append(res)
    summary = summarise(runs)
    print(f"\n=== summary: {args.repeat} run(s), min / median ===")
    for k, s in summary.items():
        goal = f"  goal {s['goal']}: {'met' if s['goal_met'] else 'NOT met'}" if "goal" in s else ""
        print(f"{k:36s} {s['min']:12.4g} {s['median']:12.4g}{goal}")
    if args.json:
        path = Path(args.json)
        path.parent.mkdir(parents=True, exist_ok=True)
        meta = {"repeat": args.repeat, "python": sys.version.split()[0],
                "machine": platform.machine(), "cpus": os.cpu_count(),
                "date_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
        path.write_text(json.dumps({"meta": meta, "figures": summary}, indent=1) + "\n")
    return 1 if any(k.endswith(".failed") for k in summary) else 0


if __name__ == "__main__":
    sys.exit(main())
