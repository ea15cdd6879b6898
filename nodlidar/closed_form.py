"""The paper's closed forms, implemented as printed (with its typos fixed where noted).

These exist to be compared with the exact model (:mod:`nodlidar.geometry`,
:class:`~nodlidar.beams.BeamModel`); where they disagree, the exact model wins.

Frame mapping: the paper measures bearings from its axis X'; here every bearing is the
sensor-frame bearing (anticlockwise from +x). For a left-side mirror the reflection turns
a beam clockwise past the reversed incident direction, so eq. 1 holds as printed with
``sign = +1``; for a right-side mirror everything is mirrored (``sign = -1``).

Eq. 1 (exact geometry): with A the foot of the perpendicular from O onto the reflected
ray, ``ZA = OZ cos(2 theta_r)`` and ``OA = OZ sin(2 theta_r)``; for the point M of the ray
at distance D from O (beyond A), ``AM = sqrt(D^2 - OA^2)`` and::

    theta_a = theta_b + sign * (2 theta_r + arccos(AM / D) - pi)

Eqs. 4-8 (the calibration model) are *not* exact (see :func:`eq4_8_point`).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

__all__ = [
    "eq1_bearing_on_arc",
    "eq1_bearing_from_range",
    "eq2_drift",
    "eq3_separation_change",
    "eq4_8_point",
]


def eq1_bearing_on_arc(theta_b: ArrayLike, theta_r: ArrayLike, oz: ArrayLike, D: ArrayLike,
                       sign: int = 1) -> np.ndarray:
    """Eq. 1: actual bearing [rad] where a reflected beam crosses the arc of radius D.

    Parameters
    ----------
    theta_b : array_like
        Bearing of the incident beam [rad].
    theta_r : array_like
        Its angle of incidence (= reflection) on the mirror [rad].
    oz : array_like
        Range from O to the mirror along the beam [m].
    D : array_like
        Arc radius [m]; must exceed ``OA``, and M must lie beyond A (``ZM > ZA``).
    sign : +1 or -1
        +1 for a left-side mirror, -1 for a right-side one.

    All inputs broadcast; returns an array of the broadcast shape.
    """
    theta_b, theta_r, oz, D = np.broadcast_arrays(*map(lambda a: np.asarray(a, float),
                                                       (theta_b, theta_r, oz, D)))
    oa = oz * np.sin(2 * theta_r)
    am = np.sqrt(D**2 - oa**2)
    return theta_b + sign * (2 * theta_r + np.arccos(am / D) - np.pi)


def eq1_bearing_from_range(theta_b: ArrayLike, theta_r: ArrayLike, oz: ArrayLike, r: ArrayLike,
                           sign: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 1 for a measured (total path) range ``r`` [m]: bearing of the measured point.

    ``ZM = r - OZ``, ``AM = ZM - ZA``, and ``D = |OM| = sqrt(AM^2 + OA^2)``.
    Returns ``(theta_a, D)``.
    """
    theta_b, theta_r, oz, r = np.broadcast_arrays(*map(lambda a: np.asarray(a, float),
                                                       (theta_b, theta_r, oz, r)))
    za = oz * np.cos(2 * theta_r)
    oa = oz * np.sin(2 * theta_r)
    am = (r - oz) - za
    D = np.hypot(am, oa)
    return theta_b + sign * (2 * theta_r + np.arccos(am / D) - np.pi), D


def eq2_drift(theta_r: ArrayLike, oz: ArrayLike, D: ArrayLike, D_star: ArrayLike) -> np.ndarray:
    """Eq. 2: ``theta(D) - theta(D*)`` [rad] for the same beam at two arc radii (left side).

    For a right-side mirror negate the result.
    """
    oa = np.asarray(oz, float) * np.sin(2 * np.asarray(theta_r, float))
    am = np.sqrt(np.asarray(D, float) ** 2 - oa**2)
    am_s = np.sqrt(np.asarray(D_star, float) ** 2 - oa**2)
    return np.arccos(am / D) - np.arccos(am_s / D_star)


def eq3_separation_change(theta_r1: ArrayLike, oz1: ArrayLike, theta_r2: ArrayLike, oz2: ArrayLike,
                          D: ArrayLike, D_star: ArrayLike) -> np.ndarray:
    """Eq. 3: change of the angular separation of two consecutive reflected beams between
    arc radii D and D* [rad] (left side; negate for the right)."""
    return eq2_drift(theta_r1, oz1, D, D_star) - eq2_drift(theta_r2, oz2, D, D_star)


def eq4_8_point(r: ArrayLike, theta: ArrayLike, alpha: float, d: float, h: float,
                dalpha: float = 0.0, dbeta: float = 0.0, dd: float = 0.0) -> np.ndarray:
    """Eqs. 4-8 as printed: the paper's point for a reflected range measurement.

    Parameters
    ----------
    r : array_like
        Measured range [m].
    theta : array_like
        Bearing of the beam [rad], in the paper's convention (from its X' axis).
    alpha, d, h : float
        Mirror orientation [rad], perpendicular distance [m] and height above its hinge
        axis [m] (the paper's alpha, d, h).
    dalpha, dbeta, dd : float
        The perturbations (Table I).

    Returns
    -------
    (n, 3) float
        ``(x, y, z)`` per eqs. 7-8: ``x = r_a sin theta_a``, ``y = r_a cos theta_a``,
        ``z = r_p sin 2 dbeta``.

    Notes
    -----
    Implemented literally, including what makes it inexact (docs/paper-reproduction.md):
    eq. 5's second term is not squared, so it is not a Pythagorean sum; it is a
    normal-incidence form while these mirrors see beams at ~10-70 deg; eq. 6 subtracts the
    offset without eq. 5's ``cos 2 dbeta``; eq. 8 takes the height from the projected
    range rather than from the reflected path; and eq. 6's ``r_p`` mixes the mirror path
    with the reflected one. Tests measure how far it lands from the exact model.
    """
    r, theta = np.broadcast_arrays(np.asarray(r, float), np.asarray(theta, float))
    off = h * np.tan(dbeta) + d + dd
    tan_term = np.tan(alpha + dalpha - theta)
    r_p = r - (off * tan_term) * np.cos(2 * dbeta)                      # eq. 4
    r_a = np.sqrt(np.abs((r_p - off * np.cos(2 * dbeta)) ** 2 + off * tan_term))  # eq. 5
    theta_a = np.arctan2(r_p - off, off * tan_term) + (alpha + dalpha - theta - np.pi / 2)  # eq. 6
    x = r_a * np.sin(theta_a)                                            # eq. 7
    y = r_a * np.cos(theta_a)
    z = r_p * np.sin(2 * dbeta)                                          # eq. 8
    return np.stack([x, y, z], -1)
