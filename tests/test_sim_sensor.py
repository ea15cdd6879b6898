"""SimulatedSensor end to end: the runtime's own drivers (UrgDriver, DynamixelBus,
NodController, MirrorLift) over a pty and over TCP, ranges checked against closed forms
and the runtime BeamModel; the device error codes; ``nodlidar emulate`` as a process."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from numpy.testing import assert_allclose

from nodlidar.runtime.actuators import DynamixelBus, MirrorLift, NodController, NodProfile
from nodlidar.runtime.urg import UrgDriver
from nodlidar.sim.scene import Plane, Scene, SensorPose, wall_scene
from nodlidar.sim.sensor import SimulatedSensor
from nodlidar.solver import solve
from nodlidar.spec import load_design

ROOT = Path(__file__).resolve().parents[1]
PAPER = ROOT / "design" / "urg04lx-paper.toml"
WALL_M = 1.5
# reported ranges are whole mm: half a quantisation step from the exact path
MM_TOL_M = 0.5e-3 + 1e-9


@pytest.fixture(scope="module")
def design():
    return solve(load_design(PAPER))


def _wait_still(bus, sid, timeout=3.0):
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        if not bus.is_moving(sid):
            return
        time.sleep(0.01)
    raise AssertionError("servo did not arrive")


def _check_wall(design, scan, nod, lifted=False):
    """Every valid range of a scan of the wall x = WALL_M projects onto it (BeamModel), and
    direct beams equal WALL_M / (cos(bearing) cos(nod)) (closed form)."""
    bm = design.beam_model(mirrors_deployed=not lifted)
    ok = np.isfinite(scan.ranges_m)
    p = bm.points(scan.steps[ok], scan.ranges_m[ok], nod)
    assert np.max(np.abs(p[:, 0] - WALL_M)) <= MM_TOL_M
    b = design.lidar.bearing_from_step(scan.steps)
    direct = bm.mirror_of_step < 0
    front = direct & (np.cos(b) > 0.4)  # on the 8 m wide wall and within DMAX
    assert_allclose(scan.ranges_m[front], WALL_M / (np.cos(b[front]) * np.cos(nod)), atol=MM_TOL_M)
    return ok


def _lost(design):
    """Steps that cannot reach the wall x = WALL_M with the mirrors deployed: the design's
    shadowed steps and the side-window steps no mirror takes. ``(k,) int``, ascending."""
    free = design.lidar.steps[design.mirror_of_step < 0]
    return np.union1d(design.shadowed_steps, np.setdiff1d(free, design.direct_steps))


@pytest.mark.parametrize("transport", ["pty", "tcp"])
def test_runtime_drivers_against_the_simulated_sensor(design, transport):
    with SimulatedSensor(design, wall_scene(WALL_M), transport=transport, noise=False) as sim:
        assert sim.lidar_url.startswith("socket://" if transport == "tcp" else "/dev/")
        with UrgDriver(sim.lidar_url) as urg, DynamixelBus(sim.servo_url) as bus:
            assert urg.parameters().dmax_mm == 5600
            assert [p.id for p in bus.discover([1, 2, 3])] == [1, 2, 3]
            # level head, mirrors deployed: every beam reaches the wall but the ones the
            # design gives up (shadowed: no return) and the unreflected side-window beams
            # (they leave sideways, past the 8 m wall)
            s = urg.scan()
            ok = _check_wall(design, s, 0.0)
            assert np.array_equal(s.steps[~ok], _lost(design))
            truth = sim.truth(sim.scan_index(s.timestamp_ms))
            hit = np.isfinite(truth.range_m)  # no return (NaN truth): URG-04LX code 0
            assert np.array_equal(np.rint(truth.range_m[hit] * 1000), s.ranges_mm[hit])
            assert np.array_equal(s.steps[~hit], _lost(design)) and np.all(s.ranges_mm[~hit] == 0)
            # nod the head down by 0.25 rad through the bus; the scans follow
            bus.set_torque(1, True)
            bus.set_goal_angle(1, 0.25)
            _wait_still(bus, 1)
            nod = bus.present_angle(1)
            assert abs(nod - 0.25) < 0.002  # one servo tick is 1.5 mrad
            _check_wall(design, urg.scan(), nod)
            # lift both mirrors: the side-window beams now go direct (or nowhere: NaN)
            bus.set_goal_angle(1, 0.0)
            _wait_still(bus, 1)
            MirrorLift(bus, design=design).lift("both", timeout_s=5.0)
            s = urg.scan()
            ok = _check_wall(design, s, bus.present_angle(1), lifted=True)
            behind = np.cos(design.lidar.bearing_from_step(s.steps)) < -0.05
            assert behind.sum() > 100 and not ok[behind].any()
            assert np.all(s.ranges_mm[behind] == 0)  # URG-04LX code 0: no return
            MirrorLift(bus, design=design).reset("both", timeout_s=5.0)
            s = urg.scan()
            assert np.array_equal(s.steps[~np.isfinite(s.ranges_m)], _lost(design))


def test_nodding_head_scans_see_the_ramp_beam_by_beam(design):
    """With NodController sweeping, each beam's range matches the head pitch the servo had
    at that beam's own time (the nod changes within one scan)."""
    with SimulatedSensor(design, wall_scene(WALL_M), transport="tcp", noise=False) as sim:
        with UrgDriver(sim.lidar_url) as urg, DynamixelBus(sim.servo_url) as bus:
            with NodController(bus, NodProfile(-0.3, 0.3, 1.0)):
                time.sleep(0.5)
                scans = [urg.scan() for _ in range(3)]
            b = design.lidar.bearing_from_step(design.lidar.steps)
            direct = (design.mirror_of_step < 0) & (np.cos(b) > 0.2)
            for s in scans:
                truth = sim.truth(sim.scan_index(s.timestamp_ms))
                nod = sim.dxl.joint_angle("nod", truth.t_s)
                assert np.ptp(nod[direct]) > 0.01  # it really moved during the scan
                assert_allclose(s.ranges_m[direct], WALL_M / (np.cos(b[direct]) * np.cos(nod[direct])),
                                atol=MM_TOL_M)
                ok = np.isfinite(s.ranges_m)
                p = design.beam_model().points(s.steps[ok], s.ranges_m[ok], nod[ok])
                assert np.max(np.abs(p[:, 0] - WALL_M)) <= MM_TOL_M


