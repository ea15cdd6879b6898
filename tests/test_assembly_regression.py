"""Point assembly against fixtures saved from the implementation before the issue-16 speed
work (tests/data/assembly_regression/*.npz).

The optimisations (3x3 transforms as multiply-adds on columns instead of BLAS, structure of
arrays, per-beam scalars gathered instead of (n, 3) rows, per-step tables precomputed in the
model) must not change a result: every float field of the PointCloud (xyz, t, range_m,
nod_rad) to 1e-9 m / s and 1e-12 rad - a float64 point is exact to ~1e-15 m at 5 m, so the
tolerance leaves room only for an equivalent reordering of float64 operations, never for a
changed formula - and every integer/bool field (step, mirror, scan, lifted), the frame, the
mirror names and the drop counters (meta) equal.

The cases cover the sensor, robot and world frames (PoseTrack with several poses and with
one, a callable per-point pose, a fixed 4x4), mirrors deployed, lifted and lifting mid-scan
per side, a perturbed model with a range model and a moved nod pivot, error codes, ranges
shorter than the path to the mirror, beams outside the nod samples (dropped, clamped,
extrapolated), a single scan and several.

Regenerate the fixtures (only from a trusted implementation!) with
``.venv/bin/python tests/test_assembly_regression.py``.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(__file__).parent / "data" / "assembly_regression"
PAPER = ROOT / "design" / "urg04lx-paper.toml"
FIELDS_FLOAT = ("xyz", "t", "range_m")
FIELDS_ANGLE = ("nod_rad",)
FIELDS_INT = ("step", "mirror", "scan", "lifted")
META = ("beams", "error_codes", "no_nod", "mirror_moving", "blocked", "points")


def _ranges(rng, lidar, m: int, model) -> np.ndarray:
    """(m, n_steps) ranges [m]: uniform 0.2-5 m, 3 % error codes (NaN), a few zeros and
    negatives (also invalid), and 2 % shorter than the path to the step's mirror."""
    r = rng.uniform(0.2, 5.0, (m, lidar.n_steps))
    r[rng.random(r.shape) < 0.03] = np.nan
    r[rng.random(r.shape) < 0.005] = 0.0
    r[rng.random(r.shape) < 0.003] = -1.0
    tm = model.deployed.t_mirror[None, :] * np.ones((m, 1))
    short = (rng.random(r.shape) < 0.02) & (tm > 0)
    r[short] = tm[short] * rng.uniform(0.2, 0.95, short.sum())
    return r


def _pose_track(t0: float, t1: float, dt: float):
    from nodlidar.runtime.assembly import PoseTrack

    tp = np.arange(t0, t1 + dt / 2, dt)
    T = np.tile(np.eye(4), (len(tp), 1, 1))
    # yaw, a little roll and pitch (a full 3D slerp) and a translation
    from nodlidar.geometry import rot_x, rot_y, rot_z

    for k, t in enumerate(tp):
        T[k, :3, :3] = rot_z(0.4 * t + 0.1) @ rot_x(0.05 * np.sin(3 * t)) @ rot_y(0.03 * t)
        T[k, :3, 3] = (0.5 * t, -0.2 * t + 0.1, 0.02 * np.sin(2 * t))
    return PoseTrack(tp, T)


def _robot_from_sensor() -> np.ndarray:
    from nodlidar.geometry import rot_x, rot_z

    T = np.eye(4)
    T[:3, :3] = rot_z(0.3) @ rot_x(0.02)
    T[:3, 3] = (0.25, -0.05, 0.4)
    return T


