"""Run every script in examples/ as a user would (``python examples/NAME.py``, a fresh
process against the built-in simulated sensor) and check what it produced with the
library's own readers and an independent ground truth, not the script's printout."""

from __future__ import annotations

import csv
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from numpy.testing import assert_allclose

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
# generous: the machine is shared; each script finishes in a few seconds when idle
TIMEOUT_S = 180


def run_example(name: str, tmp_path: Path) -> tuple[Path, str]:
    """Run examples/NAME in a subprocess, cwd = tmp_path, its output directory given by
    $NODLIDAR_EXAMPLES_OUT; asserts exit 0 and that nothing was written outside it."""
    out = tmp_path / "out"
    env = {**os.environ, "NODLIDAR_EXAMPLES_OUT": str(out), "MPLBACKEND": "Agg"}
    proc = subprocess.run([sys.executable, str(EXAMPLES / name)], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=TIMEOUT_S)
    assert proc.returncode == 0, f"{name} exited {proc.returncode}:\n{proc.stdout}\n{proc.stderr}"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"], "wrote outside its directory"
    return out, proc.stdout


def test_every_example_is_tested_and_listed():
    scripts = sorted(p.name for p in EXAMPLES.glob("*.py"))
    tested = {"connect_and_sweep.py", "record.py", "calibrate.py", "track_live.py",
              "design_sweep.py"}
    assert set(scripts) == tested
    readme = (EXAMPLES / "README.md").read_text()
    assert all(s in readme for s in scripts)


def test_examples_use_only_public_api():
    """Examples import public names only: no underscore module or name, and every name
    imported from a nodlidar module is in that module's ``__all__``."""
    import ast
    import importlib

    for script in EXAMPLES.glob("*.py"):
        for node in ast.walk(ast.parse(script.read_text())):
            if isinstance(node, ast.Import):
                assert not any("._" in a.name for a in node.names), script
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("nodlidar"):
                assert not any(part.startswith("_") for part in node.module.split(".")), script
                mod = importlib.import_module(node.module)
                for alias in node.names:
                    assert alias.name in getattr(mod, "__all__", ()), (script.name, node.module,
                                                                       alias.name)


@pytest.mark.slow
def test_connect_and_sweep(tmp_path):
    from nodlidar.runtime.cloud import read_cloud

    out, stdout = run_example("connect_and_sweep.py", tmp_path)
    cloud = read_cloud(out / "sweep.ply")
    # a full nod sweep of the simulated room: ~14 k points (21 scans x ~680 beams)
    assert len(cloud) > 1000
    assert stdout.startswith(f"{len(cloud)} points")  # the script's count = the file's
    assert np.isfinite(cloud.xyz).all()
    # the mirrors are deployed: both direct and reflected beams are in the cloud
    assert (cloud.mirror >= 0).any() and (cloud.mirror < 0).any()
    # robot frame: the same points moved by the script's robot_from_sensor (a translation);
    # each file holds float32 x y z, within half an ulp (<= 2**-21 m below 16 m) of exact
    on_robot = read_cloud(out / "sweep_robot.ply")
    assert on_robot.frame == "robot" and len(on_robot) == len(cloud)
    assert_allclose(on_robot.xyz, cloud.xyz + [0.1, 0.0, 0.5], atol=2 * 2.0**-21, rtol=0)


@pytest.mark.slow
def test_record_and_replay(tmp_path):
    from nodlidar.runtime.bag import read_recording, replay_bag
    from nodlidar.runtime.cloud import read_cloud

    out, _ = run_example("record.py", tmp_path)
    contents = read_recording(out / "capture_bag")
    assert len(contents.scans) == 20                      # the script stops after 20 scans
    assert (out / "capture_bag" / "capture_bag.mcap").is_file()
    # the live cloud (read back from its file) and a replay in this process go through the
    # same assembly: the same points, to the file's float32 resolution
    live = read_cloud(out / "live.ply")
    _, replayed = replay_bag(out / "capture_bag")
    assert len(live) > 1000 and len(live) == len(replayed)
    assert_allclose(live.xyz, replayed.xyz, atol=1e-5)   # float32 xyz of a few-m room: ~1e-7 m


