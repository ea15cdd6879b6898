"""Dynamixel bus emulator, checked with the independent dynamixel-sdk and with our driver."""

from __future__ import annotations

import math
import time

import dynamixel_sdk as sdk  # the independent client (dev dependency): never skipped
import dynamixel_sdk.port_handler as sdk_port_handler
import numpy as np
import pytest

from nodlidar import dynamixel as dx
from nodlidar.errors import DeviceError, ParameterError
from nodlidar.runtime.actuators import (
    DynamixelBus,
    MirrorLift,
    MirrorLiftProfile,
    NodController,
    NodProfile,
    PositionSampler,
    SampleBuffer,
    interpolate_angle,
    unwrap_tick_ms,
)
from nodlidar.sim.clock import ManualClock, SimClock
from nodlidar.sim.dxl_emulator import DxlEmulator, ServoSpec

pytestmark = pytest.mark.timeout(60)

RATE = 10.0  # simulated seconds per wall second
TICK_S_PER_UNIT = dx.RAD_S_PER_VELOCITY_UNIT / dx.RAD_PER_TICK


@pytest.fixture(autouse=True)
def _sdk_patient(monkeypatch):
    """The SDK waits 2 x 16 ms (USB latency timer) + bytes for a reply: on a loaded
    machine the emulator's thread may not run that soon. Real adapters set the latency
    timer too; 250 ms makes a missing reply mean a missing reply, not a busy machine."""
    monkeypatch.setattr(sdk_port_handler, "LATENCY_TIMER", 250)


@pytest.fixture
def clock():
    return SimClock(rate=RATE)


@pytest.fixture
def emu(clock):
    with DxlEmulator(clock) as e:
        yield e


@pytest.fixture
def sdk_port(emu):
    port = sdk.PortHandler(emu.serve_pty())
    assert port.openPort()
    assert port.setBaudRate(57600)
    yield port, sdk.PacketHandler(2.0)
    port.closePort()


def ok(result):
    """Unpack an SDK (value..., comm, error) tuple, asserting success."""
    *value, comm, err = result if len(result) == 3 else (None, *result)
    assert comm == sdk.COMM_SUCCESS, f"comm {comm}"
    assert err == 0, f"error {err}"
    return value[0] if value else None


# -- dynamixel-sdk against the emulator over a pty --------------------------------------


def test_sdk_ping_and_model_number(sdk_port):
    port, ph = sdk_port
    for i in (1, 2, 3):
        model, comm, err = ph.ping(port, i)
        assert (model, comm, err) == (dx.XM430_W350_MODEL_NUMBER, sdk.COMM_SUCCESS, 0)
        assert ok(ph.read2ByteTxRx(port, i, 0)) == dx.XM430_W350_MODEL_NUMBER
        assert ok(ph.read1ByteTxRx(port, i, 7)) == i
    _, comm, _ = ph.ping(port, 9)
    assert comm == sdk.COMM_RX_TIMEOUT
    found, comm = ph.broadcastPing(port)
    assert comm == sdk.COMM_SUCCESS and sorted(found) == [1, 2, 3]


@pytest.fixture
def manual():
    """An emulator on a clock that moves only when the test advances it: what a client
    reads between two advances is exactly determined (no race with the wall clock)."""
    clock = ManualClock()
    with DxlEmulator(clock) as e:
        yield clock, e


def test_sdk_goal_moves_at_profile_velocity(manual):
    clock, emu = manual
    port = sdk.PortHandler(emu.serve_pty())
    assert port.openPort() and port.setBaudRate(57600)
    ph = sdk.PacketHandler(2.0)
    ok(ph.write1ByteTxRx(port, 1, 64, 1))
    assert ok(ph.read4ByteTxRx(port, 1, 132)) == 2048
    v_units = 40  # 9.16 rpm = 0.959 rad/s ~ 625 ticks/s
    ok(ph.write4ByteTxRx(port, 1, 112, v_units))
    ok(ph.write4ByteTxRx(port, 1, 116, 3048))  # +1000 ticks: 1.6 s simulated

    def state():
        data = ok(ph.readTxRx(port, 1, 120, 16))
        tick = data[0] | data[1] << 8
        moving = data[2]
        pos = int.from_bytes(bytes(data[12:16]), "little", signed=True)
        vel = int.from_bytes(bytes(data[8:12]), "little", signed=True)
        return tick, moving, vel, pos

    clock.advance(0.3)
    k1, m1, v1, p1 = state()
    clock.advance(0.6)
    k2, m2, v2, p2 = state()
    assert m1 == m2 == 1 and v1 == v2 == v_units
    assert 2048 < p1 < p2 < 3048
    dt = ((k2 - k1) % dx.REALTIME_TICK_MODULO) * 1e-3
    # the realtime tick is the clock floored to whole ms (0.3 + 0.6 may floor 1 ms low)
    assert dt == pytest.approx(0.6, abs=1.5e-3)
    slope = (p2 - p1) / dt
    # positions are whole ticks: +-1 tick over ~375 ticks, +-1 ms over 600 ms
    assert slope == pytest.approx(v_units * TICK_S_PER_UNIT, rel=0.006)
    # arrives (1.6 s after the goal) and stops
    clock.advance(0.71)
    _, m3, v3, p3 = state()
    assert (m3, v3, p3) == (0, 0, 3048)
    assert emu.joint_angle(1) == pytest.approx(dx.ticks_to_rad(3048))
    port.closePort()


