"""Verification of a design by exact ray trace of every beam through the finite mirrors.

Independent of the solver's construction: every valid step is cast from the origin,
intersected with every finite mirror patch (first hit wins), reflected exactly, and its
reflected ray is checked against all other mirrors and the lidar housing cylinder up to
the lidar's maximum range. Bearings are measured where the beam crosses the arc of radius
D and compared with the target the solver assigned.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .design import Design
from .geometry import (
    CLEAR,
    DIRECT,
    HOUSING,
    TOL,
    MirrorPatch,
    Perturbation,
    arc_point,
    bearing_of,
    directions_from_bearings,
    ray_cylinder_hit,
    reflect,
    wrap_angle,
)

__all__ = ["Verification", "verify", "trace_beams"]


def trace_beams(patches: list[MirrorPatch], dirs: np.ndarray, max_range: float,
                housing_radius: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Cast rays from the origin through finite mirrors.

    Parameters
    ----------
    patches : list of MirrorPatch
    dirs : (n, 3) float
        Unit beam directions from the origin.
    max_range : float
        Path length [m] up to which reflected rays are checked for blocking.
    housing_radius : float
        Radius [m] of the housing cylinder that reflected rays must not enter.

    Returns
    -------
    hit : (n,) int
        Index of the first mirror hit, ``DIRECT`` (-1) for none.
    t : (n,) float
        Distance to that mirror (inf for none).
    out : (n, 3) float
        Direction after the mirror (the beam's own direction if none).
    blocker : (n,) int
        ``CLEAR`` (geometry.CLEAR, -1) if the path is clear, the index of a mirror hit by the reflected
        ray, or ``HOUSING`` (geometry.HOUSING, -2) if the reflected ray enters the housing.
    """
    n = len(dirs)
    origins = np.zeros((n, 3))
    T = np.stack([p.intersect(origins, dirs)[0] for p in patches]) if patches else np.full((1, n), np.inf)
    hit = np.argmin(T, axis=0)
    t = T[hit, np.arange(n)]
    hit = np.where(np.isfinite(t), hit, DIRECT)
    out = dirs.copy()
    blocker = np.full(n, CLEAR)
    for i, p in enumerate(patches):
        sel = np.nonzero(hit == i)[0]
        if not len(sel):
            continue
        o = dirs[sel] * t[sel, None]
        d = reflect(dirs[sel], p.normal_)
        out[sel] = d
        left = max_range - t[sel]
        for j, q in enumerate(patches):
            if j == i:
                continue
            tq = q.intersect(o, d)[0]
            blocked = (tq > TOL.block_ahead_m) & (tq < left) & (blocker[sel] == CLEAR)
            blocker[sel[blocked]] = j
        in_housing = ray_cylinder_hit(o, d, housing_radius, left) & (blocker[sel] == CLEAR)
        blocker[sel[in_housing]] = HOUSING
    return hit, t, out, blocker


