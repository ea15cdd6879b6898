"""Calibration in a real room (issue 12): clutter, doorways, gates, ambiguous beams,
lidar intrinsics, the full covariance.

Data: the simulated sensor (embree ray tracer, finite mirrors, URG noise: 1 cm to 1 m, 1 %
beyond) built with the paper's Table I errors (or random ones), capturing the
``design/scenes/calib-*.toml`` scenes with the sensor turned to -25, 0 and +25 deg. The
accuracy target is the issue's: every mirror within 3 mrad / 1 mm, or refused by a gate.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from numpy.testing import assert_allclose

from nodlidar.calibration.calfile import load_calibration, read_calibration, write_calibration
from nodlidar.calibration.fit import CalibrationConfig, beam_map, calibrate
from nodlidar.calibration.synthetic import (
    DEFAULT_WALLS,
    WallPose,
    scene_captures,
    simulated_captures,
    synthetic_captures,
    with_range_error,
)
from nodlidar.cli import main
from nodlidar.errors import CalibrationError, ParameterError
from nodlidar.geometry import Perturbation
from nodlidar.paper import TABLE_I_PERTURBATIONS
from nodlidar.sim.scene import Opening, Wall, load_scene
from nodlidar.solver import solve
from nodlidar.spec import load_design

ROOT = Path(__file__).resolve().parents[1]
PAPER = ROOT / "design" / "urg04lx-paper.toml"
SCENES = ROOT / "design" / "scenes"
TRUTH = dict(TABLE_I_PERTURBATIONS)
YAWS = np.radians([-25.0, 0.0, 25.0])


@pytest.fixture(scope="module")
def design():
    return solve(load_design(PAPER))


@pytest.fixture(scope="module")
def table1_fit(design):
    caps = simulated_captures(design, TRUTH, seed=0)
    return caps, calibrate(design, caps)


def _within(result, truth=TRUTH) -> bool:
    """The issue's accuracy target for every mirror: 3 mrad, 3 mrad, 1 mm."""
    return all(abs(e[0]) <= 3e-3 and abs(e[1]) <= 3e-3 and abs(e[2]) <= 1e-3
               for e in (m.perturbation.as_array() - truth[n].as_array()
                         for n, m in result.mirrors.items()))


# -- scene format --------------------------------------------------------------------------
def test_wall_with_openings_is_the_wall_minus_the_holes():
    w = Wall((1.0, 0.0, 1.25), (-1.0, 0.0, 0.0), (6.0, 2.5),
             (Opening(0.6, 0.9, 2.0), Opening(-1.5, 1.0, 0.8, bottom_m=1.0)))
    rects = w.rects()
    area = sum((u1 - u0) * (z1 - z0) for u0, u1, z0, z1 in rects)
    # closed form: 15 m^2 minus a 1.8 m^2 door and a 0.8 m^2 window
    assert_allclose(area, 6.0 * 2.5 - 0.9 * 2.0 - 1.0 * 0.8, rtol=1e-12)
    assert_allclose(w.mesh().area, area, rtol=1e-12)  # the mesh covers exactly the solid part
    with pytest.raises(ParameterError, match="inside"):
        Wall((0, 0, 1), (1, 0, 0), (2.0, 2.0), (Opening(0.8, 0.9, 1.0),))
    with pytest.raises(ParameterError, match="horizontal"):
        Wall((0, 0, 1), (0, 0, 1), (2.0, 2.0))


def test_calib_scenes_load_and_the_doorway_shows_the_wall_behind(design):
    from nodlidar.sim.raycast import SceneSimulator

    for name in ("flat", "doorway", "doorway-side", "box", "pole", "kink"):
        sc = load_scene(SCENES / f"calib-{name}.toml")
        assert sc.name == f"calib-{name}" and sc.static_parts()
    sim = SceneSimulator(design, load_scene(SCENES / "calib-doorway.toml"))
    # a horizontal ray at the sensor's height through the door's centre (0.6 m right of the
    # foot point, i.e. y = -0.6) meets the wall behind at x = 2; one beside it the wall at x = 1
    o = np.array([[0.0, 0.0, 0.4], [0.0, 0.0, 0.4]])
    d = np.array([[1.0, -0.6, 0.0], [1.0, 0.6, 0.0]])
    d /= np.linalg.norm(d, axis=1)[:, None]
    dist, _, _ = sim.cast_world(o, d, np.zeros(2))
    assert_allclose(dist * d[:, 0], [2.0, 1.0], atol=1e-9)


