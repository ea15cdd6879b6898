"""The transform validator (nodlidar.frames.check_transform) and the renamed frame names:
what passes, what is refused and what the refusal says (the parameter, the offending value
- not its shape - and what is allowed)."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_array_equal
from scipy.spatial.transform import Rotation

from nodlidar.errors import ParameterError
from nodlidar.frames import RENAMED, check_transform, refuse_renamed, renamed_hint
from nodlidar.geometry import TOL


def rigid(n: int, seed: int = 0) -> np.ndarray:
    """``n`` random rigid transforms (scipy's rotations: orthonormal to ~1e-16)."""
    rng = np.random.default_rng(seed)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.random(n, random_state=seed).as_matrix()
    T[:, :3, 3] = rng.normal(0, 10, (n, 3))
    return T


def test_rigid_transforms_pass_unchanged():
    T = rigid(50)
    assert_array_equal(check_transform(T, "T", stack=True), T)
    for one in T[:5]:
        assert_array_equal(check_transform(one.tolist(), "T"), one)


def test_every_reflection_refused_naming_its_index():
    """A reflection is orthonormal (R^T R = I), so only the determinant catches it: each
    random rotation times a mirror matrix is refused, in a stack by its own index."""
    T = rigid(20, seed=1)
    flip = np.diag([1.0, -1.0, 1.0])
    for k in (0, 7, 19):
        S = T.copy()
        S[k, :3, :3] = S[k, :3, :3] @ flip
        with pytest.raises(ParameterError, match=rf"det\(poses\[{k}\]\[:3, :3\]\) = -1\.0 .*"
                                                 "reflection"):
            check_transform(S, "poses", stack=True)
    with pytest.raises(ParameterError, match=r"det\(robot_from_sensor\[:3, :3\]\) = -1\.0"):
        check_transform(np.diag([-1.0, -1.0, -1.0, 1.0]), "robot_from_sensor")


def test_orthonormality_bound_is_geometry_tol():
    """A shear ``R (I + e diag(1, -1, 0))`` has ``max |R^T R - I| = 2e + e^2`` and
    ``det = 1 - e^2`` (so the determinant test does not interfere): just inside
    TOL.rotation passes, just outside is refused with the matrix shown, not its shape."""
    R = Rotation.from_rotvec([0.3, -0.2, 0.9]).as_matrix()
    T = np.eye(4)
    for e, ok in ((0.45 * TOL.rotation, True), (0.55 * TOL.rotation, False)):
        T[:3, :3] = R @ (np.eye(3) + e * np.diag([1.0, -1.0, 0.0]))
        if ok:
            check_transform(T, "world_from_robot")
            continue
        with pytest.raises(ParameterError) as exc:
            check_transform(T, "world_from_robot")
        msg = str(exc.value)
        assert msg.startswith("world_from_robot[:3, :3] = [[")
        assert f"{R[0, 0]:.4f}".rstrip("0") in msg and "(4, 4)" not in msg
        assert "orthonormal" in msg and f"{TOL.rotation:g}" in msg


def test_other_refusals_name_the_part_and_value():
    T = np.eye(4)
    T[3] = [0.0, 0.0, 0.1, 1.0]
    with pytest.raises(ParameterError, match=r"^T\[3\] = \[0\.0, 0\.0, 0\.1, 1\.0\].*\[0, 0, 0, 1\]"):
        check_transform(T, "T")
    T = np.eye(4)
    T[0, 3] = np.nan
    with pytest.raises(ParameterError, match=r"^T = \[\[1\.0, 0\.0, 0\.0, nan\].*finite"):
        check_transform(T, "T")
    with pytest.raises(ParameterError, match=r"^T\.shape = \(3, 3\).*\(4, 4\)"):
        check_transform(np.eye(3), "T")
    with pytest.raises(ParameterError, match=r"^T\.shape = \(4, 4\).*\(k, 4, 4\)"):
        check_transform(np.eye(4), "T", stack=True)
    with pytest.raises(ParameterError, match="^T = 'eye'"):
        check_transform("eye", "T")
    S = rigid(4)
    S[2, :3, :3] *= 2.0
    with pytest.raises(ParameterError, match=r"^poses\[2\]\[:3, :3\] = \[\["):
        check_transform(S, "poses", stack=True)


def test_renamed_hints():
    assert renamed_hint("robot2sensor") == ("robot2sensor was renamed robot_from_sensor (it maps "
                                            "sensor coordinates into the robot frame)")
    assert renamed_hint("world2robot", "--") == ("--world2robot was renamed --world-from-robot (it "
                                                 "maps robot coordinates into the world frame)")
    # every new name reads <to>_from_<from> with the frames of the old A2B the other way round
    for old, (new, meaning) in RENAMED.items():
        to, frm = old.split("2")
        assert new == f"{to}_from_{frm}"
        assert f"maps {frm} coordinates into the {to} frame" in meaning
    refuse_renamed({}, "f")
    with pytest.raises(TypeError, match=r"^f\(\): world2robot was renamed world_from_robot"):
        refuse_renamed({"world2robot": 1}, "f")
    with pytest.raises(TypeError, match=r"^f\(\) got an unexpected keyword argument 'x'"):
        refuse_renamed({"x": 1}, "f")
