"""Scans for the tracking pipeline: world-frame points with per-beam time and free-space rays.

:class:`~nodlidar.tracking.scans.ScanPoints` (defined in :mod:`.scans`, re-exported here) is
what the tracking pipeline consumes: one lidar scan projected with the
runtime :class:`~nodlidar.beams.BeamModel` (per-beam nod angle) and placed in the world by the
robot pose (the paper assumes reliable localisation). It also carries the outgoing ray of every
beam, so that :mod:`nodlidar.tracking.voxels` can carve free space.

:func:`simulate_scans` produces them from the simulator's direct (non-emulator) API
(:class:`nodlidar.sim.raycast.SceneSimulator`), with the nod ramp of the design's
:class:`~nodlidar.spec.NodSpec`, mirrors deployed or lifted, and per-beam ground truth
(which object each beam hit). :func:`synthetic_scans` is a small independent generator
(cylinder + two walls, analytic ray intersection) used by unit tests.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING

import numpy as np

from ..errors import require
from .scans import ScanPoints, sensor_velocity  # ScanPoints re-exported: it was defined here

if TYPE_CHECKING:
    from pathlib import Path

    from ..beams import BeamModel
    from ..design import Design
    from ..geometry import Perturbation
    from ..runtime.assembly import AssemblyModel
    from ..sim.raycast import SceneSimulator
    from ..sim.scene import Scene, SensorPose

__all__ = ["ScanPoints", "project_scan", "simulate_scans", "synthetic_scans"]


def _world(pose, p_sensor: np.ndarray, t: np.ndarray, direction: bool = False) -> np.ndarray:
    if pose is None:
        return p_sensor
    if direction:
        return p_sensor @ pose.rotation.T
    return pose.to_world(p_sensor, t)


def project_scan(beam_model: BeamModel, scan: int, steps: np.ndarray, range_m: np.ndarray,
                 t_s: np.ndarray, nod_rad: np.ndarray, pose: SensorPose | None = None,
                 truth_id: np.ndarray | None = None) -> ScanPoints:
    """Project one scan with the runtime beam model and place it in the world.

    Parameters
    ----------
    beam_model : BeamModel
    scan : int
    steps : (n,) int
    range_m : (n,) float
        Measured ranges [m] (NaN = no return).
    t_s, nod_rad : (n,) float
        Beam times [s] and head pitch at each [rad].
    pose : object with ``to_world(p (n,3), t (n,))`` and ``rotation (3,3)``, optional
        Sensor base pose in the world (e.g. :class:`nodlidar.sim.scene.SensorPose`);
        ``None``: world = sensor base frame.
    truth_id : (n,) int, optional
    """
    steps = np.asarray(steps)
    r = np.asarray(range_m, dtype=float)
    p = beam_model.points(steps, r, nod_rad)
    start, d, off = beam_model.rays(steps, nod_rad)
    return ScanPoints(scan=int(scan), steps=steps, t_s=np.asarray(t_s, float),
                      mirror=beam_model.mirror_index(steps), range_m=r,
                      points=_world(pose, p, t_s), ray_start=_world(pose, start, t_s),
                      ray_dir=_world(pose, d, t_s, direction=True), ray_offset=off,
                      truth_id=truth_id, sensor_velocity_m_s=sensor_velocity(pose, t_s))


def simulate_scans(design: Design, n_scans: int, *, mirrors_deployed: bool = True,
                   scene: Scene | str | Path = "paper-tracking",
                   perturbations: Mapping[str, Perturbation] | None = None, noise: bool = True,
                   seed: int = 0, t0_s: float = 0.0, simulator: SceneSimulator | None = None,
                   model: AssemblyModel | None = None) -> list[ScanPoints]:
    """Simulate ``n_scans`` consecutive scans of ``scene`` (direct simulator API) and
    assemble them as the runtime does.

    The head nods along ``design.spec.nod`` (triangle ramp starting at the lower pitch limit at
    ``t0_s``); the mirrors are deployed or lifted for the whole run. The simulator is built
    with ``perturbations`` (the sensor as built). The scans then go through the runtime's
    one projection path, :func:`nodlidar.runtime.assembly.assemble` (via
    :func:`nodlidar.tracking.recording.scans_from_capture`), with ``model``: the runtime's
    :class:`~nodlidar.runtime.assembly.AssemblyModel` (its calibration, its re-traced beam
    map). Default ``model``: the design calibrated exactly, i.e. built from the same
    ``perturbations`` (so the projection is exact up to range noise); pass
    ``AssemblyModel.from_design(design)`` for an uncalibrated runtime, or one from a
    calibration file. The nod samples handed to the assembly are the simulator's pitch at
    every beam time (a servo read per beam), so the only projection error is the model's.
    Points are placed in the world by the scene's (known) sensor pose.

    Returns
    -------
    list of ScanPoints (beams the assembly drops are absent), with ``truth_id`` from the
    simulator and ``calibration_id`` from ``model``.
    """
    from types import SimpleNamespace

    from ..runtime.assembly import AssemblyModel
    from ..sim.raycast import SceneSimulator
    from ..sim.scene import load_scene
    from .recording import scans_from_capture

    require(n_scans >= 1, "n_scans", n_scans, ">= 1")
    sim = simulator or SceneSimulator(design, load_scene(scene), perturbations)
    if model is None:
        model = AssemblyModel.from_design(design, perturbations,
                                          "simulated" if perturbations else "none")
    lift = 0.0 if mirrors_deployed else 1.0
    nod = None if t0_s == 0.0 else (lambda t: design.spec.nod.pitch_at(t, t0_s))
    truths = sim.scans(n_scans, t0_s=t0_s, nod=nod, lift_left=lift, lift_right=lift, noise=noise,
                       seed=seed)
    lidar = model.lidar
    raw, tid = [], np.full((len(truths), lidar.n_steps), -1, dtype=np.int64)
    for k, st in enumerate(truths):
        r = st.measured_m()
        # stamp = step 0's time (SPEC p.12), the convention the assembly's beam times use
        stamp = float(st.t_s[0] - st.steps[0] * lidar.step_period_s)
        raw.append(SimpleNamespace(steps=st.steps, ranges_m=r, stamp_s=stamp))
        tid[k, st.steps - lidar.step_min] = np.where(np.isfinite(r), st.object_id, -1)
    nod_t = np.concatenate([st.t_s for st in truths])
    nod_a = np.concatenate([st.nod_rad for st in truths])
    state = "deployed" if mirrors_deployed else "lifted"
    joints = {"nod": (nod_t, nod_a), "mirror_left": state, "mirror_right": state}
    return scans_from_capture(model, raw, joints, pose=sim.scene.sensor, truth_id=tid)


def _ray_cylinder(o, d, c_xy, radius, z0, z1):
    """Distance along rays ``o + s d`` to a vertical cylinder's side (inf: miss)."""
    ox, oy = o[:, 0] - c_xy[:, 0], o[:, 1] - c_xy[:, 1]
    a = d[:, 0] ** 2 + d[:, 1] ** 2
    b = 2 * (ox * d[:, 0] + oy * d[:, 1])
    c = ox ** 2 + oy ** 2 - radius ** 2
    disc = b * b - 4 * a * c
    with np.errstate(invalid="ignore", divide="ignore"):
        s = (-b - np.sqrt(disc)) / (2 * a)
    z = o[:, 2] + s * d[:, 2]
    ok = (disc > 0) & (s > 0) & (z >= z0) & (z <= z1)
    return np.where(ok, s, np.inf)


