"""Solve the paper's design for a few design distances D and print a table.

    python examples/design_sweep.py [OUT_DIR]

For each D the mirrors are re-solved (paper Section III) and ray-traced; the table shows
the interleave error at D and at 6 m, the density gain and the glass needed (a D the
solver refuses is listed with the reason). The table is also written to
OUT_DIR/design_sweep.csv (OUT_DIR defaults to $NODLIDAR_EXAMPLES_OUT, else the current
directory).
"""

import os
import sys
from pathlib import Path

from nodlidar.analysis.explore import Sweep, explore
from nodlidar.paper import PAPER_DESIGN
from nodlidar.spec import load_design

out_dir = Path(sys.argv[1] if len(sys.argv) > 1 else os.environ.get("NODLIDAR_EXAMPLES_OUT", "."))
out_dir.mkdir(parents=True, exist_ok=True)

spec = load_design(PAPER_DESIGN)
result = explore(spec, [Sweep.parse("layout.design_distance_m=1,2,3,5,6", spec)], workers=0)

print(f"{'D m':>5} {'rms err at D deg':>17} {'rms err 6 m deg':>16} {'density gain':>13} "
      f"{'glass cm2':>10} {'pareto':>7}")
for row in result.rows:
    if not row["feasible"]:     # e.g. beyond the lidar's reach: the row says why
        print(f"{row['layout.design_distance_m']:5.1f}  infeasible: {row['reason']}")
        continue
    print(f"{row['layout.design_distance_m']:5.1f} {row['rms_error_deg']:17.4f} "
          f"{row['rms_error_6m_deg']:16.4f} {row['density_gain']:13.3f} "
          f"{row['glass_area_cm2']:10.2f} {str(row['pareto']):>7}")
print(f"wrote {result.write_csv(out_dir / 'design_sweep.csv')}")
