"""The online tracking (segmentation + tracker) of this tree against another revision's, in
one process, interleaved scan by scan: the ratio of their update times measured in the same
run, and whether every scan's output is the same.

Why: on a shared machine, separate runs of the same code differ by 10 % or more in their
median update time (``bench_tracking.py`` gave 8.3 to 9.0 ms for one tree in one
session), so a change worth 10 % cannot be seen by running the two trees one after the
other. Here both pipelines see each scan back to back (the order alternating), so the
machine's slow spells fall on both.

The other revision's ``nodlidar`` package is taken from git (``git archive``) into a
temporary folder as ``nodlidar_base``; its tracking modules import their siblings
relatively, so its segmentation and tracker are entirely that revision's. The scans are
simulated once, by this tree.

Run::

    .venv/bin/python benchmarks/ab_tracking.py [--base REV] [--scene NAME] [--scans N]
        [--entropy renyi|voxel] [--lifted] [--seed S] [--json]

``--scene`` is a file of ``design/scenes`` without ``.toml`` or ``paper`` (the default:
the paper's scenario); the statistics skip the first 60 scans (the paper's: the 40-scan
window full, as ``bench_tracking.py``) or 10 (a scene: from the first sightings on).
Exit status 1 when an output differs (a change meant to keep outputs identical did not).
"""

from __future__ import annotations

import argparse
import importlib
import io
import json
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def base_package(rev: str, into: Path) -> str:
    """Extract revision ``rev``'s ``nodlidar`` as ``into/nodlidar_base``; its name."""
    tar = subprocess.run(["git", "-C", str(ROOT), "archive", "--format=tar", rev, "nodlidar"],
                         capture_output=True, check=False)
    if tar.returncode:
        raise SystemExit(f"error: --base {rev!r}: git archive failed: "
                         f"{tar.stderr.decode().strip()}")
    with tarfile.open(fileobj=io.BytesIO(tar.stdout)) as t:
        t.extractall(into, filter="data")
    (into / "nodlidar").rename(into / "nodlidar_base")
    sys.path.insert(0, str(into))
    return "nodlidar_base"


def _state_key(states) -> list:
    """A scan's output, comparable exactly: every float by its repr (the shortest string
    that reads back to the same bits; NaN equals NaN, as it does not as a float)."""
    return [(s.track_id, s.scan, *(repr(float(x)) for x in (s.t_s, s.x_m, s.y_m, s.v_m_s,
                                                            s.heading_rad)),
             tuple(repr(x) for x in np.asarray(s.cov, float).ravel().tolist()),
             s.n_scans, s.n_points, s.confirmed, s.alive) for s in states]


def run(args: argparse.Namespace) -> dict:
    from nodlidar.solver import solve
    from nodlidar.spec import load_design
    from nodlidar.tracking.simdata import simulate_scans

    design = solve(load_design(ROOT / "design" / "urg04lx-paper.toml"))
    scene = None if args.scene == "paper" else ROOT / "design" / "scenes" / f"{args.scene}.toml"
    if scene is not None and not scene.is_file():
        raise SystemExit(f"error: --scene {args.scene!r}: no {scene.relative_to(ROOT)}")
    skip = 60 if scene is None else 10
    if args.scans <= skip:
        raise SystemExit(f"error: --scans {args.scans}: need more than {skip} (the statistics "
                         f"skip the first {skip})")
    with tempfile.TemporaryDirectory() as tmp:
        name = base_package(args.base, Path(tmp))
        scans = simulate_scans(design, args.scans, mirrors_deployed=not args.lifted,
                               seed=args.seed, scene=scene)
        pipes = {}
        for label, pkg in (("base", name), ("new", "nodlidar")):
            seg_mod = importlib.import_module(f"{pkg}.tracking.segment")
            trk_mod = importlib.import_module(f"{pkg}.tracking.tracker")
            kernel = importlib.import_module(f"{pkg}.tracking._kernel")
            getattr(kernel, "warm_up", lambda: None)()  # compile now, not in the timing
            pipes[label] = (
                seg_mod.OnlineSegmenter(seg_mod.SegmentConfig(), design.lidar.range_sigma_m),
                trk_mod.Tracker(trk_mod.TrackerConfig(entropy=args.entropy),
                                range_sigma=design.lidar.range_sigma_m))
        cpu: dict[str, list[float]] = {"base": [], "new": []}
        out: dict[str, list] = {"base": [], "new": []}
        for k, scan in enumerate(scans):
            for label in (("base", "new") if k % 2 == 0 else ("new", "base")):
                seg, trk = pipes[label]
                c0 = time.process_time()
                states = trk.update(seg.update(scan))
                cpu[label].append(time.process_time() - c0)
                out[label].append(_state_key(states))
    b, n = (np.array(cpu[x][skip:]) * 1e3 for x in ("base", "new"))
    differ = [k for k, (x, y) in enumerate(zip(out["base"], out["new"])) if x != y]
    return {"base": args.base, "scene": args.scene, "entropy": args.entropy,
            "mirrors": not args.lifted, "seed": args.seed, "scans_timed": len(b),
            "base_median_ms": float(np.median(b)), "new_median_ms": float(np.median(n)),
            "base_max_ms": float(b.max()), "new_max_ms": float(n.max()),
            "median_ratio": float(np.median(n) / np.median(b)),
            "mean_ratio": float(n.mean() / b.mean()),
            "per_scan_ratio_median": float(np.median(n / b)),
            "outputs_identical": not differ, "first_differing_scan": differ[0] if differ else None}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--base", default="HEAD", help="git revision to compare with (HEAD)")
    ap.add_argument("--scene", default="paper", help="design/scenes/NAME.toml, or paper")
    ap.add_argument("--scans", type=int, default=300)
    ap.add_argument("--entropy", choices=("renyi", "voxel"), default="renyi")
    ap.add_argument("--lifted", action="store_true", help="mirrors lifted (default: deployed)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", action="store_true", help="print the figures as JSON")
    args = ap.parse_args(argv)
    r = run(args)
    if args.json:
        print(json.dumps(r))
    else:
        print(f"{r['scene']} ({r['entropy']}, {'mirrors' if r['mirrors'] else 'lifted'}), "
              f"{r['scans_timed']} scans timed, CPU per update:")
        print(f"  base {r['base']}: median {r['base_median_ms']:6.2f} ms, "
              f"max {r['base_max_ms']:6.2f} ms")
        print(f"  this tree: median {r['new_median_ms']:6.2f} ms, max {r['new_max_ms']:6.2f} ms")
        print(f"  ratio this / base: medians {r['median_ratio']:.3f}, means "
              f"{r['mean_ratio']:.3f}, per scan (median) {r['per_scan_ratio_median']:.3f}")
        print("  outputs: identical at every scan" if r["outputs_identical"] else
              f"  outputs DIFFER, first at scan {r['first_differing_scan']}")
    return 0 if r["outputs_identical"] else 1


if __name__ == "__main__":
    sys.exit(main())
