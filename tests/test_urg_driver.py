"""UrgDriver against the SCIP 2.0 emulator over TCP and a pty, with and without faults.

Tests that check a stream's timing (consecutive timestamps, no drops, the 24-bit wrap) run
on a :class:`ManualClock` moved by a :class:`Pacer`, so a loaded machine cannot make the
emulator skip scans; the fault tests run on a fast real-time clock and check correctness
(ground truth, exact drop counts) and generous recovery bounds only.
"""

from __future__ import annotations

import gc
import math
import socket
import threading
import time

import numpy as np
import psutil
import pytest
import serial

from nodlidar import scip
from nodlidar.errors import DeviceError, NodlidarError, ParameterError, ProtocolError
from nodlidar.lidar import lidar_model
from nodlidar.runtime.urg import UrgDriver
from nodlidar.sim.clock import ManualClock, SimClock
from nodlidar.sim.faults import FaultConfig
from nodlidar.sim.scip_emulator import ScipEmulator, flat_wall_source

URG = lidar_model("URG-04LX")
RATE = 20.0  # simulated seconds per wall second


def random_source(k: int, t: float) -> np.ndarray:
    """Different ranges every scan (so a scan from the wrong index cannot match)."""
    rng = np.random.default_rng(k)
    r = 0.05 + 6.0 * rng.random(URG.n_steps)  # some beyond DMAX -> code 0
    r[rng.random(URG.n_steps) < 0.05] = np.nan
    return r


def assert_ground_truth(emu: ScipEmulator, scan) -> None:
    k = emu.scan_index(scan.timestamp_ms)
    expected = emu.expected_ranges_mm(k, scan.request)
    assert np.array_equal(scan.ranges_mm, expected), f"scan {scan.seq} (k={k}) is corrupt"


class Pacer:
    """Moves a :class:`ManualClock` to each next scan the emulator has due, at most
    ``lead`` scans ahead of what the driver has delivered or counted as dropped (waiting
    on the emulator's and the driver's counters, never on wall time). The emulator is
    then never behind its clock, so it never skips scans, and the driver never waits long
    for one."""

    def __init__(self, emu: ScipEmulator, clock: ManualClock, drv: UrgDriver, lead: int = 3):
        self.emu, self.clock, self.drv, self.lead = emu, clock, drv, lead
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="pacer", daemon=True)

    def __enter__(self) -> Pacer:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join(5.0)

    def _run(self) -> None:
        emu, drv = self.emu, self.drv
        while not self._stop.is_set():
            due = emu.device.next_due()
            # scans sent that the driver has neither delivered nor counted as dropped
            ahead = emu.stats.scans_sent - drv.stats.scans - drv.stats.dropped_scans
            if due is None or ahead >= self.lead:
                self._stop.wait(0.001)  # polling two counters; nothing is due yet
                continue
            sent = emu.stats.scans_sent
            self.clock.advance(max(0.0, due - self.clock.now()))
            emu.wait_for(lambda st, sent=sent: st.scans_sent > sent or self._stop.is_set(), 5.0)


@pytest.fixture(params=["tcp", "pty"])
def emulator(request, tmp_path):
    def make(**kw):
        emu = ScipEmulator(URG, kw.pop("clock", SimClock(rate=RATE)), kw.pop("source",
                           random_source), **kw)
        port = emu.serve_tcp() if request.param == "tcp" else emu.serve_pty(tmp_path / "ttyURG")
        made.append(emu)
        return emu, port

    made: list[ScipEmulator] = []
    yield make
    for emu in made:
        emu.stop()


def test_info(emulator):
    emu, port = emulator()
    with UrgDriver(port, timeout=0.5) as drv:
        info = drv.info()
        assert info.version.protocol == "SCIP 2.0"
        assert info.params.amin == 44 and info.params.amax == 725
        assert not info.state.laser_on
        assert drv.model == URG


