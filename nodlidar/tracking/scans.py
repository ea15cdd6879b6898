"""One scan as the tracking pipeline consumes it: world-frame points with per-beam time and
free-space rays.

:class:`ScanPoints` is the neutral type every source of scans produces (the runtime assembly
via :mod:`nodlidar.tracking.recording` for recordings and the live path, the simulator via
:mod:`nodlidar.tracking.simdata`) and that :mod:`nodlidar.tracking.segment` and the tracker
take. It lives here, not with the simulated source, so the live path imports nothing of the
simulation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["ScanPoints", "sensor_velocity"]


@dataclass(frozen=True, eq=False)
class ScanPoints:
    """One scan in the world frame. Arrays are over the scan's beams, ``(n,)`` / ``(n, 3)``.

    Attributes
    ----------
    scan : int
        Scan index.
    steps : (n,) int
    t_s : (n,) float
        Time of each beam [s].
    mirror : (n,) int
        Mirror index of the beam (-1 direct), from the runtime BeamModel.
    range_m : (n,) float
        Measured range (total path) [m]; NaN = no return.
    points : (n, 3) float
        World point [m] (NaN where no return).
    ray_start : (n, 3) float
        World start of the outgoing ray (the lidar, or the beam's hit on its mirror) [m].
    ray_dir : (n, 3) float
        World unit direction of the outgoing ray.
    ray_offset : (n,) float
        Path length before ``ray_start`` [m]: the point is ``start + (r - offset) dir``.
    truth_id : (n,) int or None
        Ground truth object id (-1 none, 0 static, 1 + k mover k), when known.
    calibration_id : str
        The calibration the points were projected with (``"none"``: the design as is).
    sensor_velocity_m_s : (3,) float or None
        World velocity of the sensor base over the scan [m/s] (a robot's known motion:
        :func:`sensor_velocity`); None: standing still, or not known. A beam fixed in the
        sensor moves with it (the tracker's speed across a window's edge is relative to it).
    """

    scan: int
    steps: np.ndarray
    t_s: np.ndarray
    mirror: np.ndarray
    range_m: np.ndarray
    points: np.ndarray
    ray_start: np.ndarray
    ray_dir: np.ndarray
    ray_offset: np.ndarray
    truth_id: np.ndarray | None = None
    calibration_id: str = "none"
    sensor_velocity_m_s: np.ndarray | None = None

    @property
    def valid(self) -> np.ndarray:
        """(n,) bool: beams with a return."""
        return np.isfinite(self.range_m)

    @property
    def t_mid_s(self) -> float:
        """Mean beam time of the scan [s] (NaN for a scan without beams)."""
        return float(np.mean(self.t_s)) if len(self.t_s) else float("nan")


def sensor_velocity(pose, t_s: np.ndarray) -> np.ndarray | None:
    """World velocity [m/s] (3,) of a sensor base ``pose`` (anything with ``to_world(p (n,
    3), t (n,))``, e.g. :class:`nodlidar.sim.scene.SensorPose`) over the beam times
    ``t_s`` [s]: the base origin's displacement from the first to the last time, divided by
    the span. None without a pose or a span."""
    t = np.asarray(t_s, float)
    if pose is None or not len(t) or not np.ptp(t) > 0:
        return None
    t0, t1 = float(t.min()), float(t.max())
    o = pose.to_world(np.zeros((2, 3)), np.array([t0, t1]))
    return (o[1] - o[0]) / (t1 - t0)
