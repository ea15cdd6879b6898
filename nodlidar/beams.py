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
from functools import cached_property
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

__all__ = ["BeamModel", "BeamColumns", "DIRECT", "cos_sin"]   # DIRECT: geometry.DIRECT, re-exported


class _SolvedDesign(Protocol):
    """What :meth:`BeamModel.from_design` needs of a design (``nodlidar.design.Design``,
    which sits above this module: it builds its BeamModel with :meth:`BeamModel.build`)."""

    def beam_model(self, perturbations: dict[str, Perturbation] | None = None,
                   mirrors_deployed: bool = True) -> BeamModel: ...


def cos_sin(angle_rad: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``cos`` and ``sin`` of angles (n,) [rad] from one ``tan`` of the half angle.

    ``t = tan(a/2)``: ``cos a = (1 - t^2) / (1 + t^2)``, ``sin a = 2 t / (1 + t^2)``,
    within a few ulp of ``np.cos``/``np.sin`` (2e-16 measured over +-3.1 rad). numpy's
    ``tan`` is vectorised (SIMD) where float64 ``cos`` and ``sin`` are not: this is
    ~4x faster than the pair (assembly turns every point by its nod and its pose). Exact
    for ``|a| <= pi``; NaN stays NaN.
    """
    t = np.tan(np.asarray(angle_rad, dtype=float) * 0.5)
    t2 = t * t
    # new arrays, not out=: some in-place variants of these ufuncs measured 4x slower here
    den = 1.0 / (1.0 + t2)
    return (1.0 - t2) * den, (2.0 * den) * t


@dataclass(frozen=True, eq=False)
class BeamColumns:
    """Per-row projection tables of one or more BeamModels, structure of arrays (each (m,)).

    A point of row ``i`` at range ``r`` is ``a + b r`` in the head frame minus the pivot
    (``a = hit - dir1 t_mirror - pivot``, ``b = dir1``), or ``dir0 r`` minus the pivot when
    ``r < t_mirror`` (stopped before its mirror). Rows are gathered as scalars per beam,
    never as (n, 3) rows; :meth:`project` is the one projection of the code base.

    Attributes
    ----------
    ax, ay, az, bx, by, bz : (m,) float
        Offset [m] and direction of each row.
    t_mirror : (m,) float
        Path length to the mirror [m] (0: direct).
    d0x, d0y, d0z : (m,) float
        Direction leaving the lidar.
    mirror : (m,) int16
        Mirror index of the row (``DIRECT`` = -1), the PointCloud's dtype.
    pivot : (3,) float, or (m, 3) when the rows' models have different pivots
        Nod axis point [m].
    """

    ax: np.ndarray
    ay: np.ndarray
    az: np.ndarray
    bx: np.ndarray
    by: np.ndarray
    bz: np.ndarray
    t_mirror: np.ndarray
    d0x: np.ndarray
    d0y: np.ndarray
    d0z: np.ndarray
    mirror: np.ndarray
    pivot: np.ndarray

    @cached_property
    def t_mirror_max(self) -> float:
        return float(self.t_mirror.max()) if self.t_mirror.size else 0.0

    @classmethod
    def of(cls, model: BeamModel, mirror: np.ndarray | None = None) -> BeamColumns:
        """The tables of ``model``; ``mirror`` (n_steps,) overrides its mirror indices."""
        a = model.hit - model.dir1 * model.t_mirror[:, None] - model.pivot
        d1, d0 = model.dir1, model.dir0
        c = np.ascontiguousarray
        return cls(ax=c(a[:, 0]), ay=c(a[:, 1]), az=c(a[:, 2]), bx=c(d1[:, 0]),
                   by=c(d1[:, 1]), bz=c(d1[:, 2]), t_mirror=c(model.t_mirror, dtype=float),
                   d0x=c(d0[:, 0]), d0y=c(d0[:, 1]), d0z=c(d0[:, 2]),
                   mirror=np.asarray(model.mirror_of_step if mirror is None else mirror,
                                     dtype=np.int16),
                   pivot=np.asarray(model.pivot, dtype=float))

    @classmethod
    def concat(cls, *tables: BeamColumns) -> BeamColumns:
        """Rows of ``tables`` one after another (row ``k m + i`` = row ``i`` of table k)."""
        names = ("ax", "ay", "az", "bx", "by", "bz", "t_mirror", "d0x", "d0y", "d0z", "mirror")
        cols = {n: np.concatenate([getattr(t, n) for t in tables]) for n in names}
        pivots = [np.broadcast_to(t.pivot, (len(t.ax), 3)) if t.pivot.ndim == 1 else t.pivot
                  for t in tables]
        same = all(t.pivot.ndim == 1 and np.array_equal(t.pivot, tables[0].pivot)
                   for t in tables)
        return cls(**cols, pivot=tables[0].pivot if same else np.concatenate(pivots))

    def project(self, rows: np.ndarray, r: np.ndarray, cos_nod: np.ndarray | None = None,
                sin_nod: np.ndarray | None = None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Points ``(x, y, z)`` (three (n,) arrays) [m] of ranges ``r`` (n,) [m] on table
        rows ``rows`` (n,) int, turned by the nod ``R_y`` (``cos_nod``, ``sin_nod`` (n,),
        e.g. from :func:`cos_sin`) about the pivot; without them, in the head frame.
        NaN ranges give NaN points."""
        x = self.ax.take(rows)
        y = self.ay.take(rows)
        z = self.az.take(rows)
        x += self.bx.take(rows) * r
        y += self.by.take(rows) * r
        z += self.bz.take(rows) * r
        if r.size and not (np.min(r) >= self.t_mirror_max):  # NaN too: then test each
            before = np.flatnonzero(r < self.t_mirror.take(rows))
            if before.size:  # stopped in front of its mirror: along the outgoing beam
                rb, rr = rows[before], r[before]
                pv = self.pivot if self.pivot.ndim == 1 else self.pivot[rb]
                x[before] = self.d0x[rb] * rr - pv[..., 0]
                y[before] = self.d0y[rb] * rr - pv[..., 1]
                z[before] = self.d0z[rb] * rr - pv[..., 2]
        if cos_nod is not None and sin_nod is not None:
            # p' = R_y(nod) p: x' = c x + s z, z' = -s x + c z (geometry.pitch_about_pivot)
            x, z = cos_nod * x + sin_nod * z, cos_nod * z - sin_nod * x
        if self.pivot.ndim == 2:
            pv = self.pivot[rows]
            x += pv[:, 0]
            y += pv[:, 1]
            z += pv[:, 2]
        elif np.any(self.pivot):
            x += self.pivot[0]
            y += self.pivot[1]
            z += self.pivot[2]
        return x, y, z


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
        shape = np.broadcast_shapes(np.shape(i), np.shape(ranges_m))
        i = np.broadcast_to(i, shape).ravel()  # any shape in, (..., 3) out
        r = np.broadcast_to(np.asarray(ranges_m, dtype=float), shape).ravel()
        c = s = None
        if nod_rad is not None:
            c, s = cos_sin(np.broadcast_to(np.asarray(nod_rad, dtype=float), shape).ravel())
        x, y, z = self.columns.project(i, r, c, s)
        out = np.empty((r.size, 3))
        out[:, 0], out[:, 1], out[:, 2] = x, y, z
        return out.reshape(shape + (3,))

    @cached_property
    def columns(self) -> BeamColumns:
        """The projection tables (:class:`BeamColumns`), one row per valid step."""
        return BeamColumns.of(self)

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