def test_single_scan_equals_source(emulator):
    emu, port = emulator()
    with UrgDriver(port, timeout=0.5) as drv:
        scan = drv.scan()
        k = emu.scan_index(scan.timestamp_ms)
        src = random_source(k, k * URG.scan_period_s)
        mm = np.rint(src * 1000)
        valid = np.isfinite(src) & (mm >= 20) & (mm <= 5600)
        assert np.array_equal(np.isnan(scan.ranges_m), ~valid)
        np.testing.assert_array_equal(scan.ranges_m[valid], mm[valid] / 1000)
        assert scan.steps.tolist() == list(range(44, 726))
        assert_ground_truth(emu, scan)
        part = drv.scan(300, 400, 3, command="GS")
        assert part.ranges_mm.size == 34
        assert_ground_truth(emu, part)


def test_stream_n_scans(emulator):
    clock = ManualClock()
    emu, port = emulator(clock=clock)
    with UrgDriver(port, timeout=2.0) as drv, Pacer(emu, clock, drv):
        scans = list(drv.stream(count=150))
        assert len(scans) == 150
        assert [s.index for s in scans] == list(range(150))
        assert np.all(np.diff([s.timestamp_ms for s in scans]) == 100)
        assert all(s.remaining == 0 for s in scans)  # >99: endless MD stopped by driver
        for s in scans:
            assert_ground_truth(emu, s)
        assert drv.stats.dropped_scans == 0 and drv.stats.rejected_messages == 0
        # the stream was stopped: a plain request works right away
        assert drv.state().laser == "OFF"


def test_stream_finite_interval_cluster():
    clock = ManualClock()
    with ScipEmulator(URG, clock, random_source) as emu, \
            UrgDriver(emu.serve_tcp(), timeout=2.0) as drv, Pacer(emu, clock, drv):
        scans = list(drv.stream(100, 200, cluster=4, interval=1, count=5, command="MS"))
        assert [s.remaining for s in scans] == [4, 3, 2, 1, 0]
        assert [s.index for s in scans] == [0, 2, 4, 6, 8]
        assert drv.stats.dropped_scans == 0
        for s in scans:
            assert s.ranges_mm.size == 26
            assert_ground_truth(emu, s)
        # break out of an endless stream: QT is sent, the device is idle again
        for s in drv.stream():
            if s.index == 3:
                break
        assert not drv.state().laser_on


def test_handshake_from_scip11(emulator):
    emu, port = emulator(scip1=True)
    with UrgDriver(port, timeout=0.5) as drv:
        assert drv.version().protocol == "SCIP 2.0"
        assert_ground_truth(emu, drv.scan())


def test_handshake_from_running_stream_and_tm_mode(tmp_path):
    link = tmp_path / "ttyURG"
    with ScipEmulator(URG, SimClock(rate=RATE), random_source) as emu:
        port = emu.serve_pty(link)
        with serial.Serial(port, timeout=1) as raw:  # someone left a stream running
            raw.write(b"MD0044072501000\n")
            assert raw.read_until(b"\n\n") == b"MD0044072501000\n00P\n\n"
            assert raw.read(3000)
        n0 = emu.stats.scans_sent
        assert emu.wait_for(lambda st: st.scans_sent >= n0 + 3)  # scans pile up in the tty
        with UrgDriver(port, timeout=0.5) as drv:
            assert drv.stats.stale_messages > 0
            assert drv.parameters().amax == 725
            scans = list(drv.stream(count=10))
            for s in scans:
                assert_ground_truth(emu, s)
        with serial.Serial(port, timeout=1) as raw:  # ...or left it in time-adjust mode
            time.sleep(0.05)
            raw.reset_input_buffer()  # the QT the driver sent when closing
            raw.write(b"TM0\n")
            assert raw.read_until(b"\n\n") == b"TM0\n00P\n\n"
        with UrgDriver(port, timeout=0.5) as drv:
            assert_ground_truth(emu, drv.scan())


