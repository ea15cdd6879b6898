"""``nodlidar record --out DIR``: record a nodding capture to a ROS 2 bag (MCAP by default,
``--storage sqlite3`` for the older format).

Topics: the raw SCIP frames, sensor_msgs/LaserScan (frame ``laser``), a PointCloud2 of each
scan's assembled points (frame ``nodlidar_base``), /tf (the nod joint at every nod sample,
the mirror joints at every lift sample), /tf_static, a latched /robot_description (URDF of
the head), sensor_msgs/JointState (servo samples) and the latched design/calibration (so
``nodlidar replay`` rebuilds the same BeamModels). Stamps are epoch time. Every scan is
committed as it arrives: a recording killed (even with SIGKILL) keeps every scan before
the one in flight; ``nodlidar replay`` reads such a bag (through a repaired copy). A write
error (disk full) is one line and exit 1; the scans committed before are kept.
"""

from __future__ import annotations

import argparse
import json

from ..errors import ParameterError
from ._args import add_force_arg, bounded_float, bounded_int, check_output_path
from ._runtime_args import add_device_args, add_frame_args, check_out, frame_kwargs, session_from_args

# what a bag directory holds (recorded or repaired): --force replaces only such a folder
_BAG_FILES = ("metadata.yaml", ".mcap", ".db3", ".db3-journal", ".db3-wal", ".db3-shm", ".tmp")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("record", help="record scans + servo angles to a ROS 2 bag",
                       description=__doc__)
    add_device_args(p)
    p.add_argument("--out", required=True, metavar="DIR", help="bag directory to create")
    g = p.add_mutually_exclusive_group()
    # bounded: a week of scans or seconds at most (--seconds inf would never stop)
    g.add_argument("--scans", type=bounded_int(1, 10**8), default=None, metavar="N",
                   help="stop after N scans")
    g.add_argument("--seconds", type=bounded_float(0, 7 * 86400, lo_open=True, unit="s"),
                   default=None, metavar="S",
                   help="stop after S seconds (session clock; default 10 s if no --scans)")
    p.add_argument("--lift", action="store_true", help="lift the mirrors while recording")
    p.add_argument("--storage", choices=("mcap", "sqlite3"), default="mcap",
                   help="bag storage (default mcap, as ROS 2 records since Iron)")
    p.add_argument("--cloud", default=None, metavar="FILE",
                   help="also assemble the recording live and write it (.ply/.pcd)")
    p.add_argument("--json", action="store_true",
                   help="print a JSON summary (bag, storage, scans, samples, points...)")
    add_force_arg(p)
    add_frame_args(p)
    p.set_defaults(func=run)


def _check_bag_folder(d) -> None:
    """--force on an existing --out replaces it only if it is a bag folder (nothing but a
    bag's files), never another directory."""
    files = list(d.iterdir())
    if not all(f.is_file() and f.name.endswith(_BAG_FILES) for f in files):
        raise ParameterError("--out", str(d), "a new directory, or with --force an existing "
                             "bag folder (this one holds other files)")


def run(args: argparse.Namespace) -> int:
    import shutil
    import sys

    from ..runtime.bag import BagRecorder, BagWriteError
    from ..runtime.session import record_capture

    if args.scans is not None and args.scans < 1:
        raise ParameterError("--scans", args.scans, ">= 1")
    if args.seconds is not None and not args.seconds > 0:
        raise ParameterError("--seconds", args.seconds, "> 0")
    if args.cloud:
        check_out(args.cloud, "--cloud", force=args.force)
    kw = frame_kwargs(args)
    out = check_output_path(args.out, force=args.force, kind="directory")
    if out.exists():
        _check_bag_folder(out)
    seconds = args.seconds if args.seconds is not None or args.scans is not None else 10.0

    def stop(scans, _nod):
        if args.scans is not None:
            return len(scans) >= args.scans
        return scans[-1].stamp_s - scans[0].stamp_s >= seconds

    try:
        with session_from_args(args) as s:
            cal_toml = s.calibration_path.read_text() if s.calibration_path else None
            urg = s.urg
            # set by Session.open (the with statement); params/clock_sync by the driver's open
            assert urg is not None and urg.params is not None and urg.clock_sync is not None
            if out.exists():  # --force on a bag folder (checked above): replaced now
                shutil.rmtree(out)
            rec = BagRecorder(args.out, s.design_path.read_text(), calibration_toml=cal_toml,
                              lift_left=s.lift_left, lift_right=s.lift_right,
                              storage=args.storage, clock=s.time_source,
                              extra={"dmin_mm": int(urg.params.dmin_mm),
                                     "simulated": s.simulated,
                                     "clock_offset_s": urg.clock_sync.offset_s})
            with rec:
                # the live cloud is assembled scan by scan and streamed to the file
                res = record_capture(s, rec, stop, lift=args.lift, cloud=args.cloud,
                                     assemble_kw=kw)
            n_cloud = res.cloud_points
            # revolutions the device measured but the host never got (a stalled host, a
            # link outage): the bag has a gap there, which the user should know of
            dropped = int(urg.stats.dropped_scans)
            if dropped:
                from ._output import status

                status(f"{dropped} scans dropped (missing between recorded scans; the bag "
                       "has gaps there)")
            if not args.json:
                print(f"recorded {rec.scans} scans and {rec.samples} servo samples to {args.out}")
                if args.cloud:
                    print(f"{n_cloud} points -> {args.cloud}")
    except BagWriteError as exc:
        # the disk (or the database) refused: the system's words, exit 1 like any OSError
        print(f"nodlidar record: {exc}", file=sys.stderr)
        return 1
    if args.json:
        print(json.dumps({
            "bag": str(args.out), "storage": rec.storage, "format": rec.header["format"],
            "scans": rec.scans, "dropped_scans": dropped, "servo_samples": rec.samples,
            "point_clouds": rec.clouds_written, "bag_points": rec.points,
            "epoch_offset_ns": rec.epoch_offset_ns, "cloud": args.cloud,
            "cloud_points": n_cloud}, indent=2))
    return 0