def test_sdk_error_bits(sdk_port):
    port, ph = sdk_port
    # goal beyond the position limit (4095)
    comm, err = ph.write4ByteTxRx(port, 1, 116, 5000)
    assert comm == sdk.COMM_SUCCESS and err == dx.ErrorCode.DATA_LIMIT
    # address beyond the control table
    _, comm, err = ph.readTxRx(port, 1, 300, 4)  # (read4ByteTxRx needs data to be present)
    assert (comm, err) == (sdk.COMM_SUCCESS, dx.ErrorCode.ACCESS)
    # read-only item
    comm, err = ph.write2ByteTxRx(port, 1, 0, 12)
    assert err == dx.ErrorCode.ACCESS
    # value out of range
    comm, err = ph.write1ByteTxRx(port, 1, 64, 7)
    assert err == dx.ErrorCode.DATA_RANGE
    # EEPROM locked while torque is on
    ok(ph.write4ByteTxRx(port, 1, 48, 3000))
    ok(ph.write1ByteTxRx(port, 1, 64, 1))
    comm, err = ph.write4ByteTxRx(port, 1, 48, 3500)
    assert err == dx.ErrorCode.ACCESS
    comm, err = ph.write4ByteTxRx(port, 1, 116, 3001)  # new, lower limit applies
    assert err == dx.ErrorCode.DATA_LIMIT


def test_sdk_torque_gates_motion(sdk_manual):
    port, ph, clock, emu = sdk_manual
    ok(ph.write4ByteTxRx(port, 2, 116, 2500))  # stored, no torque: no motion
    clock.advance(0.5)
    assert ok(ph.read4ByteTxRx(port, 2, 132)) == 2048
    assert ok(ph.read1ByteTxRx(port, 2, 122)) == 0
    ok(ph.write1ByteTxRx(port, 2, 64, 1))  # torque on: holds present position
    assert ok(ph.read4ByteTxRx(port, 2, 116)) == 2048
    ok(ph.write4ByteTxRx(port, 2, 112, 0))  # 0 = velocity limit
    ok(ph.write4ByteTxRx(port, 2, 116, 2100))
    clock.advance(0.5)  # 52 ticks at the velocity limit (200 units, ~1300 ticks/s): 0.04 s
    assert ok(ph.read4ByteTxRx(port, 2, 132)) == 2100
    assert emu.joint_angle("mirror_left") == pytest.approx(dx.ticks_to_rad(2100))


def test_sdk_group_sync_write_and_read(sdk_manual):
    port, ph, clock, emu = sdk_manual
    n = emu.packets_handled
    sw_t = sdk.GroupSyncWrite(port, ph, 64, 1)
    for i in (2, 3):
        assert sw_t.addParam(i, [1])
    assert sw_t.txPacket() == sdk.COMM_SUCCESS
    sw = sdk.GroupSyncWrite(port, ph, 116, 4)
    assert sw.addParam(2, list((1500).to_bytes(4, "little")))
    assert sw.addParam(3, list((2600).to_bytes(4, "little")))
    assert sw.txPacket() == sdk.COMM_SUCCESS
    assert emu.wait_handled(n + 2)  # broadcasts have no reply to wait for
    clock.advance(3.0)  # 548 ticks at the velocity limit: 0.4 s
    sr = sdk.GroupSyncRead(port, ph, 132, 4)
    for i in (1, 2, 3):
        assert sr.addParam(i)
    assert sr.txRxPacket() == sdk.COMM_SUCCESS
    got = {i: sr.getData(i, 132, 4) for i in (1, 2, 3)}
    assert got == {1: 2048, 2: 1500, 3: 2600}
    truth = emu.joint_angles()
    assert truth[3] == pytest.approx(dx.ticks_to_rad(2600))


# -- in-process protocol checks on a manual clock ----------------------------------------


