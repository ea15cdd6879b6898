"""Wall captures from runtime data: scans + servo samples -> :class:`WallCapture`.

The runtime (:mod:`nodlidar.runtime.assembly`) stores scans as a ``ScanBatch`` (steps,
ranges, scan index, each scan's step-0 time) and the servos as timestamped angle samples.
Calibration needs each beam's nod angle and whether its mirror was deployed; both come
from the assembly itself (:func:`~nodlidar.runtime.assembly.assemble`, the one place the
beam time, the nod interpolation and the mirror state are decided), so a wall capture
holds exactly the beams a point cloud of the same data would: no error codes, none outside
the nod samples' time span, none whose mirror was moving. Beams of a lifted side are
dropped too: the fit maps the reflected windows' steps through the deployed mirrors.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import CalibrationError
from .walls import WallCapture

if TYPE_CHECKING:
    from ..design import Design
    from ..runtime.assembly import ScanBatch
    from ..runtime.servo_angles import MirrorLiftProfile
    from ..runtime.session import Capture

__all__ = ["capture_from_scans", "capture_from_capture", "capture_from_recording"]


def capture_from_scans(design: Design, scans: ScanBatch, nod: Any, *, mirror_left: Any = None,
                       mirror_right: Any = None, lift_left: MirrorLiftProfile | None = None,
                       lift_right: MirrorLiftProfile | None = None,
                       mirrors_deployed: bool = True, name: str = "") -> WallCapture:
    """A wall capture from a runtime ``ScanBatch`` and servo samples.

    Parameters
    ----------
    design : Design
    scans : nodlidar.runtime.assembly.ScanBatch
        All beams of the capture's scans with each scan's step-0 time [s].
    nod : AngleSamples, Samples or (t (k,), angle (k,)) pair
        Head pitch [rad] of the nod servo at times [s] (the scans' clock).
    mirror_left, mirror_right : samples, "deployed", "lifted" or None
        Lift-servo samples of each side (None: deployed throughout), as for ``assemble``.
    lift_left, lift_right : MirrorLiftProfile, optional
        The sides' deployed/lifted servo angles (default: the design's,
        :func:`~nodlidar.runtime.servo_angles.lift_profiles`).
    mirrors_deployed : bool
        False: a capture with both mirrors lifted (every beam direct; not usable by the
        mirror fit, which refuses it).
    name : str
        Label for reports.
    """
    from ..runtime.assembly import AssemblyModel, assemble

    if not mirrors_deployed:
        mirror_left = mirror_right = "lifted"
    model = AssemblyModel.from_design(design)
    cloud = assemble(model, scans, nod, mirror_left=mirror_left, mirror_right=mirror_right,
                     lift_left=lift_left, lift_right=lift_right)
    # a lifted side's beams are projected as direct ones: keep them only for an all-lifted
    # capture (the fit maps the reflected windows' steps through the deployed mirrors)
    lifted, nod_rad = cloud.lifted, cloud.nod_rad
    assert lifted is not None and nod_rad is not None  # assemble() sets both (not a file's)
    keep = ~lifted if mirrors_deployed else np.ones(len(cloud), bool)
    if not keep.any():
        raise CalibrationError(f"{name or 'capture'}: no usable beam (none inside the nod samples' "
                               "time span with its mirror deployed); are the scan and servo "
                               "clocks the same?")
    return WallCapture(steps=cloud.step[keep].astype(int), ranges_m=cloud.range_m[keep],
                       nod_rad=nod_rad[keep], mirrors_deployed=mirrors_deployed, name=name)


def capture_from_capture(design: Design, capture: Capture, *, name: str = "") -> WallCapture:
    """A wall capture from a live :class:`~nodlidar.runtime.session.Capture` (a sweep)."""
    from ..runtime.assembly import ScanBatch

    if not capture.scans:
        raise CalibrationError(f"{name or 'capture'}: the sweep returned no scans")
    return capture_from_scans(design, ScanBatch.from_scans(capture.scans), capture.joints["nod"],
                              mirror_left=capture.joints.get("mirror_left"),
                              mirror_right=capture.joints.get("mirror_right"),
                              lift_left=capture.lift_left, lift_right=capture.lift_right,
                              name=name)


def capture_from_recording(path: str | Path, design: Design | None = None, *,
                           name: str = "") -> tuple[Design, WallCapture]:
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
    from ..runtime.assembly import ScanBatch
    from ..runtime.bag import design_from_header, read_recording
    from .fit import design_hash

    contents = read_recording(path)
    recorded, _, _ = design_from_header(contents.header)
    if design is None:
        design = recorded
    elif design_hash(design.spec) != design_hash(recorded.spec):
        raise CalibrationError(f"{path}: recorded with design '{recorded.spec.name}' "
                               f"({design_hash(recorded.spec)}), not '{design.spec.name}' "
                               f"({design_hash(design.spec)})")
    left, right = contents.lift_profiles()
    return design, capture_from_scans(
        design, ScanBatch.from_scans(contents.scans), contents.joints["nod"],
        mirror_left=contents.joints.get("mirror_left"),
        mirror_right=contents.joints.get("mirror_right"), lift_left=left, lift_right=right,
        name=name or Path(path).name)
