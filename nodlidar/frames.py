"""Frame names and the one check of a user's rigid transform.

Transforms are named ``<to>_from_<from>`` (pytransform3d's convention, STYLE.md):
``robot_from_sensor`` maps coordinates in the sensor frame into the robot frame,
``p_robot = robot_from_sensor @ p_sensor``, so names chain like the product reads:
``world_from_sensor = world_from_robot @ robot_from_sensor``. Rotations are active
(docs/conventions.md, "Frames").

The runtime once called these ``robot2sensor`` and ``world2robot`` (the same matrices:
only the names changed); :data:`RENAMED` lists them, and :func:`refuse_renamed` answers the
old keywords with a one-line hint.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from .errors import ParameterError
from .geometry import TOL

__all__ = ["RENAMED", "check_transform", "refuse_renamed", "renamed_hint"]

#: Old transform names -> (new name, what the transform does).
RENAMED: Mapping[str, tuple[str, str]] = {
    "robot2sensor": ("robot_from_sensor", "it maps sensor coordinates into the robot frame"),
    "world2robot": ("world_from_robot", "it maps robot coordinates into the world frame"),
}


def renamed_hint(old: str, prefix: str = "") -> str:
    """One line saying that ``old`` (a key of :data:`RENAMED`) was renamed, and what the
    new name means; ``prefix`` (e.g. ``"--"``) is put before both names, and the
    underscores of the new one become dashes when it is ``"--"`` (a CLI flag)."""
    new, meaning = RENAMED[old]
    if prefix == "--":
        new = new.replace("_", "-")
    return f"{prefix}{old} was renamed {prefix}{new} ({meaning})"


def refuse_renamed(kwargs: Mapping[str, Any], func: str) -> None:
    """Raise ``TypeError`` for keyword arguments ``kwargs`` that ``func`` does not take:
    a renamed one with :func:`renamed_hint`, any other as Python itself would."""
    for key in kwargs:
        if key in RENAMED:
            raise TypeError(f"{func}(): {renamed_hint(key)}")
        raise TypeError(f"{func}() got an unexpected keyword argument {key!r}")


def _brief(a: np.ndarray) -> list:
    """A matrix as short nested lists (4 decimals) for an error message."""
    return np.round(np.asarray(a, dtype=float), 4).tolist()


def check_transform(T: Any, name: str, *, stack: bool = False) -> np.ndarray:
    """The validated rigid transform ``T`` as a float array.

    ``T`` must be a ``(4, 4)`` homogeneous transform (``(k, 4, 4)`` of them with
    ``stack``): finite, last row ``[0, 0, 0, 1]``, its ``R = T[:3, :3]`` orthonormal
    (``max |R^T R - I| <= geometry.TOL.rotation``) and a proper rotation
    (``|det R - 1| <= TOL.rotation``: a reflection, which would mirror the points, is
    refused).

    Raises
    ------
    ParameterError
        Naming ``name`` (with the index of the first bad one in a stack), showing the
        offending value (the matrix or its part, rounded) and what is allowed.
    """
    try:
        A = np.asarray(T, dtype=float)
    except (TypeError, ValueError):
        raise ParameterError(name, T, "a 4x4 homogeneous transform (numbers)") from None
    want = "(k, 4, 4)" if stack else "(4, 4)"
    ok_shape = (A.ndim == 3 and A.shape[1:] == (4, 4)) if stack else A.shape == (4, 4)
    if not ok_shape:
        raise ParameterError(f"{name}.shape", A.shape, f"{want} homogeneous transform(s)")
    S = A if stack else A[None]
    tol = TOL.rotation

    def where(i: int) -> str:
        return f"{name}[{i}]" if stack else name

    bad = ~np.all(np.isfinite(S), axis=(1, 2))
    if bad.any():
        i = int(np.argmax(bad))
        raise ParameterError(where(i), _brief(S[i]), "finite numbers")
    # component-major copies (a few contiguous (k,) vectors): a million poses (a
    # callable's, one per point) are checked in a fraction of a second
    last = np.ascontiguousarray(S[:, 3].T)  # (4, k)
    bad = np.max(np.abs(last - np.array([[0.0], [0.0], [0.0], [1.0]])), axis=0) > tol
    if bad.any():
        i = int(np.argmax(bad))
        raise ParameterError(f"{where(i)}[3]", _brief(S[i, 3]), "[0, 0, 0, 1] (a homogeneous "
                                                               "transform's last row)")
    R = S[:, :3, :3]
    C = np.ascontiguousarray(R.transpose(2, 1, 0))  # C[a, j] = component j of column a
    # R^T R - I by the columns' dot products, det R by their triple product
    G = np.einsum("ajk,bjk->abk", C, C)  # (3, 3, k), contiguous in k
    err = np.max(np.abs(G - np.eye(3)[:, :, None]), axis=(0, 1))
    bad = err > tol
    if bad.any():
        i = int(np.argmax(bad))
        raise ParameterError(f"{where(i)}[:3, :3]", _brief(R[i]),
                             f"a rotation: orthonormal, max |R^T R - I| <= {tol:g} "
                             f"(this one {err[i]:.3g})")
    det = np.sum(C[0] * np.cross(C[1], C[2], axis=0), axis=0)
    bad = np.abs(det - 1.0) > tol
    if bad.any():
        i = int(np.argmax(bad))
        raise ParameterError(f"det({where(i)}[:3, :3])", round(float(det[i]), 6),
                             "+1, a proper rotation (a reflection would mirror the points)")
    return A
