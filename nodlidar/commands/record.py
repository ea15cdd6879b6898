"""``nodlidar record --out DIR``: record a nodding capture to a ROS 2 bag (sqlite3).

Topics: the raw SCIP frames, sensor_msgs/LaserScan, sensor_msgs/JointState (nod and mirror
servo samples) and the design/calibration (so ``nodlidar replay`` rebuilds the same
BeamModels). Every scan is committed as it arrives: a recording killed (even with SIGKILL)
keeps every scan before the one in flight; ``nodlidar replay`` repairs such a bag.
"""

from __future__ import annotations

from ..errors import ParameterError
from ._runtime_args import add_device_args, add_frame_args, check_out, frame_kwargs, session_from_args


def register(sub) -> None:
    p = sub.add_parser("record", help="record scans + servo angles to a ROS 2 bag",
                       description=__doc__)
    add_device_args(p)
    p.add_argument("--out", required=True, metavar="DIR", help="bag directory to create")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--scans", type=int, default=None, metavar="N", help="stop after N scans")
    g.add_argument("--seconds", type=float, default=None, metavar="S",
                   help="stop after S seconds (session clock; default 10 s if no --scans)")
    p.add_argument("--lift", action="store_true", help="lift the mirrors while recording")
    p.add_argument("--cloud", default=None, metavar="FILE",
                   help="also assemble the recording live and write it (.ply/.pcd)")
    add_frame_args(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from pathlib import Path

    from ..runtime.bag import BagRecorder
    from ..runtime.cloud import write_cloud
    from ..runtime.session import record_capture

    if args.scans is not None and args.scans < 1:
        raise ParameterError("--scans", args.scans, ">= 1")
    if args.seconds is not None and not args.seconds > 0:
        raise ParameterError("--seconds", args.seconds, "> 0")
    if args.cloud:
        check_out(args.cloud, "--cloud")
    kw = frame_kwargs(args)
    if Path(args.out).exists():
        raise ParameterError("--out", args.out, "a directory that does not exist yet")
    seconds = args.seconds if args.seconds is not None or args.scans is not None else 10.0

    def stop(scans, _nod):
        if args.scans is not None:
            return len(scans) >= args.scans
        return scans[-1].stamp_s - scans[0].stamp_s >= seconds

    with session_from_args(args) as s:
        cal_toml = s.calibration_path.read_text() if s.calibration_path else None
        rec = BagRecorder(args.out, s.design_path.read_text(), calibration_toml=cal_toml,
                          lift_left=s.lift_left, lift_right=s.lift_right,
                          extra={"dmin_mm": int(s.urg.params.dmin_mm),
                                 "simulated": s.simulated,
                                 "clock_offset_s": s.urg.clock_sync.offset_s})
        with rec:
            cap = record_capture(s, rec, stop, lift=args.lift)
        print(f"recorded {rec.scans} scans and {rec.samples} servo samples to {args.out}")
        if args.cloud:
            cloud = cap.assemble(s.model, **kw)
            print(f"{len(cloud)} points -> {write_cloud(args.cloud, cloud)}")
    return 0