def _one(emu, pkt):
    (st,) = emu.handle_packet(pkt)
    return st


def _write(emu, i, name, value):
    it = dx.item(name)
    return _one(emu, dx.write_packet(i, it.address, dx.encode_value(value, it.size, it.signed)))


def _read(emu, i, name):
    it = dx.item(name)
    st = _one(emu, dx.read_packet(i, it.address, it.size))
    assert st.error == 0
    return dx.decode_value(st.params, it.signed)


def test_trapezoid_profile_and_history_on_manual_clock():
    clk = ManualClock(t0=100.0)
    emu = DxlEmulator(clk, [ServoSpec(1, "nod", initial_angle_rad=-0.5)])
    assert emu.joint_angle("nod") == pytest.approx(-0.5, abs=1e-12)
    _write(emu, 1, "torque_enable", 1)
    _write(emu, 1, "profile_velocity", 100)
    _write(emu, 1, "profile_acceleration", 50)
    t_cmd = clk.now()
    st = _write(emu, 1, "goal_position", dx.rad_to_ticks(0.5))
    assert st.error == 0 and st.params == b""
    v = 100 * dx.RAD_S_PER_VELOCITY_UNIT
    a = 50 * 214.577 * 2 * math.pi / 3600
    goal = dx.ticks_to_rad(dx.rad_to_ticks(0.5))
    start = -0.5  # the shaft is not quantised; only reported positions are
    dist = goal - start
    t_acc = v / a
    assert v * t_acc < dist  # trapezoid, not triangle
    t_total = 2 * t_acc + (dist - v * t_acc) / v
    # acceleration phase is quadratic
    clk.advance(t_acc / 2)
    assert emu.joint_angle(1) == pytest.approx(start + 0.5 * a * (t_acc / 2) ** 2, abs=1e-9)
    assert _read(emu, 1, "moving") == 1
    clk.advance(t_total - t_acc / 2 - 1e-3)
    assert _read(emu, 1, "moving") == 1
    clk.advance(2e-3)
    assert _read(emu, 1, "moving") == 0
    assert _read(emu, 1, "present_position") == dx.rad_to_ticks(0.5)
    assert _read(emu, 1, "realtime_tick") == int(clk.now() * 1000) % 32768
    # history: past times evaluate the old segment, vectorised
    ts = t_cmd + np.array([-1.0, 0.0, t_acc, t_total, t_total + 5, t_acc + 0.1])
    ang = emu.joint_angle(1, ts)
    assert ang.shape == (6,)
    assert ang[5] == pytest.approx(start + 0.5 * a * t_acc**2 + v * 0.1, abs=1e-9)
    np.testing.assert_allclose(ang[[0, 1, 3, 4]], [start, start, goal, goal], atol=1e-9)
    assert ang[2] == pytest.approx(start + 0.5 * a * t_acc**2, abs=1e-9)


def test_reg_write_action_broadcast_and_status_level():
    clk = ManualClock()
    emu = DxlEmulator(clk)
    it = dx.item("led")
    st = _one(emu, dx.reg_write_packet(2, it.address, b"\x01"))
    assert st.error == 0
    assert _read(emu, 2, "registered_instruction") == 1
    assert _read(emu, 2, "led") == 0
    assert emu.handle_packet(dx.action_packet()) == []  # broadcast: no reply
    assert _read(emu, 2, "led") == 1
    # broadcast write reaches every servo, no reply
    assert emu.handle_packet(dx.write_packet(dx.BROADCAST_ID, it.address, b"\x01")) == []
    assert [_read(emu, i, "led") for i in (1, 2, 3)] == [1, 1, 1]
    # status return level 1: only reads (and pings) answer
    it_level = dx.item("status_return_level")
    assert emu.handle_packet(dx.write_packet(3, it_level.address, b"\x01")) == []
    assert emu.handle_packet(dx.write_packet(3, it.address, b"\x00")) == []
    assert _read(emu, 3, "led") == 0
    # unknown instruction, bad length
    st = _one(emu, dx.InstructionPacket(1, 0x30))
    assert st.error_code is dx.ErrorCode.INSTRUCTION
    st = _one(emu, dx.InstructionPacket(1, dx.Instruction.READ, b"\x00"))
    assert st.error_code is dx.ErrorCode.DATA_LENGTH