def _cases() -> dict[str, object]:
    """name -> PointCloud from the current implementation."""
    from nodlidar.paper import TABLE_I_PERTURBATIONS
    from nodlidar.runtime.assembly import AssemblyModel, PoseTrack, ScanBatch, assemble
    from nodlidar.solver import solve
    from nodlidar.spec import load_design

    design = solve(load_design(PAPER))
    lid = design.lidar
    T = lid.scan_period_s
    model = AssemblyModel.from_design(design)
    rng = np.random.default_rng(16)
    out: dict[str, object] = {}

    # nod servo samples at 100 Hz covering scans 0..3 (the 4th scan's end falls outside)
    t_nod = np.arange(0.0, 3.7 * T, 0.01)
    nod = (t_nod, 0.3 * np.sin(2.0 * t_nod) - 0.05)

    # 1. sensor frame, mirrors deployed, 4 scans (the last partly without nod samples)
    b4 = ScanBatch.from_arrays(lid.steps, _ranges(rng, lid, 4, model), np.arange(4) * T + 0.02)
    out["sensor_deployed"] = assemble(model, b4, nod)
    # 2. the same beams, nod outside the samples clamped / extrapolated
    out["sensor_clamp"] = assemble(model, b4, nod, nod_outside="clamp")
    out["sensor_extrapolate"] = assemble(model, b4, nod, nod_outside="extrapolate",
                                         mirror_left="lifted")
    # 3. robot frame, left lifted, right deployed (strings), 3 scans
    b3 = ScanBatch.from_arrays(lid.steps, _ranges(rng, lid, 3, model), np.arange(3) * T + 0.01)
    out["robot_left_lifted"] = assemble(model, b3, nod, mirror_left="lifted",
                                        mirror_right="deployed", frame="robot",
                                        robot_from_sensor=_robot_from_sensor())
    # 4. world frame (PoseTrack), each side lifting mid-scan from servo samples: left goes
    # up during scan 1, right comes down during scan 2
    pl, pr = model.lift_left, model.lift_right
    assert pl is not None and pr is not None
    tl = np.array([0.0, 0.13, 0.16, 10.0])
    left = (tl, np.array([pl.deployed_rad, pl.deployed_rad, pl.lifted_rad, pl.lifted_rad]))
    tr = np.array([0.0, 0.21, 0.25, 10.0])
    right = (tr, np.array([pr.lifted_rad, pr.lifted_rad, pr.deployed_rad, pr.deployed_rad]))
    track = _pose_track(-0.1, 0.6, 0.07)
    out["world_lifting"] = assemble(model, b3, nod, mirror_left=left, mirror_right=right,
                                    frame="world", robot_from_sensor=_robot_from_sensor(),
                                    world_from_robot=track)
    # 5. perturbed model (Table I), a range model, the nod pivot moved off the origin,
    # ambiguous steps; world frame from a callable giving one pose per point
    pm = AssemblyModel.from_design(design, TABLE_I_PERTURBATIONS, "table-1",
                                   ambiguous_steps=[100, 300, 301, 600])
    piv = np.array([0.01, -0.004, 0.03])
    pm = dataclasses.replace(pm, deployed=dataclasses.replace(pm.deployed, pivot=piv),
                             lifted=dataclasses.replace(pm.lifted, pivot=piv),
                             range_offset_m=0.012, range_scale=-0.004)

    def world_fn(t):
        return track.at(t)

    out["world_perturbed_callable"] = assemble(pm, b3, nod, mirror_right="lifted",
                                               frame="world",
                                               robot_from_sensor=_robot_from_sensor(),
                                               world_from_robot=world_fn)
    # 6. single scan, fixed nod, world frame from one 4x4; and a one-pose PoseTrack
    b1 = ScanBatch.from_arrays(lid.steps, _ranges(rng, lid, 1, model), [0.55])
    W = track.at(np.array([0.3]))[0]
    out["single_fixed_pose"] = assemble(pm, b1, 0.12, frame="world",
                                        robot_from_sensor=_robot_from_sensor(),
                                        world_from_robot=W)
    out["single_one_pose_track"] = assemble(model, b1, -0.2, mirror_left=left,
                                            mirror_right=right, frame="world",
                                            robot_from_sensor=_robot_from_sensor(),
                                            world_from_robot=PoseTrack([0.0], W[None]))
    return out


def _pack(pc) -> dict[str, np.ndarray]:
    d = {f: np.asarray(getattr(pc, f)) for f in FIELDS_FLOAT + FIELDS_ANGLE + FIELDS_INT}
    d["frame"] = np.array(pc.frame)
    d["mirror_names"] = np.array(pc.mirror_names)
    d["meta"] = np.array([pc.meta[k] for k in META])
    return d


NAMES = ("sensor_deployed", "sensor_clamp", "sensor_extrapolate", "robot_left_lifted",
         "world_lifting", "world_perturbed_callable", "single_fixed_pose",
         "single_one_pose_track")


@pytest.fixture(scope="module")
def cases():
    return _cases()


@pytest.mark.parametrize("name", NAMES)
def test_assembly_matches_saved_outputs(cases, name):
    ref = np.load(DATA / f"{name}.npz")
    got = _pack(cases[name])
    assert sorted(ref.files) == sorted(got)
    for key in ref.files:
        if key in FIELDS_FLOAT:  # metres / seconds
            np.testing.assert_allclose(got[key], ref[key], rtol=0, atol=1e-9, err_msg=key)
        elif key in FIELDS_ANGLE:
            np.testing.assert_allclose(got[key], ref[key], rtol=0, atol=1e-12, err_msg=key)
        else:  # integer fields, frame, names and the drop counters: exactly
            assert got[key].dtype == ref[key].dtype, key
            np.testing.assert_array_equal(got[key], ref[key], err_msg=key)


def test_fixtures_exercise_what_they_claim():
    """The fixtures hold reflected, direct and lifted points, every drop reason and all
    three frames: otherwise a regression there would go unnoticed."""
    refs = [np.load(DATA / f"{n}.npz") for n in NAMES]
    mirror = np.concatenate([r["mirror"] for r in refs])
    lifted = np.concatenate([r["lifted"] for r in refs])
    meta = np.sum([r["meta"] for r in refs], axis=0)
    assert np.any(mirror >= 0) and np.any(mirror < 0) and np.any(lifted)
    assert np.all(meta[1:5] > 0), dict(zip(META, meta))  # error codes, no nod, moving, blocked
    assert {str(r["frame"]) for r in refs} == {"sensor", "robot", "world"}
    assert sum(len(r["t"]) for r in refs) > 10_000


if __name__ == "__main__":
    DATA.mkdir(parents=True, exist_ok=True)
    for name, pc in _cases().items():
        np.savez_compressed(DATA / f"{name}.npz", **_pack(pc))
        print("wrote", name, len(pc.t), pc.meta)
