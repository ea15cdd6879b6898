"""BeamModel: (step, range[, nod angle]) -> 3D point, for direct and reflected beams.

The runtime's projection, built from a solved :class:`~nodlidar.design.Design` (plus a
calibration's perturbations; ``Design.beam_model``). Per valid step it precomputes, once, the exact path: the
hit point on its mirror and the reflected direction (:func:`~nodlidar.geometry.reflect_rays`
on the perturbed patch), so projecting a scan is a gather and a multiply-add, vectorised
over beams.

A measured range ``r`` of a reflected beam is the total path length: ``t_m`` to the mirror
then ``r - t_m`` along the reflected direction. Points are in the head frame (nod = 0) or,
given per-beam nod angles, in the sensor base frame: ``p = R_y(nod) (p_head - pivot) + pivot``
(:func:`~nodlidar.geometry.pitch_about_pivot`).
Which beams a mirror takes comes from the design (the runtime cannot see misses); whether a
perturbed mirror still catches them is for :func:`nodlidar.verify.verify` to check.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike

from .geometry import (
    DIRECT,
    MirrorPatch,
    Perturbation,
    directions_from_bearings,
    pitch_about_pivot,
    reflect_rays,
)
from .lidar import LidarModel

__all__ = ["BeamModel", "DIRECT"]   # DIRECT: geometry.DIRECT, re-exported


class _SolvedDesign(Protocol):
    """What :meth:`BeamModel.from_design` needs of a design (``nodlidar.design.Design``,
    which sits above this module: it builds its BeamModel with :meth:`BeamModel.build`)."""

    def beam_model(self, perturbations: dict[str, Perturbation] | None = None,
                   mirrors_deployed: bool = True) -> BeamModel: ...


@dataclass(frozen=True, eq=False)
class BeamModel:
    """Exact beam geometry of every valid step.

    Attributes
    ----------
    lidar : LidarModel
    mirror_names : tuple of str
    mirror_of_step : (n_steps,) int
        Mirror index per valid step (``DIRECT`` = -1: direct).
    dir0 : (n_steps, 3) float
        Direction of each beam leaving the lidar.
    t_mirror : (n_steps,) float
        Path length to the mirror [m] (0 for direct beams).
    hit : (n_steps, 3) float
        Where the beam leaves its mirror (the origin for direct beams) [m].
    dir1 : (n_steps, 3) float
        Direction after the mirror (= ``dir0`` for direct beams).
    pivot : (3,) float
        Nod axis point [m].
    """

    lidar: LidarModel
    mirror_names: tuple[str, ...]
    mirror_of_step: np.ndarray
    dir0: np.ndarray
    t_mirror: np.ndarray
    hit: np.ndarray
    dir1: np.ndarray
    pivot: np.ndarray

    @classmethod
    def build(cls, lidar: LidarModel, patches: list[MirrorPatch], mirror_of_step: np.ndarray,
              pivot: ArrayLike = (0.0, 0.0, 0.0)) -> BeamModel:
        """Precompute paths; ``mirror_of_step`` may be all ``DIRECT`` (mirrors lifted)."""
        th = lidar.bearing_from_step(lidar.steps)
        dir0 = directions_from_bearings(th)
        t_m = np.zeros(len(th))
        hit = np.zeros_like(dir0)
        dir1 = dir0.copy()
        for i, p in enumerate(patches):
            sel = mirror_of_step == i
            if not np.any(sel):
                continue
            t, h, out = reflect_rays(np.zeros((sel.sum(), 3)), dir0[sel], p.origin_, p.normal_)
            t_m[sel], hit[sel], dir1[sel] = t, h, out
        return cls(lidar=lidar, mirror_names=tuple(p.name for p in patches),
                   mirror_of_step=np.asarray(mirror_of_step, dtype=int), dir0=dir0,
                   t_mirror=t_m, hit=hit, dir1=dir1, pivot=np.asarray(pivot, dtype=float))

    @classmethod
    def from_design(cls, design: _SolvedDesign,
                    perturbations: dict[str, Perturbation] | None = None,
                    *, mirrors_deployed: bool = True) -> BeamModel:
        """The BeamModel of a solved design (mirrors perturbed and/or lifted): the same as
        ``design.beam_model(...)``, kept for older callers."""
        return design.beam_model(perturbations, mirrors_deployed=mirrors_deployed)

    # ------------------------------------------------------------------------------
    def _index(self, steps: np.ndarray) -> np.ndarray:
        steps = np.asarray(steps)
        self.lidar.check_step(steps, "steps")
        return steps.astype(int) - self.lidar.step_min

    def mirror_index(self, steps: np.ndarray) -> np.ndarray:
        """Mirror index (``DIRECT`` = -1: direct) of each step. Same shape as ``steps``."""
        return self.mirror_of_step[self._index(steps)]

    def points(self, steps: np.ndarray, ranges_m: np.ndarray,
               nod_rad: np.ndarray | float | None = None) -> np.ndarray:
        """Project measurements to 3D.

        Parameters
        ----------
        steps : (n,) int
            Valid lidar steps.
        ranges_m : (n,) float
            Measured ranges (total path length) [m]. NaN stays NaN.
        nod_rad : (n,) float or float, optional
            Nod (pitch) angle of the head at each beam's time [rad]; ``None`` gives points
            in the head frame.

        Returns
        -------
        (n, 3) float
            Points [m]. A reflected beam whose range is shorter than its path to the mirror
            (something in front of the mirror) is placed along its outgoing direction.
        """
        i = self._index(steps)
        r = np.asarray(ranges_m, dtype=float)
        t_m = self.t_mirror[i]
        before = r < t_m  # the beam stopped before reaching its mirror
        rr = np.where(before, r, r - t_m)[:, None]
        p = np.where(before[:, None], self.dir0[i] * rr, self.hit[i] + self.dir1[i] * rr)
        if nod_rad is None:
            return p
        nod = np.broadcast_to(np.asarray(nod_rad, dtype=float), r.shape)
        return pitch_about_pivot(p, nod, self.pivot)

    def rays(self, steps: np.ndarray, nod_rad: np.ndarray | float | None = None
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Outgoing rays of ``steps``: ``(start (n,3), direction (n,3), path offset (n,))``.

        A point at measured range ``r`` is ``start + (r - offset) * direction``; useful for
        ray casting (simulator) and free-space carving (segmentation).
        """
        i = self._index(steps)
        start, d, off = self.hit[i], self.dir1[i], self.t_mirror[i]
        if nod_rad is None:
            return start, d, off
        nod = np.broadcast_to(np.asarray(nod_rad, dtype=float), off.shape)
        return pitch_about_pivot(start, nod, self.pivot), pitch_about_pivot(d, nod), off