def test_handle_bytes_crc_error_and_garbage():
    emu = DxlEmulator(ManualClock())
    parser = dx.PacketParser()
    bad = bytearray(dx.ping_packet(1).encode())
    bad[-2] ^= 1
    out = emu.handle_bytes(b"\x00\x13" + bytes(bad) + dx.ping_packet(2).encode(), parser)
    p2 = dx.PacketParser()
    p2.feed(out)
    replies = list(p2.packets())
    assert [r.id for r in replies] == [1, 2]
    assert replies[0].error_code is dx.ErrorCode.CRC
    assert dx.decode_value(replies[1].params[:2]) == dx.XM430_W350_MODEL_NUMBER
    assert emu.crc_errors == 1


def test_servo_spec_validation():
    with pytest.raises(ParameterError, match="servo.id"):
        ServoSpec(300)
    with pytest.raises(ParameterError, match="servo.initial_angle_rad"):
        ServoSpec(1, min_angle_rad=-0.1, max_angle_rad=0.1, initial_angle_rad=0.5)
    with pytest.raises(ParameterError, match="emulator.servo_ids"):
        DxlEmulator(ManualClock(), [ServoSpec(1), ServoSpec(1)])
    with pytest.raises(ParameterError, match="servo"):
        DxlEmulator(ManualClock()).joint_angle(7)


# -- our driver ------------------------------------------------------------------------


def test_driver_over_tcp_and_pty(emu, clock):
    for url in (emu.serve_tcp(), emu.serve_pty()):
        with DynamixelBus(url, time_source=clock.now) as bus:
            assert [p.id for p in bus.discover()] == [1, 2, 3]
            assert [p.id for p in bus.discover([1, 3, 5])] == [1, 3]
            assert bus.ping(2).model_number == dx.XM430_W350_MODEL_NUMBER
            assert bus.present_angles([1, 2, 3]) == {1: 0.0, 2: 0.0, 3: 0.0}
    assert url.startswith("/dev/")


def test_driver_errors(emu, clock):
    with DynamixelBus(emu.serve_tcp(), time_source=clock.now, timeout_s=0.02) as bus:
        with pytest.raises(DeviceError, match="missing"):
            bus.ping(9)
        bus.write(1, "max_position_limit", dx.rad_to_ticks(0.5))
        bus.set_torque(1, True)
        with pytest.raises(DeviceError, match="goal_position .* data_limit"):
            bus.set_goal_angle(1, 0.8)
        with pytest.raises(ParameterError, match="servo.goal_angle_rad"):
            bus.set_goal_angle(1, 4.0)
        rate = bus.set_profile_velocity(1, 0.5)
        assert rate == pytest.approx(0.5, abs=dx.RAD_S_PER_VELOCITY_UNIT / 2)
    with pytest.raises(DeviceError, match="not open"):
        bus.ping(1)


def _step_clock(clock, done, readers, *, dt, max_steps, wall_timeout_s=20.0):
    """Advance a ManualClock by ``dt`` until ``done()``; after each step wait until every
    reader (a callable giving the time of its last read) has read at the new time, so the
    threads see every step - an event wait, not a sleep that hopes."""
    for _ in range(max_steps):
        if done():
            return True
        clock.advance(dt)
        now = clock.now()
        deadline = time.monotonic() + wall_timeout_s
        while not all(r() >= now for r in readers):
            assert time.monotonic() < deadline, "a reader stopped reading the bus"
            time.sleep(0.0002)
    return done()


