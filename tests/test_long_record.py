"""Long captures: the live cloud equals the replay of its bag, memory stays flat, and a
servo bus that vanishes is one clean error (issue 15)."""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from nodlidar.errors import DeviceError
from nodlidar.runtime.actuators import SampleBuffer, interpolate_angle
from nodlidar.runtime.assembly import AssemblyModel, ScanBatch, assemble
from nodlidar.runtime.session import LiveAssembler, Session

pytestmark = pytest.mark.timeout(300)


# -- sample buffer -------------------------------------------------------------------


def test_unbounded_buffer_keeps_everything_until_pruned():
    buf = SampleBuffer()
    t = np.repeat(np.arange(5000) * 0.01, 2)  # pairs of equal times (two READs per tick)
    for i, ti in enumerate(t):
        buf.append(float(ti), i, float(np.sin(ti)) + (i % 2) * 1e-3)
    assert len(buf) == buf.total == t.size and buf.dropped == 0
    full = buf.snapshot()
    np.testing.assert_array_equal(full.host_time_s, t)  # nothing lost past the old ring size
    # interpolation at t >= t_s on the pruned buffer equals it on the whole buffer
    # (duplicates keep the first sample, as AngleSamples does)
    t_s = 20.005
    part = buf.snapshot_around(t_s)
    assert part.host_time_s[0] == 20.0 and part.host_time_s[1] == 20.0
    q = np.linspace(t_s, t[-1], 1001)

    def interp(s):
        _, first = np.unique(s.host_time_s, return_index=True)
        return interpolate_angle(s.host_time_s[first], s.angle_rad[first], q)

    np.testing.assert_array_equal(interp(part), interp(full))
    dropped = buf.prune(t_s)
    assert dropped == 4000 and len(buf) == t.size - 4000 and buf.pruned == 4000
    np.testing.assert_array_equal(interp(buf.snapshot()), interp(full))
    # appending after a prune reuses the arrays: memory follows the most ever kept, not
    # the total appended
    size = buf._t.size
    for k in range(100_000):
        buf.append(50.0 + k * 0.01, k, 0.0)
        if k % 1000 == 999:
            buf.prune(50.0 + (k - 10) * 0.01)
    assert len(buf) < 1100 and buf._t.size == size
    assert buf.last_time_s == 50.0 + 99_999 * 0.01


# -- live assembly -------------------------------------------------------------------


class _Smp:
    """A sampler stand-in: a SampleBuffer filled by the test."""

    def __init__(self):
        self.buffer = SampleBuffer()

    def prune(self, t):
        return self.buffer.prune(t)


class _Scan:
    def __init__(self, steps, ranges_m, stamp_s):
        self.steps, self.ranges_m, self.stamp_s = steps, ranges_m, stamp_s


def test_live_assembler_equals_whole_capture_assembly():
    from nodlidar.paper import PAPER_DESIGN
    from nodlidar.solver import solve
    from nodlidar.spec import load_design

    design = solve(load_design(PAPER_DESIGN))
    model = AssemblyModel.from_design(design)
    lid = model.lidar
    rng = np.random.default_rng(3)
    steps = np.arange(lid.step_min, lid.step_max + 1)
    period = lid.scan_period_s
    n_scans = 300
    stamps = 1.0 + period * np.arange(n_scans) + rng.uniform(0, 1e-3, n_scans)
    ranges = rng.uniform(0.3, 4.0, (n_scans, steps.size))
    ranges[rng.random(ranges.shape) < 0.01] = np.nan  # error codes
    scans = [_Scan(steps, ranges[k], stamps[k]) for k in range(n_scans)]
    # irregular sample times (a loaded machine), the mirrors lifted for a while in the middle
    joints = {}
    for name, dt in (("nod", 0.013), ("mirror_left", 0.05), ("mirror_right", 0.047)):
        ts = np.cumsum(rng.uniform(0.2, 1.8, 4000) * dt) + 0.9
        ts = ts[ts < stamps[-1] + 1.0]
        if name == "nod":
            a = 0.3 * np.sin(ts)
        else:
            prof = model.lift_left if name == "mirror_left" else model.lift_right
            a = np.where((ts > 10) & (ts < 20), prof.lifted_rad, 0.0)
        joints[name] = (ts, a)
    whole = assemble(model, ScanBatch.from_scans(scans), joints["nod"],
                     mirror_left=joints["mirror_left"], mirror_right=joints["mirror_right"])
    assert whole.meta["points"] > 0.5 * n_scans * steps.size
    assert whole.meta["no_nod"] == 0 and whole.lifted.any() and (~whole.lifted).any()

    # stream: samples arrive as time passes, each scan once it is complete
    smp = {k: _Smp() for k in joints}
    chunks = []
    # what assemble() uses by default: the design's profiles
    live = LiveAssembler(model, model.lift_left, model.lift_right, chunks.append, batch_scans=7)
    pos = dict.fromkeys(joints, 0)
    peak = 0
    for sc in scans:
        now = sc.stamp_s + period  # the scan is delivered one period after step 0
        for k, (ts, a) in joints.items():
            while pos[k] < ts.size and ts[pos[k]] <= now:
                smp[k].buffer.append(float(ts[pos[k]]), 0, float(a[pos[k]]))
                pos[k] += 1
        live.add(sc, smp)
        for s in smp.values():
            s.prune(live.need_since_s())
            peak = max(peak, len(s.buffer))
    for k, (ts, a) in joints.items():  # the capture ends: the samplers' last samples
        for i in range(pos[k], ts.size):
            smp[k].buffer.append(float(ts[i]), 0, float(a[i]))
    live.finish({k: (s.buffer.snapshot().host_time_s, s.buffer.snapshot().angle_rad)
                 for k, s in smp.items()})
    assert live.n_done == n_scans and not live.pending
    # same points, bit for bit: interpolation only ever used the two samples around a beam
    cat = {f: np.concatenate([getattr(c, f) for c in chunks])
           for f in ("xyz", "t", "step", "mirror", "scan", "range_m", "nod_rad", "lifted")}
    for f, v in cat.items():
        np.testing.assert_array_equal(v, getattr(whole, f), err_msg=f)
    assert live.stats == {k: whole.meta[k] for k in live.stats}
    # bounded: a few scans' worth of samples, not the capture's 4000
    assert peak < 200


