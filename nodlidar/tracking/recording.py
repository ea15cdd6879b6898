"""Scans for the tracking pipeline from runtime data: a recording, or a live session.

The runtime keeps the raw scans, the nod and mirror servo samples and the design (and
calibration) they belong to (:mod:`nodlidar.runtime.bag` for recordings,
:class:`~nodlidar.runtime.session.Capture` live). Each scan becomes a
:class:`~nodlidar.tracking.scans.ScanPoints` through the runtime assembly itself
(:func:`~nodlidar.runtime.assembly.assemble`: the one place that decides each beam's time,
its nod angle, its mirror's state, and drops beams outside the nod samples, with the
mirror moving, or blocked); only the outgoing rays are added here, from the same
BeamModel the assembly used for the beam (deployed or lifted). Unlike a point cloud,
beams with no return are kept (NaN range): the segmentation carves them as free space.
They pass through the assembly with a placeholder range and get their NaN back after.

Frame: the sensor base, raised by ``sensor_height_m`` - the tracking's world frame has the
floor at z = 0 (the segmentation removes a band above it as ground), and neither a
recording nor a live session knows where the floor is. The default 0.4 m is the paper's
mount on a Pioneer P3-DX (and the simulated scenes' sensor height).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from .._light import DEFAULT_SENSOR_HEIGHT_M  # defined without numpy: the CLI parser shows it
from .scans import ScanPoints, sensor_velocity

if TYPE_CHECKING:
    from ..design import Design
    from ..runtime.actuators import PositionSampler
    from ..runtime.assembly import AssemblyModel
    from ..runtime.servo_angles import MirrorLiftProfile
    from ..runtime.session import Capture
    from ..sim.scene import SensorPose

__all__ = ["DEFAULT_SENSOR_HEIGHT_M", "scans_from_capture", "scans_from_recording",
           "LiveScans"]

_PLACEHOLDER_M = 1.0  # any valid range: the assembly keeps the beam, its NaN is restored


def scans_from_capture(model: AssemblyModel, scans: Sequence[Any], joints: Mapping[str, Any],
                       lift_profiles: Sequence[MirrorLiftProfile | None] = (None, None), *,
                       sensor_height_m: float = DEFAULT_SENSOR_HEIGHT_M,
                       first_index: int = 0, pose: SensorPose | None = None,
                       truth_id: np.ndarray | None = None) -> list[ScanPoints]:
    """Runtime scans + servo samples -> one :class:`ScanPoints` per scan with any beam kept.

    Parameters
    ----------
    model : nodlidar.runtime.assembly.AssemblyModel
        The design's BeamModels, calibration applied.
    scans : sequence of driver Scans (or anything with ``steps``, ``ranges_m``, ``stamp_s``)
    joints : mapping
        ``"nod"`` (required), ``"mirror_left"``, ``"mirror_right"``: servo samples
        (anything :class:`~nodlidar.runtime.assembly.AngleSamples` takes).
    lift_profiles : (MirrorLiftProfile or None, MirrorLiftProfile or None)
    sensor_height_m : float
        Height of the sensor base above the floor [m] (module docstring).
    first_index : int
        ``ScanPoints.scan`` of the first scan (scan indices count on across calls).
    pose : object with ``to_world(p (n, 3), t (n,))`` and ``rotation (3, 3)``, optional
        The sensor base's pose in the world (e.g. :class:`nodlidar.sim.scene.SensorPose`:
        the simulator's known robot pose); replaces ``sensor_height_m`` when given.
    truth_id : (n_scans, lidar.n_steps) int, optional
        Ground-truth object id per scan and step (simulator), carried to ``ScanPoints``.
    """
    from ..runtime.assembly import ScanBatch, assemble

    if not scans:
        return []
    batch = ScanBatch.from_scans(scans)
    r = np.asarray(batch.ranges_m, dtype=float)
    no_return = ~(np.isfinite(r) & (r > 0))
    lidar = model.lidar
    grid = np.zeros((len(scans), lidar.n_steps), bool)
    grid[np.asarray(batch.scan), np.asarray(batch.steps) - lidar.step_min] = no_return
    held = ScanBatch(batch.steps, np.where(no_return, _PLACEHOLDER_M, r), batch.scan,
                     batch.scan_time_s)
    left, right = lift_profiles
    cloud = assemble(model, held, joints["nod"], mirror_left=joints.get("mirror_left"),
                     mirror_right=joints.get("mirror_right"), lift_left=left, lift_right=right)
    if not len(cloud):
        return []
    step, scan_i, t = cloud.step.astype(int), cloud.scan.astype(int), cloud.t
    missing = grid[scan_i, step - lidar.step_min]
    rng = np.where(missing, np.nan, cloud.range_m)
    nod, lifted = cloud.nod_rad, cloud.lifted  # as the assembly decided them for each beam
    # assemble() always fills both (None only in clouds from elsewhere)
    assert nod is not None and lifted is not None
    start, direc, off = np.empty((len(t), 3)), np.empty((len(t), 3)), np.empty(len(t))
    for bm, sel in ((model.deployed, ~lifted), (model.lifted, lifted)):
        if sel.any():
            start[sel], direc[sel], off[sel] = bm.rays(step[sel], nod[sel])
    if pose is None:
        lift = np.array([0.0, 0.0, float(sensor_height_m)])
        xyz, start = cloud.xyz + lift, start + lift
    else:
        xyz, start = pose.to_world(cloud.xyz, t), pose.to_world(start, t)
        direc = direc @ pose.rotation.T
    pts = np.where(missing[:, None], np.nan, xyz)
    tid = None if truth_id is None else np.asarray(truth_id)[scan_i, step - lidar.step_min]
    out = []
    bounds = np.flatnonzero(np.diff(scan_i)) + 1  # assemble keeps the batch's scan order
    for idx in np.split(np.arange(len(t)), bounds):
        k = int(scan_i[idx[0]])
        order = idx[np.argsort(step[idx], kind="stable")]
        out.append(ScanPoints(scan=first_index + k, steps=step[order], t_s=t[order],
                              mirror=cloud.mirror[order].astype(int), range_m=rng[order],
                              points=pts[order], ray_start=start[order], ray_dir=direc[order],
                              ray_offset=off[order], calibration_id=cloud.calibration_id,
                              truth_id=None if tid is None else np.where(missing[order], -1,
                                                                         tid[order]),
                              sensor_velocity_m_s=sensor_velocity(pose, t[order])))
    return out


def scans_from_recording(path: str | Path, *,
                         sensor_height_m: float = DEFAULT_SENSOR_HEIGHT_M,
                         calibration: str | Path | None = None) -> tuple[Design, list[ScanPoints]]:
    """Read a recording and return ``(design, [ScanPoints, ...])`` (see the module docstring).

    Beams whose nod angle is unknown (outside the servo samples), whose mirror was moving,
    or that the calibrated mirrors block are dropped, as in the assembly.

    ``calibration``: a calibration file of the recording's design, used instead of the
    calibration the recording was made with (a sensor calibrated after recording).
    """
    from ..errors import DesignFileError
    from ..runtime.assembly import AssemblyModel
    from ..runtime.bag import design_from_header, read_recording

    contents = read_recording(path)
    design, perts, cal_id = design_from_header(contents.header)
    if calibration is not None:
        from ..calibration.calfile import load_calibration

        cal = load_calibration(calibration, design)
        perts, cal_id = cal.perturbations, cal.id
    model = AssemblyModel.from_design(design, perts, cal_id)
    out = scans_from_capture(model, contents.scans, contents.joints, contents.lift_profiles(),
                             sensor_height_m=sensor_height_m)
    if not out:
        raise DesignFileError(f"{path}: no scan has nod samples covering it")
    return design, out


class LiveScans:
    """Scans of a live :meth:`Session.capture <nodlidar.runtime.session.Session.capture>` as
    they arrive, each handed on once the servo samples cover it.

    Use :meth:`on_scan` as the capture's ``on_scan`` callback; it returns the
    :class:`ScanPoints` now ready (a scan waits until a nod sample later than its last beam
    has been read, typically one scan period), in order. :meth:`finish` returns the rest
    from the capture's final samples.

    Parameters
    ----------
    model : AssemblyModel
        The session's (``Session.model``).
    lift_profiles : (MirrorLiftProfile, MirrorLiftProfile)
    sensor_height_m : float
    """

    def __init__(self, model: AssemblyModel, lift_profiles: Sequence[MirrorLiftProfile | None], *,
                 sensor_height_m: float = DEFAULT_SENSOR_HEIGHT_M) -> None:
        self.model = model
        self.lift_profiles = tuple(lift_profiles)
        self.sensor_height_m = float(sensor_height_m)
        self.pending: list[Any] = []  # driver Scans
        self.n_in = 0  # scans received
        self.n_done = 0  # scans handed on (or dropped) so far
        self._done_until = -np.inf  # last beam time [s] of the scans handed on

    def need_since_s(self) -> float:
        """Earliest time [s] a scan not yet handed on may need servo samples for: the oldest
        pending scan's first beam, or (none pending) the last handed-on beam - the next
        scan's beams come after it. Samples before it may be pruned (``sampler.prune``):
        a long live run then keeps a few scans' worth, and loses none."""
        if not self.pending:
            return self._done_until
        s = self.pending[0]
        return float(self.model.lidar.beam_time_s(s.stamp_s, np.asarray([np.min(s.steps)]))[0])

    def _ready(self, joints, final: bool) -> list[ScanPoints]:
        lidar = self.model.lidar
        # every servo's samples must reach past a scan's last beam (nod and mirror state)
        t_cover = min((float(np.max(j[0])) if len(j[0]) else -np.inf) for j in joints.values())
        n = 0
        for s in self.pending:
            last_beam = float(lidar.beam_time_s(s.stamp_s, np.asarray([np.max(s.steps)]))[0])
            if not final and last_beam >= t_cover:
                break
            n += 1
        batch, self.pending = self.pending[:n], self.pending[n:]
        first = self.n_done
        self.n_done += n
        if batch:
            s = batch[-1]
            self._done_until = float(lidar.beam_time_s(s.stamp_s, np.asarray([np.max(s.steps)]))[0])
        return scans_from_capture(self.model, batch, joints, self.lift_profiles,
                                  sensor_height_m=self.sensor_height_m, first_index=first)

    def on_scan(self, scan: Any, samplers: Mapping[str, PositionSampler]) -> list[ScanPoints]:
        """Add a scan; return the scans the samples read so far cover."""
        self.pending.append(scan)
        self.n_in += 1
        joints = {}
        for name, smp in samplers.items():
            s = smp.samples()
            joints[name] = (np.asarray(s.host_time_s), np.asarray(s.angle_rad))
        if len(joints.get("nod", ((),))[0]) < 2:
            return []
        return self._ready(joints, final=False)

    def finish(self, capture: Capture) -> list[ScanPoints]:
        """The scans still waiting, from the capture's final samples."""
        return self._ready(capture.joints, final=True) if self.pending else []
