"""Record a few scans to a ROS 2 bag (MCAP), replay it, compare the point counts.

    python examples/record.py [OUT_DIR]

The live cloud assembled while recording and the cloud replayed from the bag go through
the same pipeline, so their point counts must agree. OUT_DIR defaults to
$NODLIDAR_EXAMPLES_OUT, else the current directory.
"""

import os
import sys
from pathlib import Path

from nodlidar.runtime.bag import BagRecorder, replay_bag
from nodlidar.runtime.session import Session, record_capture

out_dir = Path(sys.argv[1] if len(sys.argv) > 1 else os.environ.get("NODLIDAR_EXAMPLES_OUT", "."))
out_dir.mkdir(parents=True, exist_ok=True)
bag = out_dir / "capture_bag"          # must not exist yet


def stop(scans, _nod):
    return len(scans) >= 20            # a few scans (0.1 s each on the paper's URG-04LX)


with Session(sim_rate=5.0) as s:
    # the bag stores the design and the lift profiles so that a replay rebuilds the same model
    with BagRecorder(bag, s.design_path.read_text(), lift_left=s.lift_left,
                     lift_right=s.lift_right, clock=s.time_source) as rec:
        live = record_capture(s, rec, stop, cloud=out_dir / "live.ply")

contents, cloud = replay_bag(bag)
print(f"recorded {live.scans} scans, live cloud {live.cloud_points} points")
print(f"replayed {len(contents.scans)} scans from {bag}: {len(cloud)} points")
print("point counts agree" if len(cloud) == live.cloud_points else "point counts DIFFER")
sys.exit(0 if len(cloud) == live.cloud_points else 1)
