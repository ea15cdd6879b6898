"""``nodlidar scan``: one full nod sweep (lower to upper pitch limit) -> a point cloud file.

Nods the head with the design's ``[nod]`` ramp, streams scans, samples the servos, and
assembles every beam with its own time and nod angle (mirrors deployed, or lifted with
``--lift``). Without ``--port``/``--servo-port`` it uses the built-in simulated sensor.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from ._args import add_force_arg, check_output_path
from ._runtime_args import add_device_args, add_frame_args, check_out, frame_kwargs, session_from_args


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("scan", help="one full nod sweep -> PLY/PCD point cloud", description=__doc__)
    add_device_args(p)
    add_frame_args(p)
    p.add_argument("--out", default="scan.ply", metavar="FILE",
                   help="output .ply or .pcd (default scan.ply)")
    p.add_argument("--ascii", action="store_true", help="ASCII instead of binary file")
    p.add_argument("--lift", action="store_true", help="lift the mirrors (direct beams only)")
    p.add_argument("--json", action="store_true",
                   help="print one JSON object (points, scans, nod range, frame, file, ...)")
    add_force_arg(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..runtime.cloud import write_cloud

    check_out(args.out)
    check_output_path(args.out, force=args.force)   # before the sweep, not after it
    kw = frame_kwargs(args)
    with session_from_args(args) as s:
        cap = s.sweep(lift=args.lift)
        assert s.model is not None  # set by Session.open (the with statement)
        cloud = cap.assemble(s.model, **kw)
    path = write_cloud(args.out, cloud, binary=not args.ascii)
    m = cloud.meta
    nod = s.nod_profile()
    dropped = {k: int(m[k]) for k in ("error_codes", "no_nod", "mirror_moving", "blocked") if m.get(k)}
    if args.json:
        print(json.dumps({
            "path": str(path), "format": Path(path).suffix.lstrip(".").lower(),
            "binary": not args.ascii, "points": len(cloud), "scans": len(cap.scans),
            "nod_lower_rad": nod.lower_rad, "nod_upper_rad": nod.upper_rad,
            "mirrors": "lifted" if args.lift else "deployed", "frame": cloud.frame,
            "design": cloud.design_name, "design_hash": cloud.design_hash,
            "calibration_id": cloud.calibration_id, "simulated": args.port is None,
            "reflected_points": int((cloud.mirror >= 0).sum()), "dropped": dropped}, indent=2))
        return 0
    dropped_txt = ", ".join(f"{k.replace('_', ' ')} {v}" for k, v in dropped.items())
    print(f"{len(cloud)} points from {len(cap.scans)} scans (nod {nod.lower_rad:+.3f}.."
          f"{nod.upper_rad:+.3f} rad, mirrors {'lifted' if args.lift else 'deployed'}, "
          f"frame {cloud.frame}, calibration {cloud.calibration_id})"
          + (f"; dropped: {dropped_txt}" if dropped_txt else ""))
    print(f"wrote {path}")
    return 0