def test_sync_clock_and_stamps():
    clock = SimClock(rate=1.0)
    with ScipEmulator(URG, clock, random_source) as emu, \
            UrgDriver(emu.serve_tcp(), timeout=0.5) as drv:
        sync = drv.sync_clock(samples=8)
        # device time = clock time = monotonic - wall0, so offset = wall0, within
        # ClockSync's bound: half the best round trip + the 1 ms timer resolution (a fixed
        # 3 ms failed when a loaded machine stretched every round trip)
        bound = sync.rtt_s / 2 + 1e-3
        assert abs(sync.offset_s - clock._wall0) <= bound
        for s in drv.stream(count=3):
            k = emu.scan_index(s.timestamp_ms)
            true_start = clock._wall0 + k * URG.scan_period_s
            assert abs(s.stamp_s - true_start) <= bound
            assert s.host_time_s > s.stamp_s


def test_timestamp_unwraps_beyond_24_bits():
    clock = ManualClock()
    with ScipEmulator(URG, clock, random_source) as emu, \
            UrgDriver(emu.serve_tcp(), timeout=2.0) as drv, Pacer(emu, clock, drv):
        # the device timer 3 s short of the 24-bit wrap: the 6 s stream crosses it
        emu.device.reset_timer(clock.now() - ((1 << 24) - 3000) / 1000.0)
        scans = list(drv.stream(count=60))
        ts = np.array([s.timestamp_ms for s in scans])
        assert ts[0] < 1 << 24 <= ts[-1], "the stream did not cross the wrap"
        assert np.all(np.diff(ts) == 100)
        assert [s.index for s in scans] == list(range(60))


def test_parameter_errors():
    with pytest.raises(ParameterError, match="port"):
        UrgDriver(1234)
    with pytest.raises(ParameterError, match="timeout"):
        UrgDriver("socket://127.0.0.1:1", timeout=0)
    with ScipEmulator(URG, SimClock(rate=RATE)) as emu, \
            UrgDriver(emu.serve_tcp(), timeout=0.5) as drv:
        with pytest.raises(ParameterError, match="urg.steps"):
            drv.scan(0, 725)
        with pytest.raises(ParameterError, match="command"):
            drv.stream(command="GD")
        with pytest.raises(ParameterError, match="interval"):
            next(drv.stream(interval=10))


def test_garbled_pp_is_asked_again_vv_is_tolerated_with_a_warning():
    """PP (the step geometry) with a line that fails its checksum is requested again; a
    VV text line that fails is kept with a ScipChecksumWarning (as real firmware needs).
    Emulator messages: 0 = QT of the handshake, 1 = PP, 2 = PP again, 3 = VV."""
    with ScipEmulator(URG, SimClock(rate=RATE), random_source,
                      faults=FaultConfig(garble_at=(1, 3))) as emu, \
            UrgDriver(emu.serve_tcp(), timeout=0.5) as drv:
        assert drv.stats.bad_info_replies == 1
        assert drv.params == scip.SensorParams.from_lidar_model(URG)
        with pytest.warns(scip.ScipChecksumWarning):
            vv = drv.version()
        assert vv.vendor == "Hokuyo Automatic Co.,Ltd/"  # the garbled '.', kept
        assert emu.stats.bytes_corrupted == 2
    # garbled three times in a row: accepted in the end, with the warning
    with ScipEmulator(URG, SimClock(rate=RATE), random_source,
                      faults=FaultConfig(garble_at=(1, 2, 3))) as emu, \
            pytest.warns(scip.ScipChecksumWarning), \
            UrgDriver(emu.serve_tcp(), timeout=0.5) as drv:
        assert drv.stats.bad_info_replies == 2
        assert drv.params.model.endswith("Ltd.(")


def test_no_device():
    drv = UrgDriver("socket://127.0.0.1:9", timeout=0.2)
    assert not drv.is_open
    with pytest.raises((serial.SerialException, OSError)):
        drv.open()


