"""``nodlidar replay BAG``: assemble a recording through the same pipeline as live.

Rebuilds the design (and calibration) stored in the bag, decodes the raw SCIP frames and
the servo samples, and writes the cloud. A bag whose recording was killed is repaired
first (its metadata.yaml rebuilt from the database).
"""

from __future__ import annotations

from ._runtime_args import add_frame_args, check_out, frame_kwargs


def register(sub) -> None:
    p = sub.add_parser("replay", help="assemble a recorded bag into a point cloud",
                       description=__doc__)
    p.add_argument("bag", help="bag directory written by 'nodlidar record'")
    p.add_argument("--out", default=None, metavar="FILE", help="write the cloud (.ply/.pcd)")
    p.add_argument("--ascii", action="store_true", help="ASCII instead of binary file")
    add_frame_args(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from ..runtime.bag import replay_bag
    from ..runtime.cloud import write_cloud

    if args.out:
        check_out(args.out)
    contents, cloud = replay_bag(args.bag, **frame_kwargs(args))
    if contents.recovered:
        print(f"{args.bag}: recording had not been closed; repaired (metadata.yaml rebuilt)")
    print(f"{len(contents.scans)} scans, {sum(len(t) for t, _ in contents.joints.values())} servo "
          f"samples -> {len(cloud)} points (design {cloud.design_name}, calibration "
          f"{cloud.calibration_id}, frame {cloud.frame})")
    if args.out:
        print(f"wrote {write_cloud(args.out, cloud, binary=not args.ascii)}")
    return 0