# -- the servo bus vanishing ---------------------------------------------------------


def test_vanishing_servo_bus_is_one_clean_error(monkeypatch):
    thread_errors = []
    monkeypatch.setattr(threading, "excepthook", thread_errors.append)
    with Session(sim_rate=5, transport="pty") as s:
        def stop(scans, _nod):
            if len(scans) == 3:
                s.sim.dxl.close()  # the pty master goes away, as when a USB adapter is pulled
            return len(scans) > 2000

        with pytest.raises(DeviceError) as ei:
            s.capture(stop)
    assert type(ei.value).__module__.startswith("nodlidar.")
    assert "servo" in str(ei.value) and "/dev/" in str(ei.value)
    assert thread_errors == []  # no termios.error tracebacks from the sampler threads


# -- long recording ------------------------------------------------------------------


def _rss_mb(pid: int) -> float | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        return None
    return None


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="needs /proc for RSS")
def test_long_record_cloud_equals_replay_and_memory_is_flat(tmp_path):
    from nodlidar.runtime.cloud import read_cloud

    bag, live_f, rep_f = tmp_path / "bag", tmp_path / "live.ply", tmp_path / "replay.ply"
    exe = str(Path(sys.executable).with_name("nodlidar"))
    # 20 simulated minutes at 40x: the old 65 536-sample ring held ~2 min of samples here
    p = subprocess.Popen([exe, "record", "--out", str(bag), "--seconds", "1200",
                          "--sim-rate", "40", "--cloud", str(live_f)],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    t0, wall, rss = time.monotonic(), [], []
    while p.poll() is None:
        m = _rss_mb(p.pid)
        if m is not None:
            wall.append(time.monotonic() - t0)
            rss.append(m)
        time.sleep(0.25)
    out, err = p.communicate()
    assert p.returncode == 0, err
    r = subprocess.run([exe, "replay", str(bag), "--out", str(rep_f)], capture_output=True,
                       text=True)
    assert r.returncode == 0, r.stderr
    live, rep = read_cloud(live_f), read_cloud(rep_f)
    assert len(live) == len(rep) > 0
    assert live.meta["no_nod"] == 0 and live.meta == rep.meta
    np.testing.assert_array_equal(live.scan, rep.scan)
    np.testing.assert_array_equal(live.step, rep.step)
    # both files hold float32 xyz; the replay's stamps went through the bag's integer
    # nanoseconds (<= 0.5 ns: ~1e-9 m here), so at most one float32 rounding apart
    np.testing.assert_allclose(live.xyz, rep.xyz, rtol=0, atol=6e-8 * 8)
    # memory: the second half of the run (after start-up) is flat - the old capture kept
    # every scan (~0.84 MB per wall second at 5x, ~7 MB/s at 40x)
    w, m = np.array(wall), np.array(rss)
    half = w >= w[-1] / 2
    assert half.sum() >= 8
    slope_mb_s = np.polyfit(w[half], m[half], 1)[0]
    assert slope_mb_s < 0.5, f"RSS grows {slope_mb_s:.2f} MB/s"


@pytest.mark.parametrize("rate", [float("inf"), float("nan"), 0.0, -1.0])
def test_non_finite_rates_refused(rate):
    from nodlidar.errors import ParameterError
    from nodlidar.sim.clock import SimClock

    with pytest.raises(ParameterError, match="clock.rate"):
        SimClock(rate)
    with pytest.raises(ParameterError, match="--sim-rate"):
        Session(sim_rate=rate)
