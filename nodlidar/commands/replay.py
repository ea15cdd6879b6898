"""``nodlidar replay BAG``: assemble a recording through the same pipeline as live.

Reads MCAP and sqlite3 bags, old (no PointCloud2, session-clock stamps) and new.
Rebuilds the design (and calibration) stored in the bag, decodes the raw SCIP frames and
the servo samples, and writes the cloud. A bag whose recording was killed is read through
a repaired temporary copy (the bag itself is never written). Messages that cannot be
decoded are skipped and counted: a warning and exit 0, or exit 2 with ``--strict``.
"""

from __future__ import annotations

import argparse
import json
import sys

from ..errors import DesignFileError
from ._args import add_force_arg
from ._runtime_args import add_frame_args, check_out, frame_kwargs


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("replay", help="assemble a recorded bag into a point cloud",
                       description=__doc__)
    p.add_argument("bag", help="bag directory written by 'nodlidar record'")
    p.add_argument("--out", default=None, metavar="FILE", help="write the cloud (.ply/.pcd)")
    p.add_argument("--ascii", action="store_true", help="ASCII instead of binary file")
    p.add_argument("--strict", action="store_true",
                   help="fail (exit 2) if any message in the bag cannot be decoded")
    p.add_argument("--json", action="store_true",
                   help="print a JSON summary (bag, storage, scans, points, skipped...)")
    add_force_arg(p)
    add_frame_args(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..runtime.bag import replay_bag
    from ..runtime.cloud import write_cloud

    if args.out:
        check_out(args.out, force=args.force)
    contents, cloud = replay_bag(args.bag, **frame_kwargs(args))
    n_skipped = sum(contents.skipped.values())
    detail = ", ".join(f"{k}: {v}" for k, v in sorted(contents.skipped.items()))
    if n_skipped and args.strict:
        raise DesignFileError(f"{args.bag}: {n_skipped} messages cannot be decoded ({detail}); "
                              "without --strict they are skipped")
    if n_skipped:
        print(f"nodlidar replay: warning: skipped {n_skipped} undecodable messages ({detail})",
              file=sys.stderr)
    n_samples = sum(len(t) for t, _ in contents.joints.values())
    written = write_cloud(args.out, cloud, binary=not args.ascii) if args.out else None
    if args.json:
        print(json.dumps({
            "bag": str(args.bag), "storage": contents.storage,
            "format": int(contents.header.get("format", 1)), "recovered": contents.recovered,
            "scans": len(contents.scans), "servo_samples": n_samples,
            "laser_scans": contents.laser_scans, "point_clouds": contents.clouds,
            "skipped": dict(contents.skipped), "skipped_total": n_skipped,
            "points": len(cloud), "design": cloud.design_name, "design_hash": cloud.design_hash,
            "calibration": cloud.calibration_id, "frame": cloud.frame,
            "assembly": {k: int(v) for k, v in cloud.meta.items()},
            "out": str(written) if written else None}, indent=2))
        return 0
    if contents.recovered:
        print(f"{args.bag}: recording had not been closed; read through a repaired temporary "
              "copy (the bag is unchanged)")
    print(f"{len(contents.scans)} scans, {n_samples} servo "
          f"samples -> {len(cloud)} points (design {cloud.design_name}, calibration "
          f"{cloud.calibration_id}, frame {cloud.frame})")
    if written:
        print(f"wrote {written}")
    return 0