def synthetic_scans(beam_model: BeamModel, n_scans: int, *, speed_m_s: float = 0.13,
                    heading_rad: float = np.deg2rad(89.4),
                    start_xy: Sequence[float] = (2.0, -0.4),
                    radius_m: float = 0.18, height_m: float = 1.0, sensor_z_m: float = 0.4,
                    wall_x_m: float = 4.0, nod_min_rad: float = -0.35, nod_max_rad: float = 0.35,
                    nod_rate_rad_s: float = 0.35, sigma_m: float = 0.0,
                    seed: int = 0) -> list[ScanPoints]:
    """A small independent scene: a cylinder moving at constant velocity in front of a wall
    (plane x = ``wall_x_m``) and a floor (z = 0), seen along ``beam_model``'s rays with a
    linear nod ramp (triangle wave), the sensor base at (0, 0, ``sensor_z_m``), facing +x.

    Analytic ray intersection (no embree), so the unit tests do not depend on the simulator.
    Truth ids: 0 static (wall/floor), 1 cylinder, -1 none.
    """
    lidar = beam_model.lidar
    steps = lidar.steps
    rng = np.random.default_rng(seed)
    sweep = (nod_max_rad - nod_min_rad) / nod_rate_rad_s
    u = np.array([np.cos(heading_rad), np.sin(heading_rad)])
    lift = np.array([0.0, 0.0, sensor_z_m])
    out = []
    for k in range(n_scans):
        t = k * lidar.scan_period_s + lidar.time_offset_from_step(steps)
        ph = np.mod(t, 2 * sweep)
        nod = nod_min_rad + np.where(ph < sweep, ph, 2 * sweep - ph) * nod_rate_rad_s
        start, d, off = beam_model.rays(steps, nod)
        o = start + lift
        c = np.asarray(start_xy) + speed_m_s * t[:, None] * u
        s_cyl = _ray_cylinder(o, d, c, radius_m, 0.0, height_m)
        with np.errstate(divide="ignore", invalid="ignore"):
            s_wall = np.where(d[:, 0] > 1e-9, (wall_x_m - o[:, 0]) / d[:, 0], np.inf)
            s_floor = np.where(d[:, 2] < -1e-9, -o[:, 2] / d[:, 2], np.inf)
        s_static = np.minimum(s_wall, s_floor)
        s = np.minimum(s_cyl, s_static)
        tid = np.where(np.isfinite(s), np.where(s_cyl < s_static, 1, 0), -1)
        r = off + s + (rng.standard_normal(len(s)) * sigma_m if sigma_m else 0.0)
        r = np.where(np.isfinite(s) & (s < 5.6), r, np.nan)
        tid = np.where(np.isfinite(r), tid, -1)
        p = o + (r - off)[:, None] * d
        out.append(ScanPoints(scan=k, steps=steps, t_s=t, mirror=beam_model.mirror_index(steps),
                              range_m=r, points=p, ray_start=o, ray_dir=d, ray_offset=off,
                              truth_id=tid))
    return out