@pytest.mark.parametrize("talk", [b"", b"\x00\xf3garbage at the wrong baud rate\n\n" * 3])
def test_port_that_never_answers(talk):
    """The most common mistake - the wrong port or baud rate: something is there but no
    SCIP comes back. open() raises one public line (it leaked the private _LinkLost)."""
    ls = socket.socket()
    ls.bind(("127.0.0.1", 0))
    ls.listen(1)
    url = f"socket://127.0.0.1:{ls.getsockname()[1]}"

    def serve():
        conn, _ = ls.accept()
        conn.recv(100)
        conn.sendall(talk)
        while conn.recv(100):  # hold the line open until the driver gives up
            pass
        conn.close()

    t = threading.Thread(target=serve, daemon=True)
    t.start()
    drv = UrgDriver(url, timeout=0.3)
    with pytest.raises(DeviceError) as ei:
        drv.open()
    msg = str(ei.value)
    assert "\n" not in msg and msg.endswith(": check the port and baud rate")
    assert msg.startswith(f"no SCIP reply from {url} within 0.3 s") if not talk else \
        msg.startswith(f"no valid SCIP reply from {url} within 0.3 s (")
    assert not drv.is_open
    t.join(5)
    ls.close()


class _PP:
    """The PP parameters a faulty device reports (``overrides`` by PP key)."""

    def __init__(self, good: scip.SensorParams, **overrides: str):
        self.good, self.overrides = good, overrides

    def __getattr__(self, name):
        return getattr(self.good, name)

    def items(self):
        return [(k, self.overrides.get(k, v)) for k, v in self.good.items()]


@pytest.mark.parametrize(("key", "value"), [("SCAN", "0"), ("DMIN", "6000"), ("ARES", "0"),
                                            ("AFRT", "1000")])
def test_impossible_pp_reply_refused_on_open(key, value):
    """SCAN 0 gave ZeroDivisionError, DMIN 6000 all-NaN scans: open() asks PP three times
    and then raises a ProtocolError naming the field."""
    with ScipEmulator(URG, ManualClock()) as emu:
        emu.device.params = _PP(emu.device.params, **{key: value})
        drv = UrgDriver(emu.serve_tcp(), timeout=0.5)
        with pytest.raises(ProtocolError, match=rf"scip\.PP\.{key} = {value} is invalid"):
            drv.open()
        assert not drv.is_open and drv.stats.bad_info_replies == 2  # asked 3 times
        assert emu.wait_for(lambda st: st.commands_answered >= 4)  # QT + 3 x PP
    assert issubclass(ProtocolError, NodlidarError)


def test_lost_md_acknowledgement_is_not_fatal():
    """The stream's acknowledgement lost (message 2: after the handshake's QT and PP): the
    first scan message stands for it - no 'status 99; allowed 00' error, no reconnect,
    every scan delivered."""
    clock = ManualClock()
    for count in (5, 150):  # a finite request (echo counts down) and an endless one
        with ScipEmulator(URG, clock, random_source,
                          faults=FaultConfig(garble_at=(2,))) as emu, \
                UrgDriver(emu.serve_tcp(), timeout=2.0) as drv, Pacer(emu, clock, drv):
            scans = list(drv.stream(count=count))
            assert len(scans) == count and [s.index for s in scans] == list(range(count))
            for s in scans:
                assert_ground_truth(emu, s)
            assert drv.stats.lost_acks == 1 and drv.stats.reconnects == 0
            assert emu.stats.bytes_corrupted == 1


def test_statuses_inside_a_stream_are_resynced():
    """Inside a stream a scan message with status '9y' (the sum of '99': a corruption the
    checksum cannot see), a documented error status ('55' hardware, '0M' unstable) or
    '98' is dropped like a bad checksum and counted; the stream goes on (it died with
    ScipStatusError)."""
    clock = ManualClock()
    cfg = FaultConfig(status_at=((5, "9y"), (8, "55"), (11, "98"), (14, "0M")))
    with ScipEmulator(URG, clock, random_source, faults=cfg) as emu, \
            UrgDriver(emu.serve_tcp(), timeout=2.0) as drv, Pacer(emu, clock, drv):
        scans = list(drv.stream(count=100))  # > 99: an endless MD the driver stops
        for s in scans:
            assert_ground_truth(emu, s)
        st = drv.stats
        assert st.bad_statuses == 3 and st.rejected_messages == 1  # '9y': not a status
        assert st.dropped_scans == 4 and st.reconnects == 0
        assert len(scans) == 100 and scans[-1].index == 103