# -- the rooms ----------------------------------------------------------------------
#: What each scene gives (measured, Table I, seed 0): recovered with every gate passed, or
#: refused naming the capture. The doorway beside the foot point leaves only 47 % of the
#: +25 deg capture's direct beams on the wall (the door, the wall behind and the floor take
#: the rest): refused; its mirrors were nevertheless within the target.
ROOMS = {
    "flat": None, "box": None, "pole": None, "doorway-side": None, "kink": None,
    "doorway": "calib-doorway yaw +25 deg: only",
}


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(ROOMS))
def test_room_is_calibrated_or_refused_with_the_reason(design, name):
    caps = scene_captures(design, load_scene(SCENES / f"calib-{name}.toml"), YAWS, TRUTH)
    res = calibrate(design, caps)
    # never a silent wrong fit: passing every gate implies the accuracy target
    assert not res.ok or _within(res), (name, res.problems)
    if ROOMS[name] is None:
        assert res.ok and _within(res), (name, res.problems)
        # clutter ends up as outliers: the walls' planes are at their true 1 m
        for c in res.captures:
            assert abs(c.distance_m - 1.0) < 0.005, (c.name, c.distance_m)
    else:
        assert any(p.startswith(ROOMS[name]) for p in res.problems), res.problems


@pytest.mark.slow
def test_cli_refuses_the_doorway_and_writes_nothing(capsys, tmp_path):
    out = tmp_path / "cal.toml"
    rc = main(["calibrate", "--sim", "--scene", str(SCENES / "calib-doorway.toml"),
               "--design", str(PAPER), "--out", str(out)])
    err = capsys.readouterr().err
    assert rc == 2 and not out.exists()
    lines = err.strip().splitlines()
    assert any("calib-doorway yaw +25 deg: only 4" in ln and "clear the wall" in ln for ln in lines)
    assert lines[-1].endswith("no calibration file written (--force writes it anyway)")
    assert "Traceback" not in err


def test_walls_closer_than_the_geometry_allows_are_refused(design, capsys):
    # issue: walls at 0.05-0.2 m were accepted with errors up to 58 mrad
    walls = [WallPose(0.1, np.radians(-25)), WallPose(0.15, 0.0), WallPose(0.2, np.radians(25))]
    caps = synthetic_captures(design, TRUTH, walls)
    with pytest.raises(CalibrationError, match="move the sensor back") as ei:
        calibrate(design, caps)
    assert len(str(ei.value).splitlines()) == 3  # one line per capture
    rc = main(["calibrate", "--sim", "--design", str(PAPER), "--distance", "0.1", "0.15", "0.2"])
    err = capsys.readouterr().err
    assert rc == 2 and "Traceback" not in err
    assert err.count("nodlidar calibrate: wall yaw") == 3 and "0.10 m from the sensor" in err


def test_options_are_refused_in_the_units_typed(capsys):
    # issue: `--yaw-deg -70 0 70` answered "wall.yaw_rad = np.float64(-1.22...)"
    with pytest.raises(SystemExit) as ei:
        main(["calibrate", "--sim", "--yaw-deg", "-70", "0", "70"])
    err = capsys.readouterr().err
    assert ei.value.code == 2 and "--yaw-deg" in err and "deg" in err
    assert "rad" not in err and "np.float64" not in err
    with pytest.raises(ParameterError, match=r"wall yaw = '70 deg'"):
        WallPose(1.0, np.radians(70.0))
    # issue 15: --orientations 0/-1/2 silently captured 3
    for bad in ("0", "-1", "2"):
        with pytest.raises(SystemExit):
            main(["calibrate", "--live", "--orientations", bad, "--yes"])
        assert "--orientations" in capsys.readouterr().err
    # the simulated sensor captures one orientation per --yaw-deg: 4 cannot be honoured
    assert main(["calibrate", "--live", "--orientations", "4", "--yes"]) == 2
    assert "--orientations = 4" in capsys.readouterr().err
    assert main(["calibrate", "--sim", "--orientations", "3"]) == 2
    assert "only with --live" in capsys.readouterr().err
    assert main(["calibrate", "--sim", "--fit-range-scale"]) == 2
    assert "--wall-distance-m" in capsys.readouterr().err


def test_existing_output_is_refused_without_force(tmp_path, capsys):
    out = tmp_path / "cal.toml"
    out.write_text("keep me")
    assert main(["calibrate", "--sim", "--design", str(PAPER), "--out", str(out)]) == 2
    assert out.read_text() == "keep me" and "--force" in capsys.readouterr().err


