"""Calibrate the mirrors from simulated wall captures and write the calibration file.

    python examples/calibrate.py [OUT_DIR]

The simulated sensor is built with the paper's Table I mounting errors; the fit
(paper Section IV) should find them again. OUT_DIR defaults to $NODLIDAR_EXAMPLES_OUT,
else the current directory.
"""

import os
import sys
from pathlib import Path

from nodlidar.calibration import calibrate, write_calibration
from nodlidar.calibration.synthetic import simulated_captures
from nodlidar.paper import PAPER_DESIGN, TABLE_I_PERTURBATIONS
from nodlidar.solver import solve
from nodlidar.spec import load_design

out_dir = Path(sys.argv[1] if len(sys.argv) > 1 else os.environ.get("NODLIDAR_EXAMPLES_OUT", "."))
out_dir.mkdir(parents=True, exist_ok=True)

design = solve(load_design(PAPER_DESIGN))
# three walls (1 m away, turned -25, 0, +25 deg), the sensor built with Table I's errors
captures = simulated_captures(design, TABLE_I_PERTURBATIONS)
result = calibrate(design, captures)
cal = write_calibration(out_dir / "calibration.toml", result, source="examples/calibrate.py")

print(f"calibration {cal.id} -> {out_dir / 'calibration.toml'} (quality gates "
      f"{'passed' if result.ok else 'FAILED: ' + '; '.join(result.problems)})")
print(f"{'mirror':6} {'dalpha mrad':>12} {'dbeta mrad':>12} {'dd mm':>8}   Table I (mrad, mrad, mm)")
for name, fit in result.mirrors.items():
    p, t = fit.perturbation, TABLE_I_PERTURBATIONS[name]
    print(f"{name:6} {p.dalpha * 1e3:12.3f} {p.dbeta * 1e3:12.3f} {p.dd * 1e3:8.3f}   "
          f"{t.dalpha * 1e3:7.3f} {t.dbeta * 1e3:7.3f} {t.dd * 1e3:6.3f}")