@dataclass(frozen=True, eq=False)
class Verification:
    """Per-beam results of :func:`verify` (arrays over all valid steps, ``(n_steps,)``)."""

    design: Design
    steps: np.ndarray
    expected: np.ndarray
    hit: np.ndarray
    blocker: np.ndarray
    bearing_at_d: np.ndarray
    error: np.ndarray

    @property
    def wrong_mirror(self) -> np.ndarray:
        return self.hit != self.expected

    @property
    def n_blocked(self) -> int:
        """Beams that hit the wrong mirror (or none) or whose reflected path is blocked."""
        return int(np.count_nonzero(self.bad))

    def blocked_by_mirror(self) -> dict[str, int]:
        """Blocked-beam count per mirror (and ``"direct"``)."""
        bad = self.bad
        out = {"direct": int(np.count_nonzero(bad & (self.expected == DIRECT)))}
        for i, m in enumerate(self.design.mirrors):
            out[m.name] = int(np.count_nonzero(bad & (self.expected == i)))
        return out

    @property
    def bad(self) -> np.ndarray:
        """Beams that hit the wrong mirror (or none) or whose path is blocked, ``(n_steps,) bool``."""
        return self.wrong_mirror | (self.blocker != CLEAR)

    def unexpected_blocked(self) -> np.ndarray:
        """:attr:`bad` outside the design's ``placement.shadowed_steps``, ``(n_steps,) bool``."""
        ok = np.zeros(len(self.steps), bool)
        for lo, hi in self.design.spec.placement.shadowed_steps:
            ok |= (self.steps >= lo) & (self.steps <= hi)
        return self.bad & ~ok

    def describe_blocked(self, mask: np.ndarray | None = None) -> str:
        """Which beams are bad and why, e.g. ``"L1 steps 616..624 blocked by L2"``.

        Runs of consecutive steps with the same expected mirror and the same cause are
        merged; ``mask`` (default :attr:`bad`) selects the beams.
        """
        mask = self.bad if mask is None else mask
        names = [m.name for m in self.design.mirrors]

        def who(i: int) -> str:
            return "direct" if i < 0 else names[i]

        def cause(i: int) -> str:
            if self.blocker[i] == HOUSING:
                return "reflected into the housing"
            if self.blocker[i] >= 0:
                return f"blocked by {who(int(self.blocker[i]))}"
            return f"hit {who(int(self.hit[i]))} instead" if self.hit[i] >= 0 else "miss their mirror"

        parts: list[list] = []
        run: list = []
        for i in np.nonzero(mask)[0]:
            key = (who(int(self.expected[i])), cause(int(i)))
            if run and run[0] == key and run[2] == self.steps[i] - 1:
                run[2] = int(self.steps[i])
                continue
            if run:
                parts.append(run)
            run = [key, int(self.steps[i]), int(self.steps[i])]
        if run:
            parts.append(run)
        return "; ".join(f"{k[0]} steps {a}..{b} {k[1]}" for k, a, b in parts)

    def density_per_degree(self, bin_deg: float = 1.0) -> dict[str, list[float]]:
        """Beams per degree across the front window at D, against the bare lidar.

        Every beam that arrives unblocked is counted where it crosses the arc of radius D
        (its traced bearing); the gain of a bin is that count over the bare lidar's count
        of steps in the same bin. Returns ``{"edges_deg": (b+1,), "beams": (b,),
        "bare": (b,), "gain": (b,)}`` as lists; bins of ``bin_deg`` from the window's
        first to its last direct beam.
        """
        lid = self.design.lidar
        front = self.design.direct_steps
        lo, hi = np.degrees(lid.bearing_from_step(np.array([front[0], front[-1]])))
        nb = max(1, int(np.floor((hi - lo) / bin_deg)))
        edges = lo + bin_deg * np.arange(nb + 1)
        ok = ~self.bad
        b = np.degrees(self.bearing_at_d[ok])
        beams = np.histogram(b, edges)[0]
        bare = np.histogram(np.degrees(lid.bearing_from_step(lid.steps)), edges)[0]
        gain = np.where(bare > 0, beams / np.maximum(bare, 1), np.nan)
        return {"edges_deg": edges.tolist(), "beams": beams.tolist(), "bare": bare.tolist(),
                "gain": gain.tolist()}

    def density_gain(self) -> float:
        """Unblocked beams arriving within the front window at D per direct beam in it."""
        lid = self.design.lidar
        front = self.design.direct_steps
        half = lid.angular_resolution / 2
        lo, hi = lid.bearing_from_step(np.array([front[0], front[-1]]))
        b = self.bearing_at_d[~self.bad]
        return float(np.count_nonzero((b >= lo - half) & (b < hi + half)) / len(front))

    def interleave_pattern(self) -> list[dict]:
        """Which mirror fills each interleave slot along the front window (from the targets).

        Slot ``q`` of direct step ``g`` is ``g + q / slots_per_step`` of a step. Runs of
        direct steps with the same pattern are merged: ``[{"steps": [first, last],
        "slots": ["direct", "L1", "R1"]}, ...]`` (``"-"``: empty slot). The traced
        bearings' distance from these targets is :attr:`error`.
        """
        d = self.design
        k = d.spec.layout.slots
        lid = d.lidar
        front = d.direct_steps
        table = np.full((len(front), k), "-", dtype=object)
        table[:, 0] = "direct"
        for m in d.mirrors:
            pos = np.round(lid.step_from_bearing(m.target_bearing) * k).astype(int)
            g, q = np.divmod(pos, k)
            inside = (g >= front[0]) & (g <= front[-1])
            table[g[inside] - front[0], q[inside]] = m.name
        runs: list[dict] = []
        for g, trow in zip(front, table, strict=True):
            row = [str(x) for x in trow]
            if runs and runs[-1]["slots"] == row and runs[-1]["steps"][1] == g - 1:
                runs[-1]["steps"][1] = int(g)
            else:
                runs.append({"steps": [int(g), int(g)], "slots": row})
        return runs

    def mirror_errors(self, name: str) -> np.ndarray:
        """Bearing errors at D [rad] of one mirror's beams, ordered by step."""
        i = [m.name for m in self.design.mirrors].index(name)
        return self.error[self.expected == i]

    def summary(self) -> dict[str, dict[str, float]]:
        """Per mirror: RMS and max |bearing error| at D [rad], beams, blocked."""
        out = {}
        blocked = self.blocked_by_mirror()
        for m in self.design.mirrors:
            e = self.mirror_errors(m.name)
            out[m.name] = {"rms_error_rad": float(np.sqrt(np.mean(e**2))),
                           "max_error_rad": float(np.max(np.abs(e))),
                           "beams": int(len(e)), "blocked": blocked[m.name]}
        return out


def verify(design: Design, perturbations: dict[str, Perturbation] | None = None) -> Verification:
    """Trace every valid beam of ``design`` (optionally with perturbed mirrors)."""
    lidar = design.lidar
    steps = lidar.steps
    dirs = directions_from_bearings(lidar.bearing_from_step(steps))
    patches = design.patches(perturbations)
    hit, t, out, blocker = trace_beams(patches, dirs, lidar.range_max_m, lidar.housing_radius_m)
    origin = np.where(np.isfinite(t), t, 0.0)[:, None] * dirs
    p = arc_point(origin, out, design.design_distance_m)
    bearing = bearing_of(p)
    err = wrap_angle(bearing - design.target_bearing)
    return Verification(design=design, steps=steps, expected=design.mirror_of_step, hit=hit,
                        blocker=blocker, bearing_at_d=bearing, error=err)