def test_plausibility_filter_in_the_driver():
    """A one-step spike (a thin pole) seen in one scan only is flagged (NaN in ranges_m,
    counted); the same spike in consecutive scans is confirmed from the second on."""
    base = flat_wall_source(URG, 1.0)

    def source(k: int, t: float) -> np.ndarray:
        r = base(k, t).copy()
        if k in (2, 5, 6, 7):
            r[384 - 44] = 1.5  # 500 mm behind the wall at the front step
        return r

    clock = ManualClock()
    with ScipEmulator(URG, clock, source) as emu, \
            UrgDriver(emu.serve_tcp(), timeout=2.0,
                      plausibility=scip.RangePlausibility()) as drv, Pacer(emu, clock, drv):
        scans = list(drv.stream(count=9))
    ks = [emu.scan_index(s.timestamp_ms) for s in scans]
    flagged = {k: np.flatnonzero(s.implausible).tolist() for k, s in zip(ks, scans,
                                                                         strict=True)}
    assert flagged == {0: [], 1: [], 2: [340], 3: [], 4: [], 5: [340], 6: [], 7: [], 8: []}
    for s in scans:
        assert np.array_equal(np.isnan(s.ranges_m), s.error_mask | s.implausible)
        assert_ground_truth(emu, s)  # ranges_mm keeps what the device sent
    assert drv.stats.implausible_values == 2
    with pytest.raises(ParameterError, match="plausibility"):
        UrgDriver("socket://127.0.0.1:1", plausibility=0.03)


# --- faults ----------------------------------------------------------------------------
def _run(drv, emu, n):
    scans = []
    for s in drv.stream(count=n):
        assert_ground_truth(emu, s)  # zero corrupt scans
        scans.append(s)
    return scans


def test_garbled_and_dropped_bytes(emulator):
    cfg = FaultConfig(seed=11, drop_byte_prob=1e-4, corrupt_byte_prob=1e-4, scans_only=True)
    emu, port = emulator(faults=cfg)
    with UrgDriver(port, timeout=0.5) as drv:
        scans = _run(drv, emu, 300)
        st = drv.stats
        assert emu.stats.bytes_dropped > 0 and emu.stats.bytes_corrupted > 0
        assert st.rejected_messages > 0
        idx = np.array([s.index for s in scans])
        assert st.dropped_scans == idx[-1] - idx[0] + 1 - len(scans) > 0
        assert len(scans) == 300


def test_stall(emulator):
    cfg = FaultConfig(stall_at=(40,), stall_s=12.0)  # 0.6 s of wall time at rate 20
    emu, port = emulator(faults=cfg)
    with UrgDriver(port, timeout=0.3) as drv:
        scans = _run(drv, emu, 120)
        assert emu.stats.stalls == 1
        assert drv.stats.timeouts >= 1 and drv.stats.reconnects >= 1
        assert drv.stats.dropped_scans > 0
        assert len(scans) == 120


def test_disconnect_and_recover(emulator):
    cfg = FaultConfig(disconnect_at=(40,), disconnect_s=10.0)  # away 0.5 s of wall time
    emu, port = emulator(faults=cfg)
    with UrgDriver(port, timeout=0.3, reconnect_timeout_s=5) as drv:
        scans = _run(drv, emu, 120)
        assert emu.stats.disconnects == 1 and len(emu.stats.up_times) == 1
        assert drv.stats.reconnects >= 1
        t_up = emu.stats.up_times[0]
        first_after = min(s.host_time_s for s in scans if s.host_time_s > t_up)
        assert first_after - t_up < 2.0
        assert drv.stats.dropped_scans > 0