def test_nod_ramp_follows_profile(manual):
    clock, emu = manual
    prof = NodProfile(lower_rad=-0.2, upper_rad=0.15, rate_rad_s=0.5)
    dt = 0.005  # simulated step [s]: 2.5 mrad (1.6 ticks) of nod per step
    with DynamixelBus(emu.serve_pty(), time_source=clock.now) as bus:
        sampler = PositionSampler(bus, period_s=0.0005)
        nod = NodController(bus, prof, poll_interval_s=0.0005)
        with sampler, nod:
            readers = [lambda: sampler.buffer.last_time_s,
                       lambda: nod.last_state.host_time_s if nod.last_state else -math.inf]
            assert _step_clock(clock, lambda: nod.sweeps >= 4 or nod.error is not None,
                               readers, dt=dt, max_steps=2000)
        s = sampler.samples()
        rate = nod.effective_rate_rad_s
    assert nod.error is None and sampler.errors == 0
    assert rate == pytest.approx(prof.rate_rad_s, abs=dx.RAD_S_PER_VELOCITY_UNIT)
    turns = list(nod.turns)
    assert [g for _, g in turns[:5]] == [-0.2, 0.15, -0.2, 0.15, -0.2]
    # samples agree with the emulator's ground truth: whole ticks (0.5 tick) plus a READ
    # that straddled an advance, stamped mid-way (half a step, 0.8 tick)
    truth = emu.joint_angle(1, s.host_time_s)
    err_ticks = np.abs(truth - s.angle_rad) / dx.RAD_PER_TICK
    assert np.max(err_ticks) <= 0.5 + 0.5 * dt * rate / dx.RAD_PER_TICK + 1e-9
    # ... and with the commanded ramp: from each turn, a line at the nod rate (starting
    # within the arrival tolerance of the turn, 2.5 ticks, plus the error above)
    checked = 0
    for (t0, g0), (t1, g1) in zip(turns[1:], turns[2:], strict=False):
        sel = (s.host_time_s > t0) & (s.host_time_s < t1)
        direction = math.copysign(1.0, g0 - g1)
        expect = np.clip(
            g1 + direction * rate * (s.host_time_s[sel] - t0), prof.lower_rad, prof.upper_rad
        )
        assert np.max(np.abs(expect - s.angle_rad[sel])) < 5.0 * dx.RAD_PER_TICK
        mid = sel & (s.angle_rad > prof.lower_rad + 0.05) & (s.angle_rad < prof.upper_rad - 0.05)
        slope = np.polyfit(s.host_time_s[mid], s.angle_rad[mid], 1)[0]
        assert slope == pytest.approx(-direction * -rate, rel=0.01)
        checked += 1
    assert checked >= 2
    # each sweep takes the nominal time, less the arrival tolerance, plus at most a step
    dt_turn = np.diff([t for t, _ in turns[1:]])
    nominal = prof.amplitude_rad / rate
    tol_s = nod.tolerance_rad / rate
    assert np.all(dt_turn >= nominal - 2 * tol_s - 1e-9)
    assert np.all(dt_turn <= nominal + 2 * dt + 1e-9)
    # the servo's realtime tick runs with the shared clock (whole ms)
    tick_s = unwrap_tick_ms(s.tick_ms)
    np.testing.assert_allclose(tick_s, s.host_time_s - s.host_time_s[0], atol=1e-3 + dt)
    # a beam time between samples gets the interpolated ground-truth angle (one sample
    # per clock step: the same time read twice is one sample)
    _, first = np.unique(s.host_time_s, return_index=True)
    q = np.linspace(s.host_time_s[0], s.host_time_s[-1], 500)
    est = interpolate_angle(s.host_time_s[first], s.angle_rad[first], q)
    assert np.max(np.abs(est - emu.joint_angle(1, q))) < 0.02


def test_mirror_lift_and_reset(emu, clock):
    left = MirrorLiftProfile(deployed_rad=0.0, lifted_rad=1.2, rate_rad_s=3.0)
    right = MirrorLiftProfile(deployed_rad=0.0, lifted_rad=-1.2, rate_rad_s=3.0)
    with DynamixelBus(emu.serve_tcp(), time_source=clock.now) as bus:
        ml = MirrorLift(bus, left, right)
        assert ml.state() == {"left": "deployed", "right": "deployed"}
        ml.lift()
        assert ml.state() == {"left": "lifted", "right": "lifted"}
        truth = emu.joint_angles()
        assert truth[2] == pytest.approx(1.2, abs=dx.RAD_PER_TICK)
        assert truth[3] == pytest.approx(-1.2, abs=dx.RAD_PER_TICK)
        assert truth[1] == 0.0  # nod untouched
        ml.reset("left")
        assert ml.state() == {"left": "deployed", "right": "lifted"}
        with pytest.raises(ParameterError, match="mirror.side"):
            ml.lift("middle")


# -- pure helpers -------------------------------------------------------------------


def test_interpolate_angle_against_analytic_ramp():
    prof = NodProfile(-0.4, 0.3, 0.7)
    rng = np.random.default_rng(0)
    ts = np.sort(rng.uniform(0.0, 5.0, 4000))
    ts = np.unique(ts)
    q = rng.uniform(ts[0], ts[-1], 20000)
    est = interpolate_angle(ts, prof.angle_at(ts), q)
    err = np.abs(est - prof.angle_at(q))
    # exact on straight pieces; near a turnaround off by at most rate * (sample gap)
    assert np.max(err) <= prof.rate_rad_s * np.max(np.diff(ts)) + 1e-12
    vertices = np.arange(0, 6) * prof.sweep_time_s
    far = np.min(np.abs(q[:, None] - vertices[None, :]), axis=1) > np.max(np.diff(ts))
    assert np.max(err[far]) < 1e-12
    # shape preserved
    assert interpolate_angle(ts, prof.angle_at(ts), q.reshape(100, 200)).shape == (100, 200)


