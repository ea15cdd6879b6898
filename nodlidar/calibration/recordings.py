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

__all__ = ["capture_from_scans", "capture_from_recording"]


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


def capture_from_recording(path, design=None, *, name: str = ""):
    """A wall capture from a recording made by ``nodlidar record`` (a ROS 2 bag).

    Beam times, nod angles and mirror states are found as in the runtime assembly: beams
    outside the nod samples are dropped, and so are reflected-window beams whose mirror was
    not deployed (lifted or moving) - the fit maps those steps through the deployed mirrors.
    A calibration recorded in the bag is ignored: calibration starts from the design.

    Parameters
    ----------
    path : str or Path
        Bag directory.
    design : Design, optional
        The design to calibrate; must be the recording's (same geometric hash). Default: the
        design stored in the recording.

    Returns
    -------
    (Design, WallCapture)
    """
    from pathlib import Path

    from ..errors import DesignFileError
    from ..runtime.assembly import DEPLOYED, AngleSamples, AssemblyModel, ScanBatch, mirror_state
    from ..runtime.bag import design_from_header, read_bag
    from .fit import design_hash

    contents = read_bag(path)
    if not contents.scans:
        raise DesignFileError(f"{path}: the recording has no scans")
    if "nod" not in contents.joints:
        raise DesignFileError(f"{path}: the recording has no nod servo samples")
    recorded, _, _ = design_from_header(contents.header)
    if design is None:
        design = recorded
    elif design_hash(design.spec) != design_hash(recorded.spec):
        raise CalibrationError(f"{path}: recorded with design '{recorded.spec.name}' "
                               f"({design_hash(recorded.spec)}), not '{design.spec.name}' "
                               f"({design_hash(design.spec)})")
    scans = ScanBatch.from_scans(contents.scans)
    cap = capture_from_scans(design, scans, contents.joints["nod"], name=name or Path(path).name)
    # the mirror state of each kept beam's side at its time, as the assembly decides it
    model = AssemblyModel.from_design(design)
    t = design.lidar.beam_time_s(np.asarray(scans.scan_time_s)[np.asarray(scans.scan)],
                                 np.asarray(scans.steps))
    t = t[np.isfinite(AngleSamples.of(contents.joints["nod"]).at(t))]
    mirror = model.deployed.mirror_index(cap.steps)
    ok = mirror < 0
    for side, (joint, profile) in enumerate(zip(("mirror_left", "mirror_right"),
                                                contents.lift_profiles())):
        on_side = (mirror >= 0) & (model.mirror_side[np.maximum(mirror, 0)] == side)
        samples = contents.joints.get(joint)
        if samples is None:  # no lift servo recorded: deployed throughout
            ok |= on_side
        elif on_side.any():
            state = mirror_state(AngleSamples.of(samples).at(t[on_side]), profile)
            ok[np.flatnonzero(on_side)[state == DEPLOYED]] = True
    return design, WallCapture(cap.steps[ok], cap.ranges_m[ok], cap.nod_rad[ok],
                               mirrors_deployed=True, name=cap.name)
