"""Open a Session on the built-in simulated sensor, nod once, assemble, write a PLY (in
the sensor frame, and in the robot frame of a sensor mounted on a robot).

    python examples/connect_and_sweep.py [OUT_DIR]

OUT_DIR defaults to $NODLIDAR_EXAMPLES_OUT, else the current directory. Pass
``--port``/``--servo-port`` to Session instead to use real hardware.
"""

import os
import sys
from pathlib import Path

import numpy as np

from nodlidar.runtime.cloud import write_cloud
from nodlidar.runtime.session import Session

out_dir = Path(sys.argv[1] if len(sys.argv) > 1 else os.environ.get("NODLIDAR_EXAMPLES_OUT", "."))

# no design: the paper's build; no port: the simulated sensor, here at 5x real time
with Session(sim_rate=5.0) as s:
    capture = s.sweep()
    cloud = capture.assemble(s.model)
    # the sensor's pose on the robot (maps sensor coordinates into the robot frame):
    # 0.1 m ahead of and 0.5 m above the robot's origin, not turned
    robot_from_sensor = np.eye(4)
    robot_from_sensor[:3, 3] = (0.1, 0.0, 0.5)
    on_robot = capture.assemble(s.model, frame="robot", robot_from_sensor=robot_from_sensor)

out_dir.mkdir(parents=True, exist_ok=True)
path = write_cloud(out_dir / "sweep.ply", cloud)
write_cloud(out_dir / "sweep_robot.ply", on_robot)
print(f"{len(cloud)} points from {len(capture.scans)} scans -> {path}")
