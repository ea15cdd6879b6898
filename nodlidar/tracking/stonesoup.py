"""Optional converter between nodlidar track states and Stone Soup tracks.

Stone Soup's constant-velocity convention orders the state as ``(x, vx, y, vy)``; nodlidar's
:class:`~nodlidar.tracking.tracker.TrackState` covariance is over ``(x, y, vx, vy)``, so both
the vector and the covariance are permuted. Times become ``datetime`` (UTC) from the
state's ``t_s`` [s] since ``epoch``. Stone Soup is imported only when these functions run.
"""

from __future__ import annotations

import datetime as _dt
from collections.abc import Iterable
from typing import TYPE_CHECKING

import numpy as np

from .tracker import TrackState

if TYPE_CHECKING:
    from stonesoup.types.track import Track

__all__ = ["to_stonesoup", "from_stonesoup"]

_EPOCH = _dt.datetime(1970, 1, 1, tzinfo=_dt.UTC)
# (x, y, vx, vy) -> (x, vx, y, vy)
_PERM = np.array([0, 2, 1, 3])


def to_stonesoup(states: Iterable[TrackState], epoch: _dt.datetime = _EPOCH) -> list[Track]:
    """Group states by track id into ``stonesoup.types.track.Track`` of ``GaussianState``.

    Returns a list of Tracks (``Track.id`` = the track id as a string), states in time order.
    """
    from stonesoup.types.state import GaussianState
    from stonesoup.types.track import Track

    by_id: dict[int, list[TrackState]] = {}
    for s in states:
        by_id.setdefault(s.track_id, []).append(s)
    out = []
    for tid, ss in by_id.items():
        gs = []
        for s in sorted(ss, key=lambda s: s.t_s):
            vel = (s.v_m_s * np.cos(s.heading_rad), s.v_m_s * np.sin(s.heading_rad))
            vel = (0.0, 0.0) if np.isnan(s.v_m_s) else vel
            x = np.array([s.x_m, s.y_m, vel[0], vel[1]])[_PERM]
            cov = np.asarray(s.cov)[np.ix_(_PERM, _PERM)]
            gs.append(GaussianState(x.reshape(4, 1), cov,
                                    timestamp=epoch + _dt.timedelta(seconds=float(s.t_s))))
        out.append(Track(gs, id=str(tid)))
    return out


def from_stonesoup(tracks: Iterable[Track], epoch: _dt.datetime = _EPOCH) -> list[TrackState]:
    """Inverse of :func:`to_stonesoup` (scan = -1, counts 0, confirmed = True)."""
    out = []
    for tr in tracks:
        for g in tr.states:
            x = np.asarray(g.state_vector, float).ravel()
            inv = np.argsort(_PERM)
            xs = x[inv]
            cov = np.asarray(g.covar, float)[np.ix_(inv, inv)]
            v = float(np.hypot(xs[2], xs[3]))
            out.append(TrackState(int(tr.id), -1, (g.timestamp - epoch).total_seconds(),
                                  float(xs[0]), float(xs[1]), v, float(np.arctan2(xs[3], xs[2])),
                                  cov, 0, 0, True))
    return out