# -- ambiguous beams --------------------------------------------------------------------------
def test_ambiguous_beams_cover_the_map_errors_and_the_runtime_drops_them(design, table1_fit,
                                                                         tmp_path):
    from nodlidar.runtime.assembly import AssemblyModel

    _, res = table1_fit
    assert res.ok, res.problems
    amb = np.asarray(res.ambiguous_steps)
    lidar = design.lidar
    # the symptom: steps whose mirror in the fitted map differs from the as-built
    # one (e.g. 594, 642, 722) put a column of points metres off. Each must be listed.
    wrong = np.flatnonzero(beam_map(design, res.perturbations) != beam_map(design, TRUTH))
    assert set(wrong + lidar.step_min) <= set(amb), (wrong + lidar.step_min, amb)
    assert 0 < amb.size < 60  # a few edge/joint beams, not a window
    path = tmp_path / "cal.toml"
    cal = write_calibration(path, res)
    back = load_calibration(path, design)
    assert back.ambiguous_steps == tuple(int(s) for s in amb)
    # the runtime takes them from the loaded calibration and drops them
    model = AssemblyModel.from_design(design, back.perturbations, back.id)
    assert not model.clear[amb - lidar.step_min].any()
    plain = AssemblyModel.from_design(design, dict(cal.perturbations), cal.id,
                                      ambiguous_steps=())
    assert np.array_equal(model.clear, plain.clear & ~np.isin(lidar.steps, amb))


@pytest.mark.slow
def test_calibrated_room_sweep_puts_every_reflected_point_on_its_surface(design, table1_fit):
    # one nod sweep of the simulated room (walls, boxes, a walker) by the Table-I sensor,
    # assembled by the runtime with the fitted calibration and with the true errors; each
    # reflected point is compared with the ray tracer's true hit point
    from nodlidar.runtime.assembly import AssemblyModel, ScanBatch, assemble
    from nodlidar.sim.raycast import SceneSimulator

    _, res = table1_fit
    lidar = design.lidar
    sim = SceneSimulator(design, "room", TRUTH)
    n_scans = int(np.ceil(design.spec.nod.sweep_period_s / lidar.scan_period_s))
    scans = sim.scans(n_scans, seed=3)
    ts = np.array([s.t_s[0] - lidar.beam_time_s(0.0, s.steps[0]) for s in scans])
    batch = ScanBatch.from_arrays(lidar.steps, np.array([s.measured_m() for s in scans]), ts)
    nod = (np.concatenate([s.t_s for s in scans]), np.concatenate([s.nod_rad for s in scans]))
    truth_w = np.stack([s.point_world for s in scans])          # (scans, steps, 3)
    stats = {}
    for label, model in (
            ("calibrated", AssemblyModel.from_design(design, res.perturbations, "cal",
                                                     ambiguous_steps=res.ambiguous_steps)),
            ("ambiguous kept", AssemblyModel.from_design(design, res.perturbations, "cal",
                                                         ambiguous_steps=())),
            ("true", AssemblyModel.from_design(design, TRUTH, "truth"))):
        cloud = assemble(model, batch, nod)
        refl = cloud.mirror >= 0
        p_true = truth_w[cloud.scan[refl], cloud.step[refl] - lidar.step_min]
        p_true = sim.scene.sensor.to_sensor(p_true, cloud.t[refl])
        err = np.linalg.norm(cloud.xyz[refl] - p_true, axis=1)
        ok = np.isfinite(err)
        sig = lidar.range_sigma_m(cloud.range_m[refl][ok])
        stats[label] = (err[ok], sig)
    err, sig = stats["calibrated"]
    # the symptom, with the ambiguous beams kept: measured 20 points up to 4.25 m
    # off (163 sigma), seed 3
    e_kept, s_kept = stats["ambiguous kept"]
    assert np.sum(e_kept > 5 * s_kept + 5e-4) >= 5
    # dropped: none beyond 5 sigma of the range noise (+0.5 mm of rounding); measured
    # 7780 points, worst 3.5 sigma
    assert err.size > 5000
    assert np.all(err <= 5 * sig + 5e-4), (np.sort(err / sig)[-5:])
    rms_cal = np.sqrt(np.mean(err**2))
    rms_true = np.sqrt(np.mean(stats["true"][0] ** 2))
    # the fitted mirrors are within ~1 sigma of the truth: the scatter is the noise's
    # (measured 36.12 mm vs 36.11 mm)
    assert rms_cal <= 1.2 * rms_true, (rms_cal, rms_true)


# -- intrinsics and covariance -----------------------------------------------------------------
MIXED = [WallPose(0.8, np.radians(-25.0)), WallPose(1.2, 0.0), WallPose(1.0, np.radians(25.0))]


