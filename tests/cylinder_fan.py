"""An analytic scan of a moving cylinder, for tests independent of the simulator: a fan of
beams from the origin meets a circle, with range noise along each ray."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

BEAM_DEG = 0.352  # the URG-04LX's step


def cylinder_scans(v, c0, r, n, noise_m, seed, half_view_deg
                   ) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """Per scan (0.1 s, per-beam times across the fan of +-``half_view_deg``), a cylinder of
    radius ``r`` [m] moving at ``v`` [m/s] from ``c0`` [m]: the beams that meet it (indices
    into the fan), their unit directions (k, 2), the noisy ranges (k,) [m] and the times
    (k,) [s]. One ``standard_normal`` draw of k per scan, in scan order."""
    rng = np.random.default_rng(seed)
    b = np.radians(np.arange(-half_view_deg, half_view_deg + 1e-9, BEAM_DEG))
    d = np.column_stack([np.cos(b), np.sin(b)])
    for k in range(n):
        t = 0.1 * k + 0.1 * (b - b[0]) / (b[-1] - b[0])
        c = np.asarray(c0) + np.outer(t, v)
        dc = (d * c).sum(1)
        disc = dc ** 2 - (c ** 2).sum(1) + r ** 2
        hit = disc > 0
        rng_m = dc[hit] - np.sqrt(disc[hit]) + noise_m * rng.standard_normal(hit.sum())
        yield np.flatnonzero(hit), d[hit], rng_m, t[hit]