def test_calibrate_recovers_table_i(tmp_path):
    from nodlidar.calibration import load_calibration
    from nodlidar.paper import PAPER_DESIGN, TABLE_I_PERTURBATIONS
    from nodlidar.solver import solve
    from nodlidar.spec import load_design

    out, stdout = run_example("calibrate.py", tmp_path)
    # read back the written file, checked against the design it claims to belong to
    cal = load_calibration(out / "calibration.toml", solve(load_design(PAPER_DESIGN)))
    assert set(cal.perturbations) == set(TABLE_I_PERTURBATIONS)
    for name, truth in TABLE_I_PERTURBATIONS.items():
        p = cal.perturbations[name]
        # issue 18's target, the paper's calibration accuracy: 3 mrad and 1 mm (measured
        # here: <= 0.35 mrad, <= 0.27 mm with noise seed 0)
        assert_allclose([p.dalpha, p.dbeta], [truth.dalpha, truth.dbeta], atol=3e-3, rtol=0)
        assert_allclose(p.dd, truth.dd, atol=1e-3, rtol=0)
    assert "quality gates passed" in stdout


@pytest.mark.slow
def test_track_live_finds_the_mover(tmp_path):
    from nodlidar.sim.scene import load_scene
    from nodlidar.tracking.evaluate import mover_truth

    out, _ = run_example("track_live.py", tmp_path)
    tracks = json.loads((out / "tracks.json").read_text())
    confirmed = [t for t in tracks if t["confirmed"]]
    assert confirmed, "no confirmed track"
    # the scene's one mover, by its trajectory's own law at the track's last update
    scene = load_scene("paper-tracking")
    best = max(confirmed, key=lambda t: t["n_scans"])
    pos, vel = mover_truth(scene, [best["t_s"]])
    # The walker turns every 12.3 s of simulated time. The example runs in real time, so its
    # 6 s capture normally ends before the first turn; a start-up slower than ~6 s (a very
    # loaded host) puts a turn inside the track's life, and then a constant-velocity
    # filter still carries the old velocity for seconds by design (speed through zero,
    # position overshooting the turn): the speed is then not judged
    life = best["t_s"] - np.linspace(0.0, best["n_scans"] * 0.1 + 1.0, 61)
    _, v_life = mover_truth(scene, life)
    turned = bool(np.any(v_life[0] @ vel[0, 0] < 0))
    # the tracker follows the visible surface's centroid: up to the radius (0.18 m) in
    # front of the centre, plus 0.1 m of lag; after a turn, plus the overshoot (at most
    # the walker's speed over the track's life)
    lag = 0.1 + (0.13 * (life[0] - life[-1]) if turned else 0.0)
    assert np.hypot(best["x_m"] - pos[0, 0, 0], best["y_m"] - pos[0, 0, 1]) < 0.18 + lag
    if not turned:
        v_true = float(np.hypot(*vel[0, 0]))
        # issue 18's tolerance: 0.05 m/s (the paper reports ~0.01 m/s after tens of
        # scans; after 60 live scans the estimate is still settling)
        assert_allclose(best["v_m_s"], v_true, atol=0.05, rtol=0)
    assert math.isfinite(best["x_m"]) and math.isfinite(best["y_m"])


def test_design_sweep_table(tmp_path):
    from nodlidar.analysis.explore import evaluate_design
    from nodlidar.paper import PAPER_DESIGN
    from nodlidar.spec import load_design

    out, stdout = run_example("design_sweep.py", tmp_path)
    with (out / "design_sweep.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    d = [float(r["layout.design_distance_m"]) for r in rows]
    assert d == [1.0, 2.0, 3.0, 5.0, 6.0]
    feasible = [r["feasible"] == "True" for r in rows]
    # the URG-04LX reaches 5.6 m: D = 6 m is refused, with the reason in the table
    assert feasible == [True, True, True, True, False]
    assert "5.6" in rows[-1]["reason"] and "infeasible" in stdout
    # the swept row at the paper's own D equals the paper design evaluated unswept (the
    # sweep changes only the swept key); CSV floats are repr-exact
    spec = load_design(PAPER_DESIGN)
    assert spec.layout.design_distance_m == 2.0
    ref = evaluate_design(spec)
    row = rows[1]
    for key in ("rms_error_deg", "rms_error_6m_deg", "density_gain", "glass_area_cm2"):
        assert_allclose(float(row[key]), ref[key], rtol=1e-12)
