"""Wall captures from runtime data: scans + nod servo samples -> :class:`WallCapture`.

The runtime (:mod:`nodlidar.runtime.assembly`) stores scans as a ``ScanBatch`` (steps,
ranges, scan index, each scan's step-0 time) and the nod servo as timestamped angle
samples. Calibration needs each beam's nod angle, obtained exactly as the assembly does:
the beam's time from :meth:`LidarModel.beam_time_s` and the nod samples interpolated there
(``AngleSamples.at``). Beams outside the nod samples' time span are dropped.
"""

from __future__ import annotations

import numpy as np

from ..errors import CalibrationError
from .walls import WallCapture

__all__ = ["capture_from_scans"]


def capture_from_scans(design, scans, nod, *, mirrors_deployed: bool = True,
                       name: str = "") -> WallCapture:
    """A wall capture from a runtime ``ScanBatch`` and nod samples.

    Parameters
    ----------
    design : Design
    scans : nodlidar.runtime.assembly.ScanBatch
        All beams of the capture's scans with each scan's step-0 time [s].
    nod : AngleSamples, Samples or (t (k,), angle (k,)) pair
        Head pitch [rad] of the nod servo at times [s] (the scans' clock).
    mirrors_deployed : bool
        The mirrors' state during the capture (calibration needs them deployed).
    name : str
        Label for reports.
    """
    from ..runtime.assembly import AngleSamples

    steps = np.asarray(scans.steps)
    t = design.lidar.beam_time_s(np.asarray(scans.scan_time_s, float)[np.asarray(scans.scan)], steps)
    nod_rad = AngleSamples.of(nod).at(t)
    keep = np.isfinite(nod_rad)
    if not keep.any():
        raise CalibrationError(f"{name or 'capture'}: no beam falls inside the nod samples' time "
                               "span; are the scan and servo clocks the same?")
    return WallCapture(steps=steps[keep].astype(int),
                       ranges_m=np.asarray(scans.ranges_m, float)[keep],
                       nod_rad=nod_rad[keep], mirrors_deployed=mirrors_deployed, name=name)
