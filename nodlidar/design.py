"""The solved design: :class:`MirrorSolution` (one placed mirror) and :class:`Design`.

Data, not the solver: :func:`nodlidar.solver.solve` makes them; the runtime
(:class:`~nodlidar.beams.BeamModel`), the verification (:mod:`nodlidar.verify`), the CAD,
calibration and analyses read them. This module imports neither the solver nor the
verification, so they can all import it at top level (layers: geometry, lidar, spec ->
beams -> design -> verify -> solver). ``nodlidar.solver`` re-exports both names.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from .beams import BeamModel
from .geometry import (
    DIRECT,
    MirrorPatch,
    Perturbation,
    directions_from_bearings,
    incidence_angle,
    reflect_rays,
)
from .lidar import LidarModel
from .spec import DesignSpec

__all__ = ["MirrorSolution", "Design"]


@dataclass(frozen=True, eq=False)
class MirrorSolution:
    """One solved mirror.

    Attributes
    ----------
    name : str
        ``"L1"``, ``"R2"``...; 1 is the outermost mirror of its side.
    side : str
        ``"L"`` (y > 0) or ``"R"``.
    index : int
        1-based position on its side, counted from the outside.
    steps : (n,) int
        The beams this mirror takes, ascending.
    target_bearing : (n,) float
        Where each of them should land on the arc of radius D [rad].
    offset_index : int
        q: the beams sit ``q * res / k`` anticlockwise of a direct beam.
    patch : MirrorPatch
        The mirror as finite geometry (unperturbed, deployed).
    """

    name: str
    side: str
    index: int
    steps: np.ndarray
    target_bearing: np.ndarray
    offset_index: int
    patch: MirrorPatch
    lidar: LidarModel = field(repr=False)
    anchor: int = -1
    target_step: int = 0

    @property
    def sign(self) -> int:
        """+1 for the left side, -1 for the right (mirror symmetry of every formula)."""
        return 1 if self.side == "L" else -1

    @property
    def anchor_step(self) -> int:
        """The beam constructed to land exactly on its target (the paper's OZ).

        The outermost beam unless the design file names another; it may lie outside
        :attr:`steps` (a construction ray only, e.g. the mirrored step 43 of the paper's R1).
        """
        if self.anchor >= 0:
            return int(self.anchor)
        return int(self.steps[-1] if self.side == "L" else self.steps[0])

    @cached_property
    def _anchor_ray(self) -> tuple[float, np.ndarray, np.ndarray]:
        """Range to the (infinite) mirror plane, incident and reflected direction of the anchor beam."""
        u = directions_from_bearings(self.lidar.bearing_from_step(self.anchor_step))
        t, hit, out = reflect_rays(np.zeros((1, 3)), u[None], self.patch.origin_, self.patch.normal_)
        return float(t[0]), u, out[0]

    @property
    def first_step(self) -> int:
        return int(self.steps[0])

    @property
    def last_step(self) -> int:
        return int(self.steps[-1])

    @cached_property
    def _hits(self) -> tuple[np.ndarray, np.ndarray]:
        th = self.lidar.bearing_from_step(self.steps)
        t, hit, out = reflect_rays(np.zeros((len(th), 3)), directions_from_bearings(th), self.patch.origin_,
                                   self.patch.normal_)
        return t, out

    @property
    def hit_ranges_m(self) -> np.ndarray:
        """Distance from O to the mirror along each of its beams [m], ``(n,)``."""
        return self._hits[0]

    @property
    def oz_m(self) -> float:
        """Range to the mirror along the anchor beam, the paper's OZ [m]."""
        return self._anchor_ray[0]

    @property
    def incidence_rad(self) -> np.ndarray:
        """Angle of incidence of each beam on the mirror [rad], ``(n,)`` (paper's gamma)."""
        th = self.lidar.bearing_from_step(self.steps)
        return incidence_angle(directions_from_bearings(th), self.patch.normal_)

    @property
    def phi_rad(self) -> float:
        """Angle between the anchor beam and the mirror, the paper's phi [rad]."""
        _, u, _ = self._anchor_ray
        return float(np.pi / 2 - incidence_angle(u, self.patch.normal_))

    @property
    def oa_m(self) -> float:
        """Perpendicular distance from O to the anchor beam's reflected ray, the paper's OA [m]."""
        t, u, d = self._anchor_ray
        return float(np.linalg.norm(np.cross(-u * t, d)))

    @property
    def standoff_m(self) -> float:
        """Perpendicular distance from O to the mirror plane, the paper's d [m]."""
        return self.patch.standoff

    @property
    def beam_span_m(self) -> float:
        """Distance between the first and last beams' hit points, the paper's QZ [m]."""
        th = self.lidar.bearing_from_step(self.steps[[0, -1]])
        p = directions_from_bearings(th) * self.hit_ranges_m[[0, -1]][:, None]
        return float(np.linalg.norm(p[1] - p[0]))

    @property
    def length_m(self) -> float:
        """Length of the mirror patch, including the beam margins [m]."""
        return self.patch.length


@dataclass(frozen=True, eq=False)
class Design:
    """A solved design: the spec, the lidar, every mirror and the beam-to-mirror map.

    Attributes
    ----------
    spec : DesignSpec
    lidar : LidarModel
    mirrors : tuple of MirrorSolution
        Order L1, L2, ..., R1, R2, ...
    direct_steps : (n,) int
        The front window's steps (seen directly).
    shadowed_steps : (k,) int
        Valid steps the design gives up (``placement.shadowed_steps``) that the exact trace
        finds blocked: their reflection meets another mirror, so a one-reflection model
        (the runtime's BeamModel) must not project them. Ascending; found by
        :func:`~nodlidar.solver.solve` with :func:`~nodlidar.verify.verify`.
    """

    spec: DesignSpec
    lidar: LidarModel
    mirrors: tuple[MirrorSolution, ...]
    direct_steps: np.ndarray
    shadowed_steps: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=int))

    @property
    def design_distance_m(self) -> float:
        return self.spec.layout.design_distance_m

    def mirror(self, name: str) -> MirrorSolution:
        for m in self.mirrors:
            if m.name == name:
                return m
        raise KeyError(f"no mirror {name!r}; have {', '.join(m.name for m in self.mirrors)}")

    @cached_property
    def mirror_of_step(self) -> np.ndarray:
        """Index into :attr:`mirrors` of each valid step, ``DIRECT`` (-1) for direct beams.
        ``(n_steps,)``."""
        out = np.full(self.lidar.n_steps, DIRECT, dtype=int)
        for i, m in enumerate(self.mirrors):
            out[m.steps - self.lidar.step_min] = i
        return out

    @cached_property
    def target_bearing(self) -> np.ndarray:
        """Target bearing at D of every valid step (direct: its own bearing). ``(n_steps,)``."""
        out = self.lidar.bearing_from_step(self.lidar.steps)
        for m in self.mirrors:
            out[m.steps - self.lidar.step_min] = m.target_bearing
        return out

    def patches(self, perturbations: dict[str, Perturbation] | None = None) -> list[MirrorPatch]:
        """Mirror patches, optionally perturbed (mirror name -> Perturbation)."""
        perturbations = perturbations or {}
        return [m.patch.perturbed(perturbations[m.name]) if m.name in perturbations else m.patch
                for m in self.mirrors]

    def beam_model(self, perturbations: dict[str, Perturbation] | None = None,
                   mirrors_deployed: bool = True) -> BeamModel:
        """The runtime :class:`~nodlidar.beams.BeamModel` of this design (mirrors perturbed
        and/or lifted: lifted, every beam goes direct)."""
        mos = self.mirror_of_step if mirrors_deployed else np.full(self.lidar.n_steps, DIRECT)
        return BeamModel.build(self.lidar, self.patches(perturbations), mos, self.spec.nod.pivot_m)
