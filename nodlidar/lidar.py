"""Scanning lidar models as data: step geometry, timing, range limits, housing.

Conventions (docs/conventions.md): sensor frame x forward (the front step), y left,
z up; bearing ``theta = atan2(y, x)`` anticlockwise positive; step ``s`` has
``theta = (s - front_step) * 2*pi / steps_per_rev`` (SCIP 2.0 ``AFRT``/``ARES``).
All Hokuyo scanners sweep anticlockwise seen from above, so within one scan the time
of step ``s`` after the scan's first valid step grows with ``s``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from .errors import ParameterError, require

__all__ = ["LidarModel", "LIDAR_MODELS", "lidar_model"]


@dataclass(frozen=True)
class LidarModel:
    """One scanner model, with the values its SCIP 2.0 ``PP`` command reports.

    Attributes
    ----------
    name : str
        Model name as used in design files (``"URG-04LX"``).
    steps_per_rev : int
        ``ARES``: angular steps in a full turn.
    step_min, step_max : int
        ``AMIN``/``AMAX``: first and last valid measurement step (inclusive).
    step_front : int
        ``AFRT``: the step pointing along +x.
    rpm : float
        ``SCAN``: mirror rotation speed [rev/min]; one scan per revolution.
    range_min_m, range_max_m : float
        ``DMIN``/``DMAX`` converted to metres.
    housing_half_width_m : float
        Half the side of the (square) housing around the optical axis [m]; the
        solver keeps mirrors clear of the circumscribed cylinder.
    housing_height_m : float
        Housing height [m] (CAD envelope).
    scan_plane_height_m : float
        Height of the scan plane above the housing base [m] (CAD envelope).
    head_radius_m : float
        Radius of the optical head around the axis at scan-plane height [m]: the part of
        the housing that mirrors must clear and reflected beams must not enter. The square
        body lies below the scan plane.
    range_noise : tuple[float, float, float]
        Range noise model ``(sigma_near_m, knee_m, rel_far)``: 1-sigma of
        ``sigma_near_m`` up to ``knee_m``, then ``rel_far * range`` beyond.
    """

    name: str
    steps_per_rev: int
    step_min: int
    step_max: int
    step_front: int
    rpm: float
    range_min_m: float
    range_max_m: float
    housing_half_width_m: float
    housing_height_m: float
    scan_plane_height_m: float
    head_radius_m: float
    range_noise: tuple[float, float, float] = (0.01, 1.0, 0.01)

    def __post_init__(self) -> None:
        require(self.steps_per_rev > 0, "lidar.steps_per_rev", self.steps_per_rev, "> 0")
        require(
            0 <= self.step_min <= self.step_front <= self.step_max < self.steps_per_rev,
            "lidar.steps",
            (self.step_min, self.step_front, self.step_max),
            "0 <= step_min <= step_front <= step_max < steps_per_rev",
        )
        require(self.rpm > 0, "lidar.rpm", self.rpm, "> 0")
        require(
            0 < self.range_min_m < self.range_max_m,
            "lidar.range_m",
            (self.range_min_m, self.range_max_m),
            "0 < range_min_m < range_max_m",
        )

    # -- derived quantities -------------------------------------------------------
    @property
    def angular_resolution(self) -> float:
        """Angle between consecutive steps [rad]."""
        return 2.0 * np.pi / self.steps_per_rev

    @property
    def scan_period_s(self) -> float:
        """Time of one revolution, i.e. one scan [s]."""
        return 60.0 / self.rpm

    @property
    def step_period_s(self) -> float:
        """Time between consecutive steps [s] (97.65625 us on a URG-04LX)."""
        return self.scan_period_s / self.steps_per_rev

    @property
    def n_steps(self) -> int:
        """Number of valid steps (682 on a URG-04LX)."""
        return self.step_max - self.step_min + 1

    @property
    def steps(self) -> np.ndarray:
        """All valid steps, ``(n_steps,) int``."""
        return np.arange(self.step_min, self.step_max + 1)

    @property
    def housing_radius_m(self) -> float:
        """Obstruction radius at scan-plane height [m] (alias of :attr:`head_radius_m`)."""
        return self.head_radius_m

    def bearing_from_step(self, step: np.ndarray | int | float) -> np.ndarray:
        """Bearing of ``step`` [rad] (anticlockwise from +x). Any shape; fractional ok."""
        return (np.asarray(step, dtype=float) - self.step_front) * self.angular_resolution

    def step_from_bearing(self, bearing: np.ndarray | float) -> np.ndarray:
        """Inverse of :meth:`bearing_from_step` (fractional steps)."""
        return np.asarray(bearing, dtype=float) / self.angular_resolution + self.step_front

    def time_offset_from_step(self, step: np.ndarray | int) -> np.ndarray:
        """Time of ``step`` after step ``step_min`` within one scan [s]: the difference of
        two :meth:`beam_time_s` (the one convention); prefer that."""
        return self.beam_time_s(0.0, step) - self.first_step_offset_s

    @property
    def first_step_offset_s(self) -> float:
        """Time from the SCIP timestamp (step 0) to the first valid step [s]:
        ``beam_time_s(0, step_min)``."""
        return float(self.beam_time_s(0.0, self.step_min))

    def beam_time_s(self, scan_time_s: ArrayLike, step: ArrayLike) -> np.ndarray:
        """Time of each beam [s] given its scan's SCIP timestamp time (step 0) [s].

        The one place the scan-time -> beam-time convention lives: ``scan_time_s`` refers to
        step 0 (SPEC p.12), so a beam of step ``s`` is ``s * step_period_s`` later.
        Broadcasts ``scan_time_s`` against ``step``.
        """
        return np.asarray(scan_time_s, dtype=float) + np.asarray(step, dtype=float) * self.step_period_s

    def range_sigma_m(self, range_m: np.ndarray | float) -> np.ndarray:
        """1-sigma range noise at ``range_m`` [m] per the spec's accuracy figure."""
        near, knee, rel = self.range_noise
        r = np.asarray(range_m, dtype=float)
        return np.where(r <= knee, near, rel * r)

    def check_step(self, step: np.ndarray | int, field: str = "step") -> None:
        """Raise :class:`ParameterError` if any step is outside ``[step_min, step_max]``."""
        s = np.asarray(step)
        if s.size and (s.min() < self.step_min or s.max() > self.step_max):
            bad = s[(s < self.step_min) | (s > self.step_max)].ravel()[0]
            raise ParameterError(field, int(bad), f"{self.step_min}..{self.step_max} for {self.name}")


