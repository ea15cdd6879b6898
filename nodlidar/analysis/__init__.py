"""Design analysis: bearing drift with range, interleave, tolerance Monte Carlo, report.

Compute functions live in :mod:`.drift` and :mod:`.tolerance` (numpy only); figures in
:mod:`.plots` and the report in :mod:`.report` import matplotlib lazily, and Dask is only
imported when a Monte Carlo run asks for it, so ``import nodlidar.analysis`` stays light.
"""

from .drift import (
    DEFAULT_RANGES_M,
    DensityResult,
    DriftResult,
    InterleaveResult,
    MirrorDrift,
    beam_density,
    bearing_drift,
    interleave,
)

__all__ = [
    "DEFAULT_RANGES_M",
    "DensityResult",
    "DriftResult",
    "InterleaveResult",
    "MirrorDrift",
    "beam_density",
    "bearing_drift",
    "interleave",
]