def test_device_error_codes_for_no_return_far_and_near(design):
    """URG-04LX codes (SPEC Table 3): 0 = no return / beyond DMAX, 6 = below DMIN."""
    far = wall_scene(7.0, size_m=(40.0, 10.0))
    near = Scene("near", (Plane((0.015, 0.0, 0.0), (-1.0, 0.0, 0.0), (0.02, 0.05)),),
                 sensor=SensorPose((0.0, 0.0, 0.0)))
    b = design.lidar.bearing_from_step(design.lidar.steps)
    for scene, want_code, sel in ((far, 0, np.abs(b) < 0.5), (near, 6, np.abs(b) < 0.5)):
        with SimulatedSensor(design, scene, transport="tcp", noise=False) as sim:
            with UrgDriver(sim.lidar_url) as urg:
                s = urg.scan()
        assert np.all(s.ranges_mm[sel] == want_code)
        assert np.all(np.isnan(s.ranges_m[sel]))
    # the near plane (20 mm wide) is missed by the beams beyond |bearing| ~ 34 deg: no return
    assert np.all(s.ranges_mm[(design.mirror_of_step < 0) & (np.abs(b) > 0.7)] == 0)


def test_noise_and_perturbations_reach_the_wire(design):
    from nodlidar.paper import TABLE_I_PERTURBATIONS

    with SimulatedSensor(design, wall_scene(WALL_M), transport="tcp", noise=True, seed=5,
                         perturbations=TABLE_I_PERTURBATIONS) as sim:
        with UrgDriver(sim.lidar_url) as urg:
            s = urg.scan()
        truth = sim.truth(sim.scan_index(s.timestamp_ms))
    assert np.array_equal(np.rint(np.nan_to_num(truth.range_m) * 1000).astype(int)[truth.range_m > 0.02],
                          s.ranges_mm[truth.range_m > 0.02])
    ok = np.isfinite(truth.true_range_m)
    err = s.ranges_m[ok] - truth.true_range_m[ok]
    # sigma 10..17 mm on this wall: the error is noise-sized, never zero everywhere
    assert 0.005 < np.std(err) < 0.03
    assert np.any(truth.mirror != design.mirror_of_step)  # Table I moves beams