# Values from each model's SCIP 2.0 PP reply (../shared/reference/scip2.md §1.5 for the
# URG-04LX; UTM-30LX-EW and UST-10LX from public device PP replies). Housing envelopes
# from the data sheets (URG-04LX 50x50x70 mm, UTM-30LX 60x60x87 mm, UST-10LX 50x50x70 mm);
# the optical-head radii and scan-plane heights are approximate envelopes read off the
# outline drawings (an assumption; a user with a different head sets their own model).
# The URG-04LX accuracy is +-30 mm to 1 m and +-3 % beyond (data sheet); we read the
# bound as 3 sigma. Noise for the others is their data sheet's figure read the same way.
LIDAR_MODELS: dict[str, LidarModel] = {
    m.name: m
    for m in (
        LidarModel(
            name="URG-04LX", steps_per_rev=1024, step_min=44, step_max=725, step_front=384,
            rpm=600.0, range_min_m=0.020, range_max_m=5.600,
            housing_half_width_m=0.025, housing_height_m=0.070, scan_plane_height_m=0.0415,
            head_radius_m=0.020, range_noise=(0.010, 1.0, 0.01),
        ),
        LidarModel(
            name="UTM-30LX", steps_per_rev=1440, step_min=0, step_max=1080, step_front=540,
            rpm=2400.0, range_min_m=0.023, range_max_m=60.0,
            housing_half_width_m=0.030, housing_height_m=0.087, scan_plane_height_m=0.0655,
            head_radius_m=0.025, range_noise=(0.010, 10.0, 0.001),
        ),
        LidarModel(
            name="UST-10LX", steps_per_rev=1440, step_min=0, step_max=1080, step_front=540,
            rpm=2400.0, range_min_m=0.020, range_max_m=30.0,
            housing_half_width_m=0.025, housing_height_m=0.070, scan_plane_height_m=0.0485,
            head_radius_m=0.022, range_noise=(0.0133, 30.0, 0.0),
        ),
    )
}


def lidar_model(name: str) -> LidarModel:
    """Look up a model by name (case-insensitive); raise naming the allowed ones."""
    for key, model in LIDAR_MODELS.items():
        if key.lower() == str(name).lower():
            return model
    raise ParameterError("lidar.model", name, "one of " + ", ".join(LIDAR_MODELS))