@pytest.mark.slow
def test_range_offset_and_scale_are_recovered(design):
    # a lidar reading r_meas = 1.01 r + 0.02 m. Measured, seeds 0-2: offset 17.7-20.7 mm
    # (sigma 1.3 mm), scale 0.90-1.20 % (sigma 0.21 %), mirrors within 2.2 sigma
    caps = [with_range_error(c, 0.02, 0.01) for c in simulated_captures(design, TRUTH, MIXED)]
    res = calibrate(design, caps, intrinsics=True,
                    known_distances_m=[w.distance_m for w in MIXED])
    it = res.intrinsics
    assert abs(it["range_offset_m"] - 0.02) <= 3 * it["sigma_range_offset_m"]
    assert abs(it["range_scale"] - 0.01) <= 3 * it["sigma_range_scale"]
    assert it["sigma_range_offset_m"] < 2e-3 and it["sigma_range_scale"] < 3e-3
    assert res.ok and _within(res), res.problems
    # the scale is not observable from the walls alone: refused, not guessed
    with pytest.raises(CalibrationError, match="range scale cannot be fitted from walls alone"):
        calibrate(design, caps, intrinsics=True)


def test_range_offset_alone_has_no_bias(design):
    # noise only, no offset: the fit must find ~0. (Point-to-plane residuals gave +5 mm,
    # 5 sigma, from the noise alone: the reason the joint fit works in range.)
    walls = [WallPose(0.8, np.radians(-25)), WallPose(0.7, 0.0), WallPose(0.8, np.radians(25))]
    caps = synthetic_captures(design, {}, walls, seed=0)
    res = calibrate(design, caps, intrinsics=("range_offset_m",), mirrors=["L1"])
    it = res.intrinsics
    assert abs(it["range_offset_m"]) <= 3 * it["sigma_range_offset_m"], it
    caps = [with_range_error(c, 0.02) for c in caps]
    res = calibrate(design, caps, intrinsics=("range_offset_m",), mirrors=["L1"])
    assert abs(res.intrinsics["range_offset_m"] - 0.02) <= 3 * it["sigma_range_offset_m"]


def test_full_covariance_in_the_file_and_json(design, table1_fit, tmp_path, capsys):
    _, res = table1_fit
    C = np.asarray(res.covariance)
    assert C.shape == (12, 12) and res.parameter_names[:3] == (
        "L1.dalpha_rad", "L1.dbeta_rad", "L1.dd_m")
    assert_allclose(C, C.T, rtol=0, atol=1e-18)
    assert np.all(np.linalg.eigvalsh(C) > 0)
    for i, name in enumerate(res.mirrors):  # the per-mirror sigmas are its diagonal
        assert_allclose(np.sqrt(np.diag(C)[3 * i:3 * i + 3]), res.mirrors[name].sigma, rtol=1e-12)
    path = tmp_path / "cal.toml"
    write_calibration(path, res)
    back = read_calibration(path)
    assert back.parameter_names == res.parameter_names
    assert_allclose(np.array(back.covariance), C, rtol=1e-15)
    rc = main(["calibrate", "--sim", "--design", str(PAPER), "--json", "--no-noise"])
    data = json.loads(capsys.readouterr().out)
    assert rc == 0 and data["ok"] and len(data["covariance"]) == 12
    # no noise, only the mm rounding: plane RMS <= (1 mm / sqrt 12) / 10 mm = 0.029 x the
    # noise model's 1 cm
    assert data["walls"][0]["inlier_share"] > 0.9 and data["walls"][0]["rms_over_noise"] < 0.03


# -- random as-built errors ----------------------------------------------------------------------
@pytest.mark.slow
def test_random_as_built_errors_32_seeds(design):
    # uniform +-50 mrad / +-15 mm per mirror parameter, the simulated sensor, the three
    # default walls: every fit within 3 mrad / 1 mm, and z = (fit - truth) / sigma with an
    # RMS in 0.8-1.25 per parameter (pooled over the 4 mirrors: 128 samples, the RMS's own
    # standard error is ~6 %, so the window is > 3 standard errors wide)
    rng = np.random.default_rng(12)
    z, worst = [], np.zeros(3)
    for seed in range(32):
        truth = {m.name: Perturbation(*rng.uniform(-1, 1, 3) * [0.05, 0.05, 0.015])
                 for m in design.mirrors}
        caps = simulated_captures(design, truth, DEFAULT_WALLS, seed=seed)
        res = calibrate(design, caps)
        assert res.ok, (seed, res.problems)
        for n, m in res.mirrors.items():
            e = m.perturbation.as_array() - truth[n].as_array()
            worst = np.maximum(worst, np.abs(e))
            z.append(e / m.sigma)
    assert np.all(worst <= [3e-3, 3e-3, 1e-3]), worst
    rms = np.sqrt(np.mean(np.square(z), axis=0))
    assert np.all((rms >= 0.8) & (rms <= 1.25)), rms


def test_config_gates_are_validated():
    with pytest.raises(ParameterError, match="min_inlier_share"):
        CalibrationConfig(min_inlier_share=1.5)
    with pytest.raises(ParameterError, match="gate_sigma"):
        CalibrationConfig(gate_sigma=0)
