"""Fast synthetic wall captures: the perturbed BeamModel's rays cut with a plane in closed form.

Not independent of the fit (both use :class:`~nodlidar.beams.BeamModel` and
:meth:`~nodlidar.geometry.MirrorPatch.perturbed`) - it is for quick unit tests and the
noise-free recovery check. The independent data source is the simulated sensor
(:mod:`nodlidar.sim`), a ray tracer with the mirrors as finite geometry.

A wall is a vertical plane in the sensor (base) frame, ``distance_m`` from the origin with
its outward normal at azimuth ``yaw_rad`` (``yaw = 0``: straight ahead, facing the sensor).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from ..beams import BeamModel
from ..errors import require
from ..geometry import BLOCKED, DIRECT, Perturbation, directions_from_bearings
from .fit import beam_map
from .walls import WallCapture

if TYPE_CHECKING:
    from ..design import Design
    from ..sim.scene import Scene

__all__ = ["WallPose", "DEFAULT_WALLS", "sweep_nod", "synthetic_capture", "synthetic_captures",
           "simulated_capture", "simulated_captures", "scene_captures", "with_range_error"]


@dataclass(frozen=True)
class WallPose:
    """A vertical wall in the sensor frame.

    Attributes
    ----------
    distance_m : float
        Perpendicular distance from the sensor origin [m].
    yaw_rad : float
        Azimuth of the wall's outward normal [rad] (0 = the wall faces the sensor head-on;
        positive = the sensor turned right relative to the wall, i.e. the wall's normal
        points to the left of +x).
    """

    distance_m: float
    yaw_rad: float = 0.0

    def __post_init__(self) -> None:
        require(float(self.distance_m) > 0, "wall distance", f"{float(self.distance_m):g} m", "> 0 m")
        # in degrees: the unit the user types (--yaw-deg)
        require(abs(float(self.yaw_rad)) < np.radians(60), "wall yaw",
                f"{np.degrees(float(self.yaw_rad)):g} deg", "|yaw| < 60 deg")

    @property
    def normal(self) -> np.ndarray:
        """Outward unit normal (3,)."""
        return directions_from_bearings(float(self.yaw_rad))

    @property
    def point(self) -> np.ndarray:
        """The wall point closest to the origin (3,) [m]."""
        return self.distance_m * self.normal


#: The paper's three orientations (Fig. 9: psi > pi/2, = pi/2, < pi/2), at 1 m: close
#: enough that the URG-04LX's range noise (1 cm to 1 m, 1 % beyond) keeps >= 95 % of
#: points inside the paper's +-2.25 cm band once calibrated.
DEFAULT_WALLS: tuple[WallPose, ...] = (
    WallPose(1.0, np.radians(-25.0)), WallPose(1.0, 0.0), WallPose(1.0, np.radians(25.0)),
)


def sweep_nod(design: Design, n_scans: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Steps and per-beam nod angles of one nod sweep (min -> max), all valid steps per scan.

    Each beam's nod is the ramp at its own time (:meth:`LidarModel.beam_time_s`), the ramp
    starting at its minimum when the first valid beam of scan 0 is taken.

    Returns
    -------
    steps : (n_scans * n_steps,) int
    nod_rad : (n_scans * n_steps,) float
    """
    lidar, nod = design.lidar, design.spec.nod
    if n_scans is None:
        n_scans = max(3, int(np.ceil(nod.sweep_period_s / lidar.scan_period_s)))
    t_scan = np.arange(n_scans) * lidar.scan_period_s
    t = (lidar.beam_time_s(t_scan[:, None], lidar.steps[None, :])
         - lidar.beam_time_s(0.0, lidar.step_min)).ravel()
    pitch = np.clip(nod.pitch_min_rad + t * nod.rate_rad_s, nod.pitch_min_rad, nod.pitch_max_rad)
    return np.tile(lidar.steps, n_scans), pitch


def synthetic_capture(design: Design, wall: WallPose,
                      perturbations: dict[str, Perturbation] | None = None,
                      *, rng: np.random.Generator | None = None, noise: bool = True,
                      quantum_m: float = 0.001, n_scans: int | None = None,
                      mirrors_deployed: bool = True, name: str = "") -> WallCapture:
    """One nodded sweep of ``wall`` by the sensor built with ``perturbations``.

    Ranges: the closed-form hit of each outgoing ray (exact, perturbed BeamModel) with the
    infinite wall plane, plus Gaussian noise of ``lidar.range_sigma_m`` (if ``noise``),
    rounded to ``quantum_m`` (the URG reports whole millimetres; 0 disables). Beams that
    never reach the wall, or beyond the lidar's range limits, are NaN. Which mirror each beam
    reaches is traced through the perturbed finite patches (:func:`~.fit.beam_map`, as the
    simulator and the runtime assembly do): a turned mirror folds beams of its neighbour's
    window; beams blocked on their way out are NaN.
    """
    rng = rng if rng is not None else np.random.default_rng(0)
    steps, nod = sweep_nod(design, n_scans)
    if mirrors_deployed:
        hit = beam_map(design, perturbations)
        blocked_step = hit == BLOCKED
        # a blocked beam is cast direct (it is NaN below whatever it meets)
        bm = BeamModel.build(design.lidar, design.patches(perturbations),
                             np.where(blocked_step, DIRECT, hit), design.spec.nod.pivot_m)
        blocked = blocked_step[steps - design.lidar.step_min]
    else:
        bm = design.beam_model(perturbations, mirrors_deployed=False)
        blocked = np.zeros(steps.shape, bool)
    start, d, off = bm.rays(steps, nod)
    n, p0 = wall.normal, wall.point
    with np.errstate(divide="ignore", invalid="ignore"):
        t = ((p0 - start) @ n) / (d @ n)
    r = np.where((t > 0) & ~blocked, off + t, np.nan)
    if noise:
        r = r + rng.standard_normal(r.shape) * design.lidar.range_sigma_m(np.nan_to_num(r))
    if quantum_m:
        r = np.round(r / quantum_m) * quantum_m
    lidar = design.lidar
    r = np.where((r >= lidar.range_min_m) & (r <= lidar.range_max_m), r, np.nan)
    return WallCapture(steps=steps, ranges_m=r, nod_rad=nod, mirrors_deployed=mirrors_deployed,
                       name=name or f"wall yaw {np.degrees(wall.yaw_rad):+.0f} deg")


