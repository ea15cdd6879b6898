"""``nodlidar track [RECORDING | --sim]``: detect and track moving objects, scan by scan.

With ``--sim`` (the default when no recording is given) the scans come from the built-in
simulated sensor (direct API, no emulators), scene ``paper-tracking`` unless ``--scene``
says otherwise. Each scan is segmented online (voxel inconsistency with the evidence so
far), clustered, associated to tracks; every track update is printed (``--json``: one JSON
object per line). A recording (``nodlidar record``) is read with
:func:`nodlidar.tracking.recording.scans_from_recording` (its own design and calibration).
"""

from __future__ import annotations

import json
import math
import sys


def register(sub) -> None:
    p = sub.add_parser("track", help="detect and track moving objects (recording or simulator)",
                       description=__doc__)
    p.add_argument("recording", nargs="?", help="recording made by nodlidar record (a bag folder)")
    p.add_argument("--sim", action="store_true", help="use the built-in simulated sensor")
    p.add_argument("--design", default="design/urg04lx-paper.toml", help="design TOML")
    p.add_argument("--scene", default="paper-tracking", help="simulator scene (name or TOML)")
    p.add_argument("--scans", type=int, default=60, help="number of simulated scans (default 60)")
    p.add_argument("--lifted", action="store_true", help="simulate with the mirrors lifted")
    p.add_argument("--entropy", choices=("renyi", "voxel"), default="renyi")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", action="store_true", help="one JSON line per track update")
    p.set_defaults(func=run)


def _scans(args, design):
    from ..errors import require

    if args.recording and not args.sim:
        from ..tracking.recording import scans_from_recording

        _, scans = scans_from_recording(args.recording)
        print(f"recording {args.recording}: {len(scans)} scans", file=sys.stderr)
        return scans
    require(args.scans >= 1, "--scans", args.scans, ">= 1")
    from ..tracking.simdata import simulate_scans

    return simulate_scans(design, args.scans, mirrors_deployed=not args.lifted, scene=args.scene,
                          seed=args.seed)


def run(args) -> int:
    from ..solver import solve
    from ..spec import load_design
    from ..tracking.segment import OnlineSegmenter
    from ..tracking.tracker import Tracker, TrackerConfig

    design = solve(load_design(args.design))
    seg = OnlineSegmenter(range_sigma=design.lidar.range_sigma_m)
    trk = Tracker(TrackerConfig(entropy=args.entropy))
    for scan in _scans(args, design):
        for st in trk.update(seg.update(scan)):
            if args.json:
                print(json.dumps(st.to_dict()), flush=True)
            elif st.confirmed or not st.alive:
                v = "   -  " if math.isnan(st.v_m_s) else f"{st.v_m_s:6.3f}"
                h = "   -   " if math.isnan(st.heading_rad) else f"{math.degrees(st.heading_rad):7.2f}"
                sd = math.sqrt(max(st.cov[2, 2], 0.0))
                print(f"scan {st.scan:4d} track {st.track_id:3d} "
                      f"{'alive' if st.alive else 'ended'}  x {st.x_m:6.3f} y {st.y_m:6.3f} m  "
                      f"v {v} m/s (sd {sd:.3f})  heading {h} deg  "
                      f"[{st.n_scans} scans, {st.n_points} pts]", flush=True)
    sys.stdout.flush()
    return 0
