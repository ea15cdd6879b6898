"""Tracking in the world (issue 13): simulated scans through the runtime assembly, --perturb
and --calibration in every source.

References: the simulator's own hit points (``ScanTruth.point_world``, computed by ray casting
the as-built mirrors, independently of the BeamModel the assembly projects with).
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from nodlidar.cli import main


@pytest.fixture(scope="module")
def design():
    from nodlidar.paper import PAPER_DESIGN
    from nodlidar.solver import solve
    from nodlidar.spec import load_design

    return solve(load_design(PAPER_DESIGN))


def _errors(scans, truths):
    """Distance [m] of each assembled point from the simulator's true hit point."""
    out = []
    for s in scans:
        st = truths[s.scan]
        i = np.searchsorted(st.steps, s.steps)
        ok = np.isfinite(s.range_m)
        out.append(np.linalg.norm(s.points[ok] - st.point_world[i][ok], axis=1))
    return np.concatenate(out)


def test_simulated_scans_use_the_runtime_retraced_model(design):
    from nodlidar.paper import TABLE_I_PERTURBATIONS
    from nodlidar.runtime.assembly import AssemblyModel
    from nodlidar.sim.raycast import SceneSimulator
    from nodlidar.sim.scene import load_scene
    from nodlidar.tracking.simdata import simulate_scans

    perts = dict(TABLE_I_PERTURBATIONS)
    sim = SceneSimulator(design, load_scene("paper-tracking"), perts)
    truths = sim.scans(12, noise=False)
    # calibrated exactly (the default model: the same perturbations, beam map re-traced):
    # every point within the simulator's 1 mm range rounding (half of it, along the ray)
    scans = simulate_scans(design, 12, perturbations=perts, simulator=sim, noise=False)
    err = _errors(scans, truths)
    assert len(err) > 2000
    assert err.max() < 0.6e-3
    assert scans[0].calibration_id == "simulated"
    # truth ids follow the beams through the assembly: the object's beams hit the mover
    for s in scans:
        st = truths[s.scan]
        i = np.searchsorted(st.steps, s.steps)
        assert np.array_equal(s.truth_id, np.where(np.isfinite(s.range_m), st.object_id[i], -1))
    # the uncalibrated runtime (design as is) misplaces the reflected points of this sensor
    raw = simulate_scans(design, 12, perturbations=perts, simulator=sim, noise=False,
                         model=AssemblyModel.from_design(design))
    err0 = _errors(raw, truths)
    assert np.mean(err0 > 0.1) > 0.2  # 59 % measured over 20 scans
    assert raw[0].calibration_id == "none"


def _track_lines(capsys, *args):
    assert main(["track", "--sim", "--scans", "24", "--json", *args]) == 0
    cap = capsys.readouterr()
    return [json.loads(x) for x in cap.out.splitlines()], cap.err


@pytest.mark.slow
def test_track_sim_honours_perturb_and_calibration(design, capsys, tmp_path):
    from nodlidar.calibration.calfile import Calibration, write_calibration
    from nodlidar.calibration.fit import design_hash
    from nodlidar.paper import TABLE_I_PERTURBATIONS

    cal = Calibration("cal-table1", design.spec.name, design_hash(design.spec),
                      "2026-01-01T00:00:00+00:00", "exact", dict(TABLE_I_PERTURBATIONS))
    path = tmp_path / "cal.toml"
    write_calibration(path, cal)
    exact, err0 = _track_lines(capsys)
    built, err1 = _track_lines(capsys, "--perturb", "table1")
    fixed, err2 = _track_lines(capsys, "--perturb", "table1", "--calibration", str(path))
    assert "as built: none; calibration none" in err0
    assert "as built: table1; calibration none" in err1
    assert "as built: table1; calibration cal-table1" in err2
    assert exact != built and built != fixed
    # calibrated with the sensor's true errors, the points are those of the exact sensor up
    # to range noise of another realisation... the same seed, so the tracker sees the same
    # object points: final speed within 5 mm/s of the exactly built sensor's
    last = {d["track"]: d for d in exact if d["v_m_s"] is not None}
    lastf = {d["track"]: d for d in fixed if d["v_m_s"] is not None}
    v0 = max(last.values(), key=lambda d: d["n_scans"])["v_m_s"]
    v1 = max(lastf.values(), key=lambda d: d["n_scans"])["v_m_s"]
    assert abs(v0 - v1) < 0.005


def test_track_recording_refuses_perturb(capsys, tmp_path):
    rc = main(["track", str(tmp_path / "nothing"), "--perturb", "table1"])
    err = capsys.readouterr().err
    assert rc != 0 and len(err.strip().splitlines()) == 1