def test_interpolate_angle_outside_and_validation():
    t = np.array([0.0, 1.0, 2.0])
    a = np.array([0.0, 1.0, 0.0])
    q = np.array([-1.0, 0.5, 3.0])
    np.testing.assert_array_equal(interpolate_angle(t, a, q)[[1]], [0.5])
    assert np.isnan(interpolate_angle(t, a, q)[[0, 2]]).all()
    np.testing.assert_allclose(interpolate_angle(t, a, q, outside="clamp"), [0, 0.5, 0])
    np.testing.assert_allclose(interpolate_angle(t, a, q, outside="extrapolate"), [-1, 0.5, -1])
    with pytest.raises(ParameterError, match=r"sample_times\[2\]"):
        interpolate_angle([0, 1, 1], [0, 0, 0], [0.5])
    with pytest.raises(ParameterError, match="sample_angles.shape"):
        interpolate_angle([0, 1], [0], [0.5])
    with pytest.raises(ParameterError, match="outside"):
        interpolate_angle(t, a, q, outside="wrap")


def test_nod_profile():
    p = NodProfile(-0.2, 0.4, 0.3)
    assert p.sweep_time_s == pytest.approx(2.0) and p.period_s == pytest.approx(4.0)
    np.testing.assert_allclose(p.angle_at([0, 1, 2, 3, 4, 5]), [-0.2, 0.1, 0.4, 0.1, -0.2, 0.1])
    with pytest.raises(ParameterError, match="nod.limits_rad"):
        NodProfile(0.4, 0.2, 0.3)
    with pytest.raises(ParameterError, match="nod.rate_rad_s"):
        NodProfile(-0.2, 0.2, 0.0)
    with pytest.raises(ParameterError, match="mirror.lifted_rad"):
        MirrorLiftProfile(0.5, 0.5)


def test_sample_buffer_and_tick_unwrap():
    buf = SampleBuffer(capacity=4)
    for i in range(6):
        buf.append(float(i), i * 10, 0.1 * i)
    s = buf.snapshot()
    np.testing.assert_array_equal(s.host_time_s, [2, 3, 4, 5])
    assert len(buf) == 4 and buf.dropped == 2
    np.testing.assert_array_equal(buf.snapshot(since_s=3.5).host_time_s, [4, 5])
    np.testing.assert_allclose(unwrap_tick_ms([32760, 32767, 5, 100]), [0, 0.007, 0.013, 0.108])


# -- the rest of Protocol 2.0, each through dynamixel-sdk ---------------------------------


@pytest.fixture
def sdk_manual(manual):
    """dynamixel-sdk on the manual-clock emulator (servos hold still unless advanced)."""
    clock, emu = manual
    port = sdk.PortHandler(emu.serve_pty())
    assert port.openPort() and port.setBaudRate(57600)
    yield port, sdk.PacketHandler(2.0), clock, emu
    port.closePort()


def test_sdk_bulk_write_and_bulk_read(sdk_manual):
    port, ph, clock, emu = sdk_manual
    bw = sdk.GroupBulkWrite(port, ph)
    assert bw.addParam(1, 64, 1, [1])  # torque on
    assert bw.addParam(2, 112, 4, list((77).to_bytes(4, "little")))  # profile velocity
    assert bw.txPacket() == sdk.COMM_SUCCESS
    # the writes took effect, read back one by one
    assert ok(ph.read1ByteTxRx(port, 1, 64)) == 1
    assert ok(ph.read4ByteTxRx(port, 2, 112)) == 77
    assert ok(ph.read1ByteTxRx(port, 2, 64)) == 0  # only what was asked
    for fast in (False, True):
        br = sdk.GroupBulkRead(port, ph)
        assert br.addParam(1, 64, 1) and br.addParam(2, 112, 4) and br.addParam(3, 132, 4)
        assert (br.fastBulkRead() if fast else br.txRxPacket()) == sdk.COMM_SUCCESS, fast
        assert br.getData(1, 64, 1) == 1
        assert br.getData(2, 112, 4) == 77
        assert br.getData(3, 132, 4) == 2048
    # a malformed bulk write (block cut short) changes nothing
    emu.handle_packet(dx.InstructionPacket(254, dx.Instruction.BULK_WRITE,
                                           bytes([3, 64, 0, 1, 0])))
    assert ok(ph.read1ByteTxRx(port, 3, 64)) == 0