@pytest.mark.parametrize("transport", ["tcp", "pty"])
def test_emulate_command_prints_urls_and_serves(tmp_path, capsys, transport):
    """`nodlidar emulate` as a process; the printed connect line, run as a command, finds
    the lidar and the three servos; the runtime drivers get the wall's ranges."""
    from nodlidar.cli import main

    env = dict(os.environ, PYTHONUNBUFFERED="1")
    proc = subprocess.Popen(
        [sys.executable, "-m", "nodlidar.cli", "emulate", "--design", str(PAPER), "--scene", "wall",
         "--no-noise"] + (["--tcp"] if transport == "tcp" else []),
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path, env=env)
    try:
        lines = [proc.stdout.readline() for _ in range(4)]
        urls = {ln.split(":", 1)[0]: ln.split(":", 1)[1].strip() for ln in lines if "URL" in ln}
        prefix = "socket://127.0.0.1:" if transport == "tcp" else "/dev/"
        assert urls["lidar URL"].startswith(prefix) and urls["servo URL"].startswith(prefix)
        connect = lines[3].split(":", 1)[1].split()
        assert connect == ["nodlidar", "info", "--port", urls["lidar URL"], "--servo-port",
                           urls["servo URL"]]
        capsys.readouterr()
        assert main(connect[1:]) == 0
        out = capsys.readouterr().out
        assert "SCIP 2.0" in out and "servos found: 3" in out and "(mirror_left)" in out
        with UrgDriver(urls["lidar URL"]) as urg:
            s = urg.scan()
        front = s.steps == 384  # straight ahead at the default 1.5 m wall
        assert s.ranges_mm[front][0] == 1500
        with DynamixelBus(urls["servo URL"]) as bus:
            assert bus.ping(1).id == 1
    finally:
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=10)
    assert proc.returncode == 0
    assert "Traceback" not in err
    assert "stopped" in out


_NO_COMPILE_AFTER_START = r"""
import sys
import numpy as np
from nodlidar.sim import _kernel as K
from nodlidar.sim.sensor import SimulatedSensor
from nodlidar.solver import solve
from nodlidar.spec import load_design

def compiled():
    return {n: len(getattr(K, n).signatures) for n in K.__all__
            if hasattr(getattr(K, n), "signatures")}

sensor = SimulatedSensor(solve(load_design(sys.argv[1])), "paper-tracking", transport="tcp")
assert not any(compiled().values()), compiled()      # nothing compiled by the constructor
with sensor:
    after_start = compiled()
    for k in range(3):                                 # what the emulator's thread does
        sensor.simulate_scan(k)
    sim = sensor.simulator
    moving = np.linspace(0.0, 1.0, sim.lidar.steps.size)
    sim.scan(0.2, 0.1, moving, moving[::-1], rng=np.random.default_rng(1))
    later = compiled()
print(sum(after_start.values()), "kernels compiled at start")
assert later == after_start, {n: (after_start[n], later[n]) for n in later
                              if later[n] != after_start[n]}
"""


def test_start_compiles_every_scan_kernel_before_serving():
    """numba compiles at the first call (~5 s the first time on a machine): inside the
    emulator's thread that lost every scan of a short sweep (``nodlidar demo`` on a fresh
    cache captured 0 scans). ``start`` must leave nothing to compile for later scans - a
    moving mover, mirrors lifting and noise included. A fresh interpreter, so no earlier
    test has compiled anything."""
    proc = subprocess.run([sys.executable, "-c", _NO_COMPILE_AFTER_START, str(PAPER)],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "kernels compiled at start" in proc.stdout