def test_power_cycle_resyncs_clock_and_counts_the_outage():
    """The device goes away for 2.5 s (simulated) and comes back power cycled, its timer
    restarted at 0. After the reconnect the driver measures the clock offset again: every
    scan's host stamp stays within ClockSync's bound (RTT/2 + 1 ms) of its true start, on
    both sides of the outage, and the scans missed meanwhile are counted exactly."""
    rate = 5.0
    clock = SimClock(rate=rate)
    offset_ms = 5_000_000
    cfg = FaultConfig(disconnect_at=(30,), disconnect_s=2.5, scans_only=True)
    with ScipEmulator(URG, clock, random_source, faults=cfg, reboot_resets_timer=True,
                      timer_offset_ms=offset_ms) as emu, \
            UrgDriver(emu.serve_tcp(), timeout=0.3, reconnect_timeout_s=5) as drv:
        sync0 = drv.sync_clock(samples=8, time_source=clock.now)
        scans = list(drv.stream(count=60))
        sync1 = drv.clock_sync
        base1 = emu.device._timer_base_ms  # the timer after the power cycle
    assert emu.stats.disconnects == 1 and drv.stats.reconnects >= 1
    assert sync1 is not sync0
    period = URG.scan_period_s
    ks, errs, bounds = [], [], []
    for s in scans:
        raw_ts = scip.decode_scan(s.raw).timestamp_ms
        before = raw_ts >= offset_ms  # the old timer ran from 5 000 000 ms
        base, sync = (-offset_ms, sync0) if before else (base1, sync1)
        k = int(round((raw_ts + base) / (1000 * period)))
        assert np.array_equal(s.ranges_mm, emu.expected_ranges_mm(k, s.request))
        ks.append(k)
        errs.append(abs(s.stamp_s - k * period))  # true start of scan k: k * period
        bounds.append(sync.rtt_s / 2 + 1e-3 + 1e-9)
    ks = np.array(ks)
    assert (ks[1:] > ks[:-1]).all()
    assert np.any(ks < 25) and np.any(ks > 60)  # scans on both sides of the outage
    assert (np.array(errs) <= np.array(bounds)).all(), max(errs)
    lost = ks[-1] - ks[0] + 1 - len(scans)
    assert lost >= 20  # 2.5 s away at 10 scans/s
    # The driver places the first scan after the outage by the new clock sync (the device's
    # timer restarted), so its count of missed scans is exact while the two syncs' stated
    # bounds together stay under half a period, and off by at most the periods they span
    # otherwise (a loaded host stretches the RTT: at sim rate 5 a 10 ms stall is 50 ms)
    slack = (sync0.rtt_s / 2 + sync1.rtt_s / 2 + 2e-3) / period
    assert abs(drv.stats.dropped_scans - lost) <= math.floor(slack + 0.5), (slack, lost)


def test_gives_up_when_device_stays_away():
    cfg = FaultConfig(disconnect_at=(10,), disconnect_s=1e6)
    with ScipEmulator(URG, SimClock(rate=RATE), random_source, faults=cfg) as emu, \
            UrgDriver(emu.serve_tcp(), timeout=0.2, reconnect_timeout_s=0.5) as drv:
        with pytest.raises(DeviceError, match="did not come back"):
            _run(drv, emu, 50)