def synthetic_captures(design: Design, perturbations: dict[str, Perturbation] | None = None,
                       walls: Iterable[WallPose] = DEFAULT_WALLS, *, seed: int = 0,
                       noise: bool = True, **kw: Any) -> list[WallCapture]:
    """:func:`synthetic_capture` for each wall, one seeded generator for all."""
    rng = np.random.default_rng(seed)
    return [synthetic_capture(design, w, perturbations, rng=rng, noise=noise, **kw) for w in walls]


def simulated_capture(design: Design, wall: WallPose,
                      perturbations: dict[str, Perturbation] | None = None,
                      *, seed: int = 0, noise: bool = True, n_scans: int | None = None,
                      name: str = "", size_m: tuple[float, float] = (8.0, 4.0),
                      scene: Scene | None = None) -> WallCapture:
    """One nodded sweep of ``wall`` by the simulated sensor (:mod:`nodlidar.sim`).

    The independent data source: an embree ray tracer with the mirrors as finite
    reflecting rectangles (``design.patches(perturbations)``), each beam cast at its own
    time and nod angle, and the URG measurement model (noise, mm rounding, range limits).

    ``scene`` (a :class:`~nodlidar.sim.scene.Scene`): capture that scene instead of a lone
    wall, the sensor turned by ``-wall.yaw_rad`` from the scene's own heading (so a wall
    straight ahead in the scene appears at azimuth ``wall.yaw_rad``, as with the lone
    wall); ``wall.distance_m`` is then not used - the scene places the walls.
    """
    from dataclasses import replace

    from ..sim.raycast import SceneSimulator
    from ..sim.scene import wall_scene

    if scene is None:
        scene = wall_scene(wall.distance_m, wall.yaw_rad, size_m)
    else:
        scene = replace(scene, sensor=replace(scene.sensor,
                                              yaw_rad=scene.sensor.yaw_rad - wall.yaw_rad))
    sim = SceneSimulator(design, scene, perturbations)
    lidar, nod = design.lidar, design.spec.nod
    if n_scans is None:
        n_scans = max(3, int(np.ceil(nod.sweep_period_s / lidar.scan_period_s)))
    steps, ranges, nods = [], [], []
    for k in range(n_scans):
        t_scan = k * lidar.scan_period_s
        # the nod ramp starts at the minimum when the first valid beam of scan 0 is taken
        t = sim.beam_times(t_scan) - lidar.beam_time_s(0.0, lidar.step_min)
        pitch = np.clip(nod.pitch_min_rad + t * nod.rate_rad_s, nod.pitch_min_rad, nod.pitch_max_rad)
        s = sim.scan(t_scan, pitch, noise=noise, rng=np.random.default_rng([seed, k]))
        steps.append(s.steps)
        ranges.append(s.measured_m())
        nods.append(s.nod_rad)
    return WallCapture(steps=np.concatenate(steps), ranges_m=np.concatenate(ranges),
                       nod_rad=np.concatenate(nods), mirrors_deployed=True,
                       name=name or f"wall yaw {np.degrees(wall.yaw_rad):+.0f} deg")


def simulated_captures(design: Design, perturbations: dict[str, Perturbation] | None = None,
                       walls: Iterable[WallPose] = DEFAULT_WALLS, *, seed: int = 0,
                       noise: bool = True, **kw: Any) -> list[WallCapture]:
    """:func:`simulated_capture` for each wall (seeds ``seed*100 + k``)."""
    return [simulated_capture(design, w, perturbations, seed=seed * 100 + k, noise=noise, **kw)
            for k, w in enumerate(walls)]


def scene_captures(design: Design, scene: Scene, yaws_rad: Iterable[float],
                   perturbations: dict[str, Perturbation] | None = None, *, seed: int = 0,
                   noise: bool = True, **kw: Any) -> list[WallCapture]:
    """One :func:`simulated_capture` of ``scene`` per sensor heading: the sensor turned by
    ``-yaw`` (so the scene's wall ahead appears at azimuth ``yaw``), seeds ``seed*100 + k``."""
    return [simulated_capture(design, WallPose(1.0, float(y)), perturbations, seed=seed * 100 + k,
                              noise=noise, scene=scene,
                              name=f"{scene.name} yaw {np.degrees(y):+.0f} deg", **kw)
            for k, y in enumerate(yaws_rad)]


def with_range_error(capture: WallCapture, offset_m: float = 0.0, scale: float = 0.0) -> WallCapture:
    """The capture as a lidar with a range error would report it:
    ``r_measured = (1 + scale) * r + offset_m`` (for the intrinsics fit)."""
    return WallCapture(steps=capture.steps, ranges_m=(1.0 + scale) * capture.ranges_m + offset_m,
                       nod_rad=capture.nod_rad, mirrors_deployed=capture.mirrors_deployed,
                       name=capture.name)