def test_sdk_fast_sync_read(sdk_manual):
    port, ph, clock, emu = sdk_manual
    ok(ph.write1ByteTxRx(port, 3, 64, 1))
    ok(ph.write4ByteTxRx(port, 3, 116, 2100))
    clock.advance(5.0)  # arrived
    sr = sdk.GroupSyncRead(port, ph, 132, 4)
    for i in (1, 2, 3):
        assert sr.addParam(i)
    assert sr.fastSyncRead() == sdk.COMM_SUCCESS
    assert [sr.getData(i, 132, 4) for i in (1, 2, 3)] == [2048, 2048, 2100]
    # ... the same values as the plain SYNC_READ (one status packet per servo)
    assert sr.txRxPacket() == sdk.COMM_SUCCESS
    assert [sr.getData(i, 132, 4) for i in (1, 2, 3)] == [2048, 2048, 2100]
    # the fast reply: one packet from ID 0xFE whose last CRC is the packet's own
    (reply,) = emu.handle_packet(dx.InstructionPacket(
        254, dx.Instruction.FAST_SYNC_READ, bytes([132, 0, 4, 0, 1, 3])))
    frame = reply.encode()
    assert frame[4] == 0xFE and frame[7] == 0x55
    assert dx.crc16(frame[:-2]) == frame[-2] | frame[-1] << 8
    assert frame[5] | frame[6] << 8 == len(frame) - 7


def test_sdk_reboot_one_and_broadcast(sdk_manual):
    port, ph, clock, emu = sdk_manual
    ok(ph.write4ByteTxRx(port, 2, 48, 3000))  # EEPROM: max position limit
    ok(ph.write1ByteTxRx(port, 2, 65, 1))  # LED on (RAM)
    ok(ph.write1ByteTxRx(port, 2, 64, 1))
    ok(ph.write4ByteTxRx(port, 2, 116, 2500))
    clock.advance(0.1)  # moving
    comm, err = ph.reboot(port, 2)
    assert (comm, err) == (sdk.COMM_SUCCESS, 0)
    here = ok(ph.read4ByteTxRx(port, 2, 132))
    assert 2048 < here < 2500
    assert ok(ph.read1ByteTxRx(port, 2, 64)) == 0  # torque off after a restart
    assert ok(ph.read1ByteTxRx(port, 2, 65)) == 0  # RAM back to power-up values
    assert ok(ph.read4ByteTxRx(port, 2, 116)) == here  # goal = where the shaft is
    assert ok(ph.read4ByteTxRx(port, 2, 48)) == 3000  # EEPROM kept
    clock.advance(5.0)
    assert ok(ph.read4ByteTxRx(port, 2, 132)) == here  # not moving on
    # broadcast: every servo restarts, nobody answers
    for i in (1, 3):
        ok(ph.write1ByteTxRx(port, i, 64, 1))
    assert ph.reboot(port, dx.BROADCAST_ID)[0] == sdk.COMM_SUCCESS
    assert [ok(ph.read1ByteTxRx(port, i, 64)) for i in (1, 2, 3)] == [0, 0, 0]
    assert [emu._servo(i).reboots for i in (1, 2, 3)] == [1, 2, 1]


def test_sdk_factory_reset_options():
    clock = ManualClock()
    specs = [ServoSpec(5, "a", max_angle_rad=1.0), ServoSpec(6, "b")]
    with DxlEmulator(clock, specs) as emu:
        port = sdk.PortHandler(emu.serve_pty())
        assert port.openPort()
        ph = sdk.PacketHandler(2.0)
        factory_max = ok(ph.read4ByteTxRx(port, 5, 48))
        assert factory_max == dx.rad_to_ticks(1.0)
        ok(ph.write4ByteTxRx(port, 5, 48, 2500))
        ok(ph.write1ByteTxRx(port, 5, 8, 3))  # baud rate 1 Mbps
        # 0x02: everything but ID and baud rate
        assert ph.factoryReset(port, 5, 0x02) == (sdk.COMM_SUCCESS, 0)
        assert ok(ph.read4ByteTxRx(port, 5, 48)) == factory_max
        assert ok(ph.read1ByteTxRx(port, 5, 8)) == 3
        # 0x01: everything but the ID
        assert ph.factoryReset(port, 5, 0x01) == (sdk.COMM_SUCCESS, 0)
        assert ok(ph.read1ByteTxRx(port, 5, 8)) == 1
        # a bad option is refused
        assert ph.factoryReset(port, 5, 0x07) == (sdk.COMM_SUCCESS, dx.ErrorCode.DATA_RANGE)
        # broadcast 0xFF would give every servo ID 1: ignored
        assert ph.factoryReset(port, dx.BROADCAST_ID, 0xFF)[0] == sdk.COMM_SUCCESS
        assert sorted(ph.broadcastPing(port)[0]) == [5, 6]
        # 0xFF: the factory ID (1) too; the status came from the old ID
        assert ph.factoryReset(port, 6, 0xFF) == (sdk.COMM_SUCCESS, 0)
        assert sorted(ph.broadcastPing(port)[0]) == [1, 5]
        assert ok(ph.read1ByteTxRx(port, 1, 7)) == 1
        port.closePort()