def test_random_faults_everywhere():
    """Faults on every message (handshake replies too): still nothing corrupt."""
    cfg = FaultConfig(seed=3, drop_byte_prob=5e-5, corrupt_byte_prob=5e-5, stall_prob=0.005,
                      stall_s=8.0, skip_messages=3)
    with ScipEmulator(URG, SimClock(rate=RATE), random_source, faults=cfg) as emu, \
            UrgDriver(emu.serve_tcp(), timeout=0.3) as drv:
        scans = _run(drv, emu, 250)
        assert len(scans) == 250


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_soak_10000_scans_under_faults():
    """A 10 000-scan endless stream with garbled and dropped bytes, two stalls and two
    disconnects (the device away 1 s of wall time, then back, rebooted):

    * every delivered scan equals the device's ground truth (zero corrupt scans);
    * the drop count is exact (:func:`assert_drops_exact`);
    * after each disconnect and each stall a scan arrives within 2 s of the device
      returning (its accept time after a disconnect, the end of a stall);
    * RSS grows by less than 8 MiB between scan 1000 and scan 10 000.
    """
    proc = psutil.Process()
    rate = 50.0  # simulated s per wall s: 10 000 scans in ~20 s of wall time
    cfg = FaultConfig(seed=9, drop_byte_prob=2e-5, corrupt_byte_prob=2e-5, scans_only=True,
                      stall_at=(2500, 7000), stall_s=0.3 * rate,
                      disconnect_at=(4500, 9000), disconnect_s=1.0 * rate)
    with ScipEmulator(URG, SimClock(rate=rate), random_source, faults=cfg) as emu, \
            UrgDriver(emu.serve_tcp(), timeout=0.5) as drv:
        rss = []
        host_t = np.empty(10_000)
        ks = np.empty(10_000, dtype=np.int64)
        n = 0
        for s in drv.stream(count=10_000):
            assert_ground_truth(emu, s)  # every scan, not a sample of them
            host_t[n], ks[n] = s.host_time_s, emu.scan_index(s.timestamp_ms)
            n += 1
            if n in (1000, 10_000):
                gc.collect()
                rss.append(proc.memory_info().rss)
        assert n == 10_000
        st = drv.stats
        assert emu.stats.disconnects == 2 and len(emu.stats.up_times) == 2
        assert emu.stats.stalls == 2 and len(emu.stats.stall_ends) == 2
        assert emu.stats.bytes_dropped > 0 and emu.stats.bytes_corrupted > 0
        assert st.rejected_messages > 0 and st.reconnects >= 2 and st.dropped_scans > 0
        assert np.all(np.diff(ks) > 0)  # each scan once, in order
        for t_back in emu.stats.up_times + emu.stats.stall_ends:
            after = host_t[host_t >= t_back]
            assert after.size, f"no scan after the device returned at {t_back:.3f}"
            assert after[0] - t_back < 2.0, f"recovered {after[0] - t_back:.2f} s after return"
        assert rss[1] - rss[0] < 8 * 2**20, f"RSS grew {(rss[1] - rss[0]) / 2**20:.1f} MiB"
        assert_drops_exact(emu, drv, int(ks[0]), int(ks[-1]))


def assert_drops_exact(emu: ScipEmulator, drv: UrgDriver, k_first: int, k_last: int) -> None:
    """The driver's drop count equals the device's ground truth between the first and the
    last delivered scan (scan numbers from the emulator's own timestamp -> k map).

    Scans the device sent *after* the last delivered one are not drops: when the consumer
    runs slower than the device (40x real time, a loaded machine) they sit in the socket
    buffer and the driver's inbox when the stream stops. Comparing against all scans the
    device produced (the old reference) counted them as "missed" - the ~5 % "undercount"
    (1067 vs 1010) was that backlog, not a counting error. Scans lost before the first
    delivered one cannot be seen by anyone without a clock sync and are excluded too.
    """
    st = drv.stats
    lost = (k_last - k_first + 1) - st.scans
    produced = emu.stats.scans_sent + emu.stats.scans_skipped
    assert st.dropped_scans == lost, (
        f"driver counted {st.dropped_scans} drops; device lost {lost} between scans "
        f"{k_first} and {k_last} ({produced} produced in all, {st.reconnects} reconnects)")


def test_drop_count_exact_with_slow_consumer():
    """Regression for the soak "undercount": a consumer slower than the device leaves a
    backlog of sent scans behind the last delivered one; the driver's count must still be
    exact between the first and last delivered scan (and the backlog must be there, or
    this test would not exercise the case)."""
    cfg = FaultConfig(seed=3, drop_byte_prob=1e-4, corrupt_byte_prob=1e-4, scans_only=True)
    with ScipEmulator(URG, SimClock(rate=40.0), random_source, faults=cfg) as emu, \
            UrgDriver(emu.serve_tcp(), timeout=0.5) as drv:
        ks = []
        for n, s in enumerate(drv.stream(count=300)):
            ks.append(emu.scan_index(s.timestamp_ms))
            if n % 10 == 0:
                time.sleep(0.06)  # 6 ms a scan vs the device's 2.5 ms: a backlog builds
        produced = emu.stats.scans_sent + emu.stats.scans_skipped
        assert drv.stats.dropped_scans > 0
        assert produced - (ks[-1] - ks[0] + 1) > 50  # the backlog the old reference counted
        assert_drops_exact(emu, drv, ks[0], ks[-1])
