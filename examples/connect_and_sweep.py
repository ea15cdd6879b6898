"""Open a Session on the built-in simulated sensor, nod once, assemble, write a PLY.

    python examples/connect_and_sweep.py [OUT_DIR]

OUT_DIR defaults to $NODLIDAR_EXAMPLES_OUT, else the current directory. Pass
``--port``/``--servo-port`` to Session instead to use real hardware.
"""

import os
import sys
from pathlib import Path

from nodlidar.runtime.cloud import write_cloud
from nodlidar.runtime.session import Session

out_dir = Path(sys.argv[1] if len(sys.argv) > 1 else os.environ.get("NODLIDAR_EXAMPLES_OUT", "."))

# no design: the paper's build; no port: the simulated sensor, here at 5x real time
with Session(sim_rate=5.0) as s:
    capture = s.sweep()
    cloud = capture.assemble(s.model)

out_dir.mkdir(parents=True, exist_ok=True)
path = write_cloud(out_dir / "sweep.ply", cloud)
print(f"{len(cloud)} points from {len(capture.scans)} scans -> {path}")
