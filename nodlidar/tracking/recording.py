"""Scans for the tracking pipeline from a recording made by ``nodlidar record``.

The bag holds the raw SCIP frames, the nod and mirror servo samples and the design (and
calibration) it was recorded with (:mod:`nodlidar.runtime.bag`). Each scan becomes a
:class:`~nodlidar.tracking.simdata.ScanPoints` the same way the simulator's scans do: beam time
from the scan stamp (:meth:`LidarModel.beam_time_s`), nod interpolated from the servo samples,
points and free-space rays from the runtime BeamModel (deployed or lifted per mirror side at
the beam's time). Unlike :func:`nodlidar.runtime.assembly.assemble`, beams with no return are
kept (NaN range): the segmentation uses them as free space.

The sensor base is taken as the world frame (a recording holds no robot poses).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .simdata import ScanPoints, project_scan

__all__ = ["scans_from_recording"]


def scans_from_recording(path: str | Path):
    """Read a recording and return ``(design, [ScanPoints, ...])``.

    Beams whose nod angle is unknown (outside the servo samples) or whose mirror was moving
    are dropped, as in the assembly.
    """
    from ..errors import DesignFileError
    from ..runtime.assembly import DEPLOYED, LIFTED, AngleSamples, AssemblyModel, mirror_state
    from ..runtime.bag import design_from_header, read_bag

    contents = read_bag(path)
    if not contents.scans:
        raise DesignFileError(f"{path}: the recording has no scans")
    if "nod" not in contents.joints:
        raise DesignFileError(f"{path}: the recording has no nod servo samples")
    design, perts, cal_id = design_from_header(contents.header)
    model = AssemblyModel.from_design(design, perts, cal_id)
    lidar = design.lidar
    nod = AngleSamples.of(contents.joints["nod"])
    profiles = contents.lift_profiles()
    sides = [contents.joints.get(j) for j in ("mirror_left", "mirror_right")]

    out: list[ScanPoints] = []
    for k, scan in enumerate(contents.scans):
        steps = np.asarray(scan.steps)
        t = lidar.beam_time_s(scan.stamp_s, steps)
        nod_rad = nod.at(t)
        mirror = model.deployed.mirror_index(steps)
        state = np.full(steps.shape, DEPLOYED, dtype=np.int8)
        for side, (samples, profile) in enumerate(zip(sides, profiles)):
            on_side = (mirror >= 0) & (model.mirror_side[np.maximum(mirror, 0)] == side)
            if samples is not None and on_side.any():
                state[on_side] = mirror_state(AngleSamples.of(samples).at(t[on_side]), profile)
        keep = np.isfinite(nod_rad) & ((state == DEPLOYED) | (state == LIFTED))
        if not keep.any():
            continue
        steps, t, nod_rad, state = steps[keep], t[keep], nod_rad[keep], state[keep]
        r = np.asarray(scan.ranges_m, dtype=float)[keep]
        lifted = state == LIFTED
        parts = [project_scan(bm, k, steps[sel], r[sel], t[sel], nod_rad[sel])
                 for bm, sel in ((model.deployed, ~lifted), (model.lifted, lifted)) if sel.any()]
        out.append(parts[0] if len(parts) == 1 else _concat(parts))
    if not out:
        raise DesignFileError(f"{path}: no scan has nod samples covering it")
    return design, out


def _concat(parts: list[ScanPoints]) -> ScanPoints:
    """One ScanPoints from parts of the same scan, in step order."""
    cat = {f: np.concatenate([getattr(p, f) for p in parts])
           for f in ("steps", "t_s", "mirror", "range_m", "points", "ray_start", "ray_dir",
                     "ray_offset")}
    order = np.argsort(cat["steps"], kind="stable")
    return ScanPoints(scan=parts[0].scan, **{f: v[order] for f, v in cat.items()})