def test_sdk_clear(sdk_manual):
    port, ph, clock, emu = sdk_manual
    assert ph.clearMultiTurn(port, 1) == (sdk.COMM_SUCCESS, 0)
    ok(ph.write1ByteTxRx(port, 1, 64, 1))
    ok(ph.write4ByteTxRx(port, 1, 116, 3000))
    clock.advance(0.1)
    # only a stopped servo may be cleared
    assert ph.clearMultiTurn(port, 1) == (sdk.COMM_SUCCESS, dx.ErrorCode.RESULT_FAIL)
    clock.advance(10.0)
    assert ph.clearMultiTurn(port, 1) == (sdk.COMM_SUCCESS, 0)
    assert ok(ph.read4ByteTxRx(port, 1, 132)) == 3000
    # the fixed key is part of the instruction
    (st,) = emu.handle_packet(dx.InstructionPacket(1, dx.Instruction.CLEAR, b"\x01DXL!"))
    assert st.error == dx.ErrorCode.DATA_RANGE
    (st,) = emu.handle_packet(dx.InstructionPacket(1, dx.Instruction.CLEAR, b"\x01"))
    assert st.error == dx.ErrorCode.DATA_LENGTH
    # unknown instructions still answer "instruction error"
    (st,) = emu.handle_packet(dx.InstructionPacket(1, 0x20))
    assert st.error == dx.ErrorCode.INSTRUCTION


def test_tcp_server_caps_connections_and_listens_on_loopback(manual):
    import socket

    _clock, emu = manual
    url = emu.serve_tcp(max_connections=3)
    host, port = url.removeprefix("socket://").rsplit(":", 1)
    assert host == "127.0.0.1"
    ping = dx.ping_packet(1).encode()
    socks = []
    for _ in range(10):
        c = socket.create_connection((host, int(port)), timeout=5)
        socks.append(c)
    served, refused = 0, 0
    for c in socks:
        c.sendall(ping)
        try:
            data = c.recv(64)
        except (ConnectionResetError, TimeoutError):
            data = b""
        if data:
            assert isinstance(dx.decode_packet(data), dx.StatusPacket)
            served += 1
        else:
            refused += 1
    assert served == 3 and refused == 7
    assert emu.refused_connections == 7
    for c in socks:
        c.close()
    # a closed client frees its place
    deadline = time.monotonic() + 10
    while emu.connections and time.monotonic() < deadline:
        time.sleep(0.01)
    assert emu.connections == 0
    with socket.create_connection((host, int(port)), timeout=5) as c:
        c.sendall(ping)
        assert isinstance(dx.decode_packet(c.recv(64)), dx.StatusPacket)
    with pytest.raises(ParameterError, match="max_connections"):
        emu.serve_tcp(max_connections=0)


def test_nod_stall_is_reported_once(manual):
    clock, emu = manual
    prof = NodProfile(lower_rad=-0.2, upper_rad=0.15, rate_rad_s=0.5)
    with DynamixelBus(emu.serve_pty(), time_source=clock.now) as bus:
        nod = NodController(bus, prof, poll_interval_s=0.0005, stall_timeout_s=0.5)
        t_seized = t_err = None
        with pytest.raises(DeviceError, match="nod controller failed: .* not reached") as caught:
            with nod:
                reader = [lambda: nod.last_state.host_time_s if nod.last_state else -math.inf]
                assert _step_clock(clock, lambda: nod.sweeps >= 1, reader, dt=0.005,
                                   max_steps=1000)
                emu.set_angle("nod", 0.0)  # seized mid-ramp: torque off, shaft held
                t_seized = clock.now()
                _step_clock(clock, lambda: nod.error is not None, reader, dt=0.005,
                            max_steps=1000)
                t_err = clock.now()
    # the stall reported must be the seizure's: one before it (seen once in a full run on
    # this machine, not reproduced in 25 runs under load) ended the body early - say where
    assert t_err is not None, (
        f"the nod controller failed before the seizure was over (seized at {t_seized}, "
        f"sweeps {nod.sweeps}, last state {nod.last_state}): {caught.value}; the test's own "
        f"error: {caught.value.__context__!r}")
    # reported once the ramp's nominal time plus the stall timeout have passed since its
    # goal was set (a step or two before the seizure), to within a few clock steps
    nominal = prof.amplitude_rad / prof.rate_rad_s
    assert t_err - t_seized == pytest.approx(nominal + 0.5, abs=4 * 0.005)
