"""Checks against a real URG-04LX: run with ``NODLIDAR_PORT=/dev/ttyACM0 make test``.

Without ``NODLIDAR_PORT`` these are skipped: the same checks run against the emulator in
test_urg_driver.py and test_sim_sensor.py, and the decoder against real device bytes
(tests/data/urg04lx-captures) in test_scip_codec.py and test_fuzz_scip.py.
"""

from __future__ import annotations

import os

import numpy as np
import pytest

from nodlidar.runtime.urg import UrgDriver
from nodlidar.scip import RangePlausibility

PORT = os.environ.get("NODLIDAR_PORT")
pytestmark = [pytest.mark.hardware,
              pytest.mark.skipif(not PORT,
                                 reason="set NODLIDAR_PORT to a URG-04LX (device or socket:// URL)")]


def test_device_reports_its_parameters():
    with UrgDriver(PORT) as urg:
        info = urg.info()
        model = urg.model
    assert info.version.protocol.startswith("SCIP 2.0")
    # the URG-04LX's documented PP values (reference/scip2.md)
    assert (model.steps_per_rev, model.step_min, model.step_max, model.step_front) == (1024, 44, 725, 384)


def test_single_scan_has_every_step():
    with UrgDriver(PORT) as urg:
        scan = urg.scan()
    assert len(scan.ranges_m) == 682
    valid = ~scan.error_mask
    assert np.all((scan.ranges_m[valid] >= 0.02) & (scan.ranges_m[valid] <= 5.6))


def test_plausibility_false_positives_on_the_device():
    """20 consecutive scans of the real device through the plausibility filter: every
    value is what the device measured, so each flag is a false positive; the filter's
    budget (RangePlausibility) is 5e-4, measured 2.8e-4 on simulated scans."""
    with UrgDriver(PORT, plausibility=RangePlausibility()) as urg:
        scans = list(urg.stream(count=20))
        flagged = urg.stats.implausible_values
    checked = sum(int((~s.error_mask).sum()) for s in scans)
    assert checked > 0
    assert flagged <= 5e-4 * checked + 1, (flagged, checked)
