"""Track moving objects live: the simulated sensor nods in the paper's tracking scene (a
person walking past) and every assembled scan goes through the segmenter and the tracker.

    python examples/track_live.py [OUT_DIR]

Prints each confirmed track's final state and writes them to OUT_DIR/tracks.json
(OUT_DIR defaults to $NODLIDAR_EXAMPLES_OUT, else the current directory).
"""

import json
import os
import sys
from pathlib import Path

from nodlidar.runtime.session import Session
from nodlidar.tracking.recording import LiveScans
from nodlidar.tracking.tracker import Tracker

out_dir = Path(sys.argv[1] if len(sys.argv) > 1 else os.environ.get("NODLIDAR_EXAMPLES_OUT", "."))
out_dir.mkdir(parents=True, exist_ok=True)
N_SCANS = 60                      # 6 s of the sensor's time at 10 scans/s

tracks = {}                       # track id -> its latest state


def step(scan_points):
    # Tracker.update segments each scan itself (online, with the lidar's range noise model)
    for state in tracker.update(scan_points):
        tracks[state.track_id] = state


# real time: the walker turns every 12.3 s, so the 6 s capture (which starts after the
# few seconds of start-up) sees one straight walk
with Session(scene="paper-tracking", sim_rate=1.0) as s:
    tracker = Tracker(range_sigma=s.design.lidar.range_sigma_m)
    live = LiveScans(s.model, (s.lift_left, s.lift_right))   # assembles each scan once covered

    def on_scan(scan, samplers):
        for scan_points in live.on_scan(scan, samplers):
            step(scan_points)

    capture = s.capture(lambda scans, _nod: len(scans) >= N_SCANS, on_scan=on_scan)
    for scan_points in live.finish(capture):      # the last scan, once its samples are in
        step(scan_points)

confirmed = [st for st in tracks.values() if st.confirmed]
for st in confirmed:
    print(f"track {st.track_id}: x {st.x_m:.3f} y {st.y_m:.3f} m, speed {st.v_m_s:.3f} m/s, "
          f"{st.n_scans} scans")
print(f"{len(confirmed)} confirmed tracks from {live.n_done} scans")
(out_dir / "tracks.json").write_text(json.dumps([st.to_dict() for st in confirmed], indent=1))
