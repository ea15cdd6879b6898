"""FROZEN BASELINE - the tolerance Monte Carlo kernel as it was before issue 16's speed work.

Copied unchanged from ``nodlidar/analysis/tolerance.py`` (``_problem``, ``_trace_mirror``,
``_sample``, ``_run_chunk``, ``_chunks``; commit "tolerance: regression fixtures ...") so
that ``benchmarks/bench_tolerance.py`` measures "new / today" in the same process and run,
interleaved, on a loaded machine. Used ONLY by the benchmark: never import it from the
package or the tests, and do not edit it (it is the yardstick). ``run_v0`` is the in-process
branch of the old ``monte_carlo``: chunks evaluated one after the other, concatenated at the
end.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nodlidar.analysis.tolerance import ToleranceSpec
from nodlidar.design import Design
from nodlidar.geometry import (
    bearing_of,
    directions_from_bearings,
    perturb_frames,
    ray_circle_exit,
    reflect,
    rot_x,
    rot_y,
    rot_z,
    wrap_angle,
)


def _mount_rotation(yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """``rot_z(yaw) @ rot_y(pitch) @ rot_x(roll)`` for arrays ``(n,)`` -> ``(n, 3, 3)``."""
    return rot_z(yaw) @ rot_y(pitch) @ rot_x(roll)


@dataclass(frozen=True, eq=False)
class _MirrorData:
    """Everything the batch needs about one mirror (plain arrays, cheap to pickle)."""

    name: str
    theta: np.ndarray        # (b,) beam bearings
    origin: np.ndarray       # (3,)
    normal: np.ndarray       # (3,) towards the lidar, as in the patch
    along: np.ndarray        # (3,)
    up: np.ndarray           # (3,)
    hinge_z: float
    extent: np.ndarray       # (4,) s_min, s_max, z_min, z_max
    t0: np.ndarray           # (b,) nominal path to the mirror (BeamModel)
    hit0: np.ndarray         # (b, 3)
    out0: np.ndarray         # (b, 3)


@dataclass(frozen=True, eq=False)
class _Problem:
    mirrors: tuple[_MirrorData, ...]
    sigma: np.ndarray        # (m, 3)
    lidar_sigma: np.ndarray  # (6,), LIDAR_COLUMNS
    distribution: str
    ranges: np.ndarray       # (r,)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(m.name for m in self.mirrors)


def _problem(design: Design, tol: ToleranceSpec, ranges_m=None) -> _Problem:
    bm = design.beam_model()
    lid = design.lidar
    data = []
    for m in design.mirrors:
        p = m.patch
        start, d, off = bm.rays(m.steps)
        data.append(_MirrorData(
            name=m.name, theta=lid.bearing_from_step(m.steps), origin=p.origin_,
            normal=p.normal_, along=p.along_, up=p.up_, hinge_z=float(p.hinge_z),
            extent=np.array([p.s_min, p.s_max, p.z_min, p.z_max]), t0=off, hit0=start, out0=d))
    names = tuple(m.name for m in design.mirrors)
    ranges = np.asarray(tol.ranges_m if ranges_m is None else ranges_m, dtype=float)
    return _Problem(mirrors=tuple(data), sigma=tol.sigma_array(names),
                    lidar_sigma=tol.lidar.as_array(), distribution=tol.distribution,
                    ranges=np.atleast_1d(ranges))


@dataclass(frozen=True, eq=False)
class SampleTrace:
    """One mirror's beams traced for ``n`` sampled builds (lidar frame).

    Attributes
    ----------
    name : str
    bearing : (n, b, r) float
        True bearing where each reflected beam crosses each arc [rad].
    points : (n, b, r, 3) float
        Those points [m].
    bearing_error : (n, b, r) float
        Bearing reported by the nominal BeamModel minus ``bearing`` [rad].
    range_error : (n, b, r) float
        Horizontal range reported minus true (true = the arc radius) [m].
    elevation : (n, b) float
        Angle of the reflected direction out of the scan plane, ``asin(dir_z)`` [rad].
    on_patch : (n, b) bool
        Whether the beam still hits its own finite mirror patch.
    """

    name: str
    bearing: np.ndarray
    points: np.ndarray
    bearing_error: np.ndarray
    range_error: np.ndarray
    elevation: np.ndarray
    on_patch: np.ndarray


def _trace_mirror(md: _MirrorData, dm: np.ndarray, dl: np.ndarray, ranges: np.ndarray,
                  keep_points: bool = True) -> SampleTrace:
    """Batched equivalent of ``patch.perturbed(...)`` then ``.transformed(...)`` + trace."""
    # 1-3. the mounting-error model, one frame per sample (the same function as
    # MirrorPatch.perturbed); 4. into the mis-mounted lidar's frame
    o, nrm, along, up = perturb_frames(md.origin, md.normal, md.along, md.up, md.hinge_z,
                                       dm[:, 0], dm[:, 1], dm[:, 2])
    RmT = np.swapaxes(_mount_rotation(dl[:, 0], dl[:, 1], dl[:, 5]), -1, -2)    # (n,3,3)
    off = RmT @ dl[:, 2:5, None]
    o = (RmT @ o[:, :, None] - off)[:, :, 0]
    nrm = (RmT @ nrm[:, :, None])[:, :, 0]
    along = (RmT @ along[:, :, None])[:, :, 0]
    up = (RmT @ up[:, :, None])[:, :, 0]
    # trace every beam (from O) on every sampled plane
    d0 = directions_from_bearings(md.theta)               # (b, 3)
    t = np.sum(o * nrm, -1)[:, None] / (nrm @ d0.T)       # (n, b) distance to the plane
    hit = t[..., None] * d0[None]                         # (n, b, 3)
    out = reflect(np.broadcast_to(d0, hit.shape), nrm[:, None, :])
    rel = hit - o[:, None, :]
    s = np.sum(rel * along[:, None, :], -1)
    z = np.sum(rel * up[:, None, :], -1)
    on = (t > 0) & (s >= md.extent[0]) & (s <= md.extent[1]) & (z >= md.extent[2]) & (z <= md.extent[3])
    # where each reflected ray leaves the arc (cylinder) of each radius: arc_point's
    # distance (ray_circle_exit) kept, as the measured path is t + that distance
    t_arc = np.stack([ray_circle_exit(hit, out, r) for r in ranges], -1)          # (n, b, r)
    P = hit[:, :, None, :] + t_arc[..., None] * out[:, :, None, :]
    # measured path length, projected with the nominal (runtime) model
    r_meas = t[..., None] + t_arc                                                  # (n, b, r)
    Q = md.hit0[None, :, None, :] + md.out0[None, :, None, :] * (r_meas - md.t0[None, :, None])[..., None]
    bearing = bearing_of(P)
    berr = wrap_angle(bearing_of(Q) - bearing)
    rerr = np.hypot(Q[..., 0], Q[..., 1]) - np.hypot(P[..., 0], P[..., 1])
    elev = np.arcsin(np.clip(out[..., 2], -1.0, 1.0))
    return SampleTrace(name=md.name, bearing=bearing, points=P if keep_points else P[..., 2:],
                       bearing_error=berr, range_error=rerr, elevation=elev, on_patch=on)


def _draw(rng: np.random.Generator, shape: tuple[int, ...], distribution: str) -> np.ndarray:
    if distribution == "normal":
        return rng.standard_normal(shape)
    return rng.uniform(-1.0, 1.0, shape)


def _sample(prob: _Problem, n: int, seed: np.random.SeedSequence) -> tuple[np.ndarray, np.ndarray]:
    """``(n, m, 3)`` mirror errors and ``(n, 6)`` lidar errors (:data:`LIDAR_COLUMNS`) for
    one chunk. The roll column is drawn last, so the other errors of a seed are the same
    as before it existed."""
    rng = np.random.default_rng(seed)
    dm = _draw(rng, (n, len(prob.mirrors), 3), prob.distribution) * prob.sigma[None]
    dl = _draw(rng, (n, 5), prob.distribution) * prob.lidar_sigma[None, :5]
    roll = _draw(rng, (n, 1), prob.distribution) * prob.lidar_sigma[None, 5:]
    return dm, np.c_[dl, roll]


def _run_chunk(prob: _Problem, n: int, seed: np.random.SeedSequence) -> dict[str, np.ndarray]:
    """Evaluate one chunk: per-sample, per-mirror summaries (float32 to keep big runs small)."""
    dm, dl = _sample(prob, n, seed)
    m, r = len(prob.mirrors), len(prob.ranges)
    out = {k: np.empty((n, m, r), np.float32)
           for k in ("bearing_error_max", "bearing_error_mean", "range_error_max", "height_max")}
    out["elevation_max"] = np.empty((n, m), np.float32)
    out["edge_misses"] = np.empty((n, m), np.int32)
    for i, md in enumerate(prob.mirrors):
        tr = _trace_mirror(md, dm[:, i], dl, prob.ranges, keep_points=False)
        out["bearing_error_max"][:, i] = np.max(np.abs(tr.bearing_error), axis=1)
        out["bearing_error_mean"][:, i] = np.mean(tr.bearing_error, axis=1)
        out["range_error_max"][:, i] = np.max(np.abs(tr.range_error), axis=1)
        out["height_max"][:, i] = np.max(np.abs(tr.points[..., 0]), axis=1)
        out["elevation_max"][:, i] = np.max(np.abs(tr.elevation), axis=1)
        out["edge_misses"][:, i] = np.count_nonzero(~tr.on_patch, axis=1)
    return out


def _chunks(samples: int, chunk_size: int) -> list[int]:
    n_full, rest = divmod(samples, chunk_size)
    return [chunk_size] * n_full + ([rest] if rest else [])


def run_v0(design: Design, tol: ToleranceSpec) -> dict[str, np.ndarray]:
    """The old ``monte_carlo(..., workers=0)``: every chunk in turn, concatenated at the end."""
    prob = _problem(design, tol)
    sizes = _chunks(tol.samples, tol.chunk_size)
    seeds = np.random.SeedSequence(tol.seed).spawn(len(sizes))
    chunks = [_run_chunk(prob, n, s) for n, s in zip(sizes, seeds, strict=True)]
    return {k: np.concatenate([r[k] for r in chunks]) for k in chunks[0]}
