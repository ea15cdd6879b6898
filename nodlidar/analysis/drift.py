"""Bearing drift of reflected beams with range (paper eqs 1-3, Figures 6 and 7).

A mirror is placed so that its beams interleave with the direct ones on the arc of radius
D (exactly for its anchor beam with ``placement.method = "anchor"``; in the RMS sense with
``"optimal"``). The reflected rays do not pass through the lidar origin (they fan out from
its mirror image), so the bearing at which a reflected beam is seen depends on the range.
This module computes, for every mirror (not only the paper's L1/L2):

* the actual bearing of each reflected beam where it crosses arcs of radius 0.4..6 m, by
  exact ray trace (:func:`~nodlidar.geometry.reflect_rays` and
  :func:`~nodlidar.geometry.arc_point` on the mirror patch) and by the paper's eq. 1
  (:func:`~nodlidar.closed_form.eq1_bearing_on_arc`);
* the angular separation between consecutive reflected beams (eq. 3's quantity);
* the interleave picture: where direct and reflected beams land at a few ranges, and the
  local beam density across the front window compared with no mirrors.

Compute only: no plotting here (see :mod:`nodlidar.analysis.plots`). SI units inside.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from ..closed_form import eq1_bearing_on_arc
from ..design import Design
from ..errors import ParameterError
from ..geometry import (
    DIRECT,
    Perturbation,
    arc_point,
    bearing_of,
    directions_from_bearings,
    incidence_angle,
    reflect_rays,
    wrap_angle,
)

__all__ = [
    "DEFAULT_RANGES_M",
    "MirrorDrift",
    "DriftResult",
    "bearing_drift",
    "InterleaveResult",
    "interleave",
    "DensityResult",
    "beam_density",
]

#: Arc radii of the paper's Figs 6-7 (40 cm .. 600 cm) [m].
DEFAULT_RANGES_M = np.array([0.4, 0.6, 0.8, 1.0, 1.5, 2.0, 3.0, 4.0, 5.0, 6.0])


def _check_ranges(ranges_m) -> np.ndarray:
    r = np.atleast_1d(np.asarray(ranges_m, dtype=float))
    if r.ndim != 1 or r.size == 0 or not np.all(np.isfinite(r)) or np.any(r <= 0):
        raise ParameterError("ranges_m", [float(x) for x in np.ravel(r)],
                             "one or more finite ranges > 0 m")
    return r


@dataclass(frozen=True, eq=False)
class MirrorDrift:
    """Drift of one mirror's beams. Ranges along axis 0, beams (ascending step) along axis 1.

    Attributes
    ----------
    name, side : str
    sign : int
        +1 left, -1 right.
    steps : (n,) int
        The mirror's beams, ascending.
    incident_bearing : (n,) float
        Bearing of each beam leaving the lidar [rad].
    target_bearing : (n,) float
        Where each should land on the arc of radius D [rad].
    ranges_m : (r,) float
        Arc radii [m].
    bearing_trace : (r, n) float
        Actual bearing where the reflected beam crosses each arc, exact trace [rad].
    bearing_closed : (r, n) float
        The same by eq. 1 [rad]; NaN where eq. 1 does not apply (arc radius not beyond
        the mirror hit point, i.e. M not beyond A).
    incidence_rad : (n,) float
        Angle of incidence on the mirror (eq. 1's theta_r) [rad].
    hit_range_m : (n,) float
        Range to the mirror along each beam (eq. 1's OZ) [m].
    """

    name: str
    side: str
    sign: int
    steps: np.ndarray
    incident_bearing: np.ndarray
    target_bearing: np.ndarray
    ranges_m: np.ndarray
    bearing_trace: np.ndarray
    bearing_closed: np.ndarray
    incidence_rad: np.ndarray
    hit_range_m: np.ndarray

    @property
    def eq1_valid(self) -> np.ndarray:
        """``(r, n) bool``: where eq. 1 applies (the arc lies beyond the hit point)."""
        return self.ranges_m[:, None] > self.hit_range_m[None, :]

    @property
    def closed_vs_trace(self) -> np.ndarray:
        """``(r, n)``: eq. 1 minus exact trace [rad] (NaN where eq. 1 does not apply)."""
        return wrap_angle(self.bearing_closed - self.bearing_trace)

    @property
    def error_from_target(self) -> np.ndarray:
        """``(r, n)``: actual bearing minus the interleave target (set for D) [rad]."""
        return wrap_angle(self.bearing_trace - self.target_bearing[None, :])

    @staticmethod
    def _sep(b: np.ndarray) -> np.ndarray:
        # A flat mirror reverses the fan: bearings fall as the step rises, so the
        # separation between consecutive beams is minus the step-wise difference.
        return -wrap_angle(np.diff(b, axis=-1))

    @property
    def separation_trace(self) -> np.ndarray:
        """``(r, n-1)``: bearing separation of consecutive reflected beams (exact) [rad]."""
        return self._sep(self.bearing_trace)

    @property
    def separation_closed(self) -> np.ndarray:
        """``(r, n-1)``: the same from eq. 1 [rad]."""
        return self._sep(self.bearing_closed)

    @property
    def first(self) -> int:
        """Column of the first beam (lowest step)."""
        return 0

    @property
    def last(self) -> int:
        """Column of the last beam (highest step)."""
        return len(self.steps) - 1


@dataclass(frozen=True, eq=False)
class DriftResult:
    """Drift of every mirror of a design, see :func:`bearing_drift`.

    Attributes
    ----------
    design_name : str
    design_distance_m : float
        The arc radius D the mirrors were placed for [m].
    resolution_rad : float
        The lidar's native angular step (pi/512 for a URG-04LX) [rad].
    ranges_m : (r,) float
    mirrors : tuple of MirrorDrift
    """

    design_name: str
    design_distance_m: float
    resolution_rad: float
    ranges_m: np.ndarray
    mirrors: tuple[MirrorDrift, ...]

    def mirror(self, name: str) -> MirrorDrift:
        for m in self.mirrors:
            if m.name == name:
                return m
        raise KeyError(f"no mirror {name!r}; have {', '.join(m.name for m in self.mirrors)}")

    @property
    def max_closed_vs_trace(self) -> float:
        """Largest |eq. 1 - trace| over every mirror, beam and range where eq. 1 applies [rad]."""
        return float(max(np.nanmax(np.abs(m.closed_vs_trace)) for m in self.mirrors))

    def first_last_table(self) -> list[dict[str, Any]]:
        """Per mirror: first and last beam's actual bearing [deg] on every arc.

        Plain data (lists, floats) for JSON and the CLI.
        """
        rows = []
        for m in self.mirrors:
            row: dict[str, Any] = {"name": m.name, "side": m.side}
            for key, col in (("first", m.first), ("last", m.last)):
                row[key] = {
                    "step": int(m.steps[col]),
                    "incident_bearing_deg": float(np.degrees(m.incident_bearing[col])),
                    "target_bearing_deg": float(np.degrees(m.target_bearing[col])),
                    "bearing_deg": [float(x) for x in np.degrees(m.bearing_trace[:, col])],
                }
            rows.append(row)
        return rows


def bearing_drift(design: Design, ranges_m: ArrayLike | None = None,
                  perturbations: dict[str, Perturbation] | None = None) -> DriftResult:
    """Actual bearing of every reflected beam on arcs of radius ``ranges_m``.

    Parameters
    ----------
    design : Design
        A solved design.
    ranges_m : (r,) float, optional
        Arc radii [m]; default :data:`DEFAULT_RANGES_M` (0.4 .. 6 m, as in the paper).
    perturbations : dict, optional
        Mirror name -> :class:`~nodlidar.geometry.Perturbation` for the trace (eq. 1 is
        always evaluated on the traced incidence and hit range, so it stays comparable).

    Returns
    -------
    DriftResult
    """
    ranges = _check_ranges(DEFAULT_RANGES_M if ranges_m is None else ranges_m)
    lid = design.lidar
    patches = design.patches(perturbations)
    out = []
    for m, patch in zip(design.mirrors, patches, strict=True):
        th = lid.bearing_from_step(m.steps)
        u = directions_from_bearings(th)
        t, hit, rdir = reflect_rays(np.zeros((len(th), 3)), u, patch.origin_, patch.normal_)
        trace = np.stack([bearing_of(arc_point(hit, rdir, r)) for r in ranges])
        incidence = incidence_angle(u, patch.normal_)
        with np.errstate(invalid="ignore"):  # arcs inside the mirror: NaN, masked below
            closed = eq1_bearing_on_arc(th[None, :], incidence[None, :], t[None, :],
                                        ranges[:, None], m.sign)
        valid = ranges[:, None] > t[None, :]
        closed = np.where(valid, wrap_angle(closed), np.nan)
        out.append(MirrorDrift(name=m.name, side=m.side, sign=m.sign, steps=m.steps.copy(),
                               incident_bearing=th, target_bearing=m.target_bearing.copy(),
                               ranges_m=ranges, bearing_trace=trace, bearing_closed=closed,
                               incidence_rad=incidence, hit_range_m=t))
    return DriftResult(design_name=design.spec.name, design_distance_m=design.design_distance_m,
                       resolution_rad=lid.angular_resolution, ranges_m=ranges, mirrors=tuple(out))


# ---------------------------------------------------------------------------------------
# interleave and density


@dataclass(frozen=True, eq=False)
class InterleaveResult:
    """Where every beam of the front window lands on a few arcs (the paper's Fig. 2b).

    Attributes
    ----------
    design_name : str
    ranges_m : (r,) float
    steps : (n,) int
        Every valid step that ends up in the front window (direct and reflected).
    mirror_index : (n,) int
        Index into ``mirror_names`` of each beam's mirror, ``DIRECT`` (-1) for direct beams.
    mirror_names : tuple of str
    points : (r, n, 3) float
        Where each beam crosses the arc (cylinder) of radius ``ranges_m[i]`` [m].
    bearing : (r, n) float
        Bearing of those points [rad].
    window_rad : (2,) float
        Bearing limits of the front (direct) window, half a step beyond its edge beams.
    resolution_rad : float
    hit : (n, 3) float
        Where each beam leaves its mirror (the origin for direct beams) [m].
    """

    design_name: str
    ranges_m: np.ndarray
    steps: np.ndarray
    mirror_index: np.ndarray
    mirror_names: tuple[str, ...]
    points: np.ndarray
    bearing: np.ndarray
    window_rad: np.ndarray
    resolution_rad: float
    hit: np.ndarray | None = None

    def gaps(self) -> list[np.ndarray]:
        """Per range, the sorted angular gaps between neighbouring beams inside the window."""
        out = []
        for b in self.bearing:
            inside = np.sort(b[(b >= self.window_rad[0]) & (b <= self.window_rad[1])])
            out.append(np.diff(inside))
        return out


def interleave(design: Design, ranges_m: ArrayLike = (0.4, 1.0, 2.0, 6.0),
               perturbations: dict[str, Perturbation] | None = None) -> InterleaveResult:
    """Landing points of all direct and reflected beams on arcs of radius ``ranges_m``.

    Uses the design's :class:`~nodlidar.beams.BeamModel` rays (exact per-beam paths) and
    :func:`~nodlidar.geometry.arc_point`.
    """
    ranges = _check_ranges(ranges_m)
    lid = design.lidar
    bm = design.beam_model(perturbations)
    steps = lid.steps
    start, d, _ = bm.rays(steps)
    pts = np.stack([arc_point(start, d, r) for r in ranges])
    res = lid.angular_resolution
    direct = design.direct_steps
    window = lid.bearing_from_step(np.array([direct[0], direct[-1]])) + np.array([-0.5, 0.5]) * res
    return InterleaveResult(design_name=design.spec.name, ranges_m=ranges, steps=steps,
                            mirror_index=bm.mirror_index(steps),
                            mirror_names=tuple(m.name for m in design.mirrors), points=pts,
                            bearing=bearing_of(pts), window_rad=window, resolution_rad=res,
                            hit=start)


@dataclass(frozen=True, eq=False)
class DensityResult:
    """Local beam density across the front window, with and without mirrors.

    Attributes
    ----------
    ranges_m : (r,) float
    bin_edges_rad : (b+1,) float
        Bearing bins spanning the front window [rad].
    density_per_rad : (r, b) float
        Beams per radian in each bin with the mirrors deployed, per arc.
    density_no_mirrors_per_rad : (b,) float
        The same with the mirrors lifted (direct beams only; range independent).
    max_gap_rad : (r,) float
        Largest angular gap between neighbouring beams inside the window, per arc [rad].
    median_gap_rad : (r,) float
        Median gap [rad] (a third of a step where the interleave is perfect).
    resolution_rad : float
    """

    design_name: str
    ranges_m: np.ndarray
    bin_edges_rad: np.ndarray
    density_per_rad: np.ndarray
    density_no_mirrors_per_rad: np.ndarray
    max_gap_rad: np.ndarray
    median_gap_rad: np.ndarray
    resolution_rad: float

    @property
    def bin_centres_rad(self) -> np.ndarray:
        return 0.5 * (self.bin_edges_rad[1:] + self.bin_edges_rad[:-1])

    @property
    def gain(self) -> np.ndarray:
        """``(r, b)``: density with mirrors over density without."""
        with np.errstate(divide="ignore", invalid="ignore"):
            return self.density_per_rad / self.density_no_mirrors_per_rad[None, :]


def beam_density(result: InterleaveResult, bin_width_rad: float = np.radians(4.0)) -> DensityResult:
    """Beams per radian across the front window from an :func:`interleave` result."""
    lo, hi = result.window_rad
    n_bins = max(1, int(round((hi - lo) / bin_width_rad)))
    edges = np.linspace(lo, hi, n_bins + 1)
    width = np.diff(edges)
    dens = np.stack([np.histogram(b, edges)[0] / width for b in result.bearing])
    direct = result.mirror_index == DIRECT
    # without mirrors only the direct beams reach the front window (bearing = their own)
    no_mirrors = np.histogram(result.bearing[0, direct], edges)[0] / width
    gaps = result.gaps()
    return DensityResult(design_name=result.design_name, ranges_m=result.ranges_m,
                         bin_edges_rad=edges, density_per_rad=dens,
                         density_no_mirrors_per_rad=no_mirrors,
                         max_gap_rad=np.array([g.max() for g in gaps]),
                         median_gap_rad=np.array([np.median(g) for g in gaps]),
                         resolution_rad=result.resolution_rad)
