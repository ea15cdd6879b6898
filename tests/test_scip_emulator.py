"""SCIP 2.0 emulator: spec exchanges byte for byte over TCP and a pty, MD/MS, errors.

Scan timing runs on a :class:`ManualClock` that the test moves to the next scan due
(:func:`next_scan`) and then waits on the emulator's statistics (``ScipEmulator.wait_for``),
never sleep-then-advance. The spec exchanges are read from tests/data/scip2.md.
"""

from __future__ import annotations

import re
import socket
import time
from pathlib import Path

import numpy as np
import pytest
import serial

from nodlidar import scip
from nodlidar.errors import ParameterError
from nodlidar.lidar import lidar_model
from nodlidar.sim.clock import ManualClock, SimClock
from nodlidar.sim.faults import FaultConfig, FaultInjector
from nodlidar.sim.scip_emulator import (
    ScipDevice,
    ScipEmulator,
    cluster_ranges,
    flat_wall_source,
    quantise_ranges,
)

URG = lidar_model("URG-04LX")


def spec_source(k: int, t: float) -> np.ndarray:
    """1000, 1234, 5432 mm at steps 384-386 (scip2.md §1.10 vector 12), 2 m elsewhere."""
    r = np.full(URG.n_steps, 2.0)
    r[384 - 44: 387 - 44] = [1.000, 1.234, 5.432]
    r[0] = np.nan
    return r


def gs_source(k: int, t: float) -> np.ndarray:
    r = spec_source(k, t).copy()
    r[386 - 44] = 4.095
    return r


class TcpClient:
    """Minimal raw-socket host for checking bytes on the wire."""

    def __init__(self, url: str):
        host, port = url.removeprefix("socket://").rsplit(":", 1)
        self.sock = socket.create_connection((host, int(port)), timeout=5)
        self.framer = scip.ScipFramer()
        self.queue: list[bytes] = []

    def send(self, data: bytes) -> None:
        self.sock.sendall(data)

    def read_messages(self, n: int, timeout: float = 5.0) -> list[bytes]:
        deadline = time.monotonic() + timeout
        while len(self.queue) < n:
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError(f"got {len(self.queue)} of {n} messages")
            self.sock.settimeout(left)
            data = self.sock.recv(65536)
            if not data:
                raise ConnectionError("closed")
            self.queue += self.framer.feed(data)
        out, self.queue = self.queue[:n], self.queue[n:]
        return out

    def ask(self, line: bytes, n: int = 1) -> list[bytes]:
        self.send(line)
        return self.read_messages(n)

    def close(self) -> None:
        self.sock.close()


def processed(emu: ScipEmulator, before: int) -> None:
    """Wait until the emulator has answered (replies written) the command sent when
    ``emu.stats.commands`` read ``before``. (``commands`` counts a line before its reply
    is written, so it is settled for every reply a host has seen; ``commands_answered``
    may still lag.)"""
    assert emu.wait_for(lambda st: st.commands_answered > before), "command not processed"


def next_scan(emu: ScipEmulator, clock: ManualClock) -> None:
    """Move the clock to the next scan message due and wait until it has been written."""
    due = emu.device.next_due()
    assert due is not None, "no scan pending"
    scans, msgs = emu.stats.scans_sent, emu.stats.messages_sent
    clock.advance(max(0.0, due - clock.now()))
    assert emu.wait_for(lambda st: st.scans_sent > scans and st.messages_sent > msgs), \
        "scan not sent"


@pytest.fixture
def manual_tcp():
    clock = ManualClock()
    with ScipEmulator(URG, clock, spec_source, timer_offset_ms=16_000_000) as emu:
        client = TcpClient(emu.serve_tcp())
        yield emu, clock, client
        client.close()


# --- the device state machine directly -------------------------------------------------
def test_device_simple_commands():
    dev = ScipDevice(URG, ManualClock(), spec_source, timer_offset_ms=16_000_000)

    def ask(line: bytes) -> list[bytes]:
        return dev.handle_line(line, 0.0)

    assert ask(b"BM") == [b"BM\n00P\n\n"]
    assert ask(b"BM") == [b"BM\n02R\n\n"]
    assert ask(b"QT") == [b"QT\n00P\n\n"]
    assert ask(b"RS") == [b"RS\n00P\n\n"]
    assert ask(b"XX") == [b"XX\n0Ee\n\n"]
    assert ask(b"SCIP2.0") == [b"SCIP2.0\n0Ee\n\n"]
    assert ask(b"BM;tag.1") == [b"BM;tag.1\n00P\n\n"]
    assert ask(b"") == []


def test_device_tm_mode_rules():
    dev = ScipDevice(URG, ManualClock(), spec_source, timer_offset_ms=16_000_000)

    def status(line: bytes) -> str:
        return scip.parse_reply(dev.handle_line(line, 0.0)[0]).status

    assert status(b"TM1") == "04"
    assert status(b"TM2") == "03"
    assert status(b"TM0") == "00"
    assert status(b"TM0") == "02"
    assert dev.handle_line(b"TM1", 0.0) == [b"TM1\n00P\nm2@0?\n\n"]
    assert status(b"QT") == "0E"  # other commands refused in adjust mode
    assert status(b"GD0044072501") == "0E"
    assert status(b"TM3") == "01"
    assert status(b"TM2") == "00"
    assert status(b"QT") == "00"


def test_device_rs_resets_timer():
    dev = ScipDevice(URG, ManualClock(), spec_source, timer_offset_ms=5000)
    assert dev.timer_ms(10.0) == 15000
    dev.handle_line(b"RS", 10.0)
    assert dev.timer_ms(10.0) == 0 and dev.timer_ms(10.5) == 500
    assert dev.timer_ms(20_000.0) == (20_000_000 - 10_000) % (1 << 24)  # 24-bit wrap


@pytest.mark.parametrize(
    ("line", "status"),
    [(b"GD004407250", "0C"), (b"GD00440725011", "0D"), (b"GDx044072501", "01"),
     (b"GD0044x72501", "02"), (b"GD00440725x1", "03"), (b"GD0044080001", "04"),
     (b"GD0000076901", "04"), (b"GD0725004401", "05"), (b"MD0044072501x00", "06"),
     (b"MD00440725010x0", "07"), (b"GD0044072501;" + b"a" * 17, "0G"),
     (b"BM;a#", "0H"), (b"GD0044072501", "10"), (b"SS123456", "02"), (b"SSabcdef", "01"),
     (b"SS019200", "03"), (b"CR11", "02"), (b"CRxx", "01"), (b"BMX", "0D"), (b"ZZ123", "0E")],
)
def test_device_error_statuses(line, status):
    dev = ScipDevice(URG, ManualClock(), spec_source)
    reply = scip.parse_reply(dev.handle_line(line, 0.0)[0])
    assert reply.echo.encode() == line
    assert reply.status == status


def test_quantise_and_cluster():
    r = np.array([np.nan, 0.010, 0.0204, 1.2344, 5.6, 5.6006, 4.0954, 4.096])
    assert quantise_ranges(r, 20, 5600, 3).tolist() == [0, 6, 20, 1234, 5600, 0, 4095, 4096]
    assert quantise_ranges(r, 20, 5600, 2).tolist() == [0, 6, 20, 1234, 0, 0, 4095, 0]
    assert cluster_ranges(np.array([0, 500, 400, 7, 6, 0, 900]), 3, 20).tolist() == [400, 7, 900]


# --- over TCP, byte for byte -----------------------------------------------------------
def test_tcp_spec_exchanges(manual_tcp):
    emu, clock, c = manual_tcp
    assert c.ask(b"BM\n") == [b"BM\n00P\n\n"]
    assert c.ask(b"BM\n") == [b"BM\n02R\n\n"]
    assert c.ask(b"XX\n") == [b"XX\n0Ee\n\n"]
    assert c.ask(b"SCIP2.0\n") == [b"SCIP2.0\n0Ee\n\n"]
    n = emu.stats.commands
    c.send(b"GD0384038601\n")
    processed(emu, n)
    next_scan(emu, clock)
    assert clock.now() == pytest.approx(0.1)  # scan 0 completes after one revolution
    assert c.read_messages(1) == [b"GD0384038601\n00P\nm2@0?\n0?X0CB1DhI\n\n"]
    assert c.ask(b"QT\r\n") == [b"QT\n00P\n\n"]  # CRLF accepted, echo without it
    assert c.ask(b"RS\n") == [b"RS\n00P\n\n"]
    assert c.ask(b"TM0\n") == [b"TM0\n00P\n\n"]
    assert c.ask(b"TM1\n") == [b"TM1\n00P\n" + scip.with_checksum(scip.encode_value(0, 4))
                               + b"\n\n"]
    assert c.ask(b"TM2\n") == [b"TM2\n00P\n\n"]


def test_tcp_gs_example():
    clock = ManualClock()
    with ScipEmulator(URG, clock, gs_source, timer_offset_ms=16_000_000) as emu:
        c = TcpClient(emu.serve_tcp())
        assert c.ask(b"BM\n") == [b"BM\n00P\n\n"]
        n = emu.stats.commands
        c.send(b"GS0384038601\n")
        processed(emu, n)
        next_scan(emu, clock)
        assert c.read_messages(1) == [b"GS0384038601\n00P\nm2@0?\n?XCBooj\n\n"]
        c.close()


def test_tcp_info_replies(manual_tcp):
    emu, clock, c = manual_tcp
    pp = scip.parse_params(c.ask(b"PP\n")[0])
    assert pp.to_lidar_model() == URG
    vv = scip.parse_version(c.ask(b"VV;v1\n")[0])
    assert vv.protocol == "SCIP 2.0"
    ii = scip.parse_state(c.ask(b"II\n")[0])
    assert not ii.laser_on and ii.status == "Sensor works well."


def test_tcp_md_count_3(manual_tcp):
    emu, clock, c = manual_tcp
    assert c.ask(b"MD0044072501003\n") == [b"MD0044072501003\n00P\n\n"]
    for _ in range(3):
        next_scan(emu, clock)
    assert emu.device.next_due() is None  # the third scan was the last
    msgs = c.read_messages(3)
    echoes = [m.split(b"\n")[0] for m in msgs]
    assert echoes == [b"MD0044072501002", b"MD0044072501001", b"MD0044072501000"]
    frames = [scip.decode_scan(m) for m in msgs]
    assert all(f.status == "99" for f in frames)
    ts = [f.timestamp_ms for f in frames]
    assert np.diff(ts).tolist() == [100, 100]  # one scan per 100 ms at 600 rpm
    k = emu.scan_index(ts[0])
    assert np.array_equal(frames[0].ranges_mm, emu.expected_ranges_mm(k, frames[0].request))
    # the laser went off after the last scan
    assert c.ask(b"GD0044072501\n")[0].split(b"\n")[1] == b"10Q"


def test_tcp_md_interval_and_tag(manual_tcp):
    emu, clock, c = manual_tcp
    assert c.ask(b"MS0100020003202;ab\n") == [b"MS0100020003202;ab\n00P\n\n"]
    for _ in range(2):
        next_scan(emu, clock)
    msgs = c.read_messages(2)
    frames = [scip.decode_scan(m) for m in msgs]
    assert [f.echo for f in frames] == ["MS0100020003201;ab", "MS0100020003200;ab"]
    assert frames[1].timestamp_ms - frames[0].timestamp_ms == 300  # interval 2 -> every 3rd
    assert frames[0].ranges_mm.size == 34


def test_tcp_infinite_md_until_qt():
    clock = ManualClock()
    with ScipEmulator(URG, clock, flat_wall_source(URG, 1.5, sway_m=0.2)) as emu:
        c = TcpClient(emu.serve_tcp())
        assert c.ask(b"MD0044072501000\n") == [b"MD0044072501000\n00P\n\n"]
        for _ in range(10):
            next_scan(emu, clock)
        msgs = c.read_messages(10)
        frames = [scip.decode_scan(m) for m in msgs]
        assert {f.echo for f in frames} == {"MD0044072501000"}
        ts = np.array([f.timestamp_ms for f in frames])
        assert (np.diff(ts) == 100).all()
        for f in frames:
            k = emu.scan_index(f.timestamp_ms)
            assert np.array_equal(f.ranges_mm, emu.expected_ranges_mm(k, f.request))
        assert c.ask(b"QT\n") == [b"QT\n00P\n\n"]  # the clock stood: no scan in between
        assert emu.device.next_due() is None  # the stream is stopped
        scans = emu.stats.scans_sent
        clock.advance(1.0)  # ten revolutions later nothing more was sent
        assert c.ask(b"BM\n") == [b"BM\n00P\n\n"]  # laser was off: the stream stopped
        assert emu.stats.scans_sent == scans
        c.close()


def test_tcp_timestamps_rate_1():
    """At rate 1 scans come every 100 ms of wall time with +100 ms timestamps: four
    scans cannot arrive in less than 0.3 s (the emulator paces against the clock). No
    upper bound: how late a loaded machine delivers them is not the emulator's to keep."""
    with ScipEmulator(URG, SimClock(rate=1.0)) as emu:
        c = TcpClient(emu.serve_tcp())
        c.ask(b"MD0044072501004\n")
        t0 = time.monotonic()
        frames = [scip.decode_scan(m) for m in c.read_messages(4)]
        dt = time.monotonic() - t0
        assert np.diff([f.timestamp_ms for f in frames]).tolist() == [100, 100, 100]
        assert dt >= 0.3
        c.close()


def test_tcp_one_host_at_a_time():
    """One host at a time (issue 15: a second connection silently took over the
    session): the second waits unanswered while the first is alive and keeps its stream,
    a third is closed at once; when the first hangs up the waiting one is served, by the
    same device, and its queued command answered."""
    clock = ManualClock()
    with ScipEmulator(URG, clock) as emu:
        url = emu.serve_tcp()
        c1 = TcpClient(url)
        c1.ask(b"MD0044072501000\n")
        next_scan(emu, clock)
        c1.read_messages(1)
        c2 = TcpClient(url)
        c2.send(b"VV\n")
        assert emu.wait_for(lambda st: st.queued_connections == 1)
        c3 = TcpClient(url)
        with pytest.raises(ConnectionError):  # closed by the emulator, nothing answered
            c3.ask(b"QT\n")
        c3.close()
        assert emu.stats.refused_connections == 1 and emu.stats.connections == 1
        next_scan(emu, clock)  # the first host's stream goes on
        assert scip.decode_scan(c1.read_messages(1)[0]).echo == "MD0044072501000"
        assert emu.stats.commands == 1  # c2's VV not read: it waits
        c1.close()
        vv = scip.parse_version(c2.read_messages(1)[0])  # served once c1 has gone
        assert vv.protocol == "SCIP 2.0"
        # the same device: the stream ended with c1, the laser is still on
        assert c2.ask(b"BM\n") == [b"BM\n02R\n\n"]
        assert emu.device.stream is None
        assert emu.stats.connections == 2 and emu.stats.refused_connections == 1
        c2.close()


def test_tcp_long_line_is_bounded_and_answered():
    """100 kB without a line end (the buffer grew without bound): dropped once it passes
    max_line_bytes and answered 0D at once, before the line ends; the session goes on."""
    with ScipEmulator(URG, ManualClock(), max_line_bytes=64) as emu:
        c = TcpClient(emu.serve_tcp())
        c.send(b"BM" + b"9" * 100_000)
        reply = scip.parse_reply(c.read_messages(1)[0])
        assert reply.status == "0D" and reply.echo == "BM" + "9" * 62
        c.send(b"9" * 1000 + b"\n")  # the rest of that line: dropped silently
        assert c.ask(b"BM\n") == [b"BM\n00P\n\n"]
        assert emu.stats.long_lines == 1
        c.send(b"\xff" * 70 + b"\n")  # a long line with a line end: the same, echo "?" * 64
        assert c.ask(b"QT\n") == [b"QT\n00P\n\n"]
        assert emu.stats.long_lines == 2
        assert c.framer.rejected == 1  # that echo is no command: the host's framer drops it
        c.close()
    with pytest.raises(ParameterError, match="max_line_bytes"):
        ScipEmulator(URG, ManualClock(), max_line_bytes=10)
    with pytest.raises(ParameterError, match="emulator.port"):
        ScipEmulator(URG, ManualClock(), port=70000)


def test_scip1_mode_handshake():
    with ScipEmulator(URG, ManualClock(), scip1=True) as emu:
        c = TcpClient(emu.serve_tcp())
        assert c.ask(b"QT\n") == [b"QT\nE\n\n"]
        assert c.ask(b"SCIP2.0\n") == [b"SCIP2.0\n0\n\n"]
        assert c.ask(b"QT\n") == [b"QT\n00P\n\n"]
        assert c.ask(b"SCIP2.0\n") == [b"SCIP2.0\n0Ee\n\n"]
        c.close()


# --- through the pty with pyserial -----------------------------------------------------
def test_pty_spec_exchanges():
    clock = ManualClock()
    with ScipEmulator(URG, clock, spec_source, timer_offset_ms=16_000_000) as emu:
        path = emu.serve_pty()
        assert path.startswith("/dev/")
        with serial.Serial(path, 115200, timeout=2) as ser:
            ser.write(b"BM\n")
            assert ser.read_until(b"\n\n") == b"BM\n00P\n\n"
            n = emu.stats.commands
            ser.write(b"GD0384038601\n")
            processed(emu, n)
            next_scan(emu, clock)
            assert ser.read_until(b"\n\n") == b"GD0384038601\n00P\nm2@0?\n0?X0CB1DhI\n\n"
            ser.write(b"XX\n")
            assert ser.read_until(b"\n\n") == b"XX\n0Ee\n\n"
            ser.write(b"TM0\nTM1\n")
            assert ser.read_until(b"\n\n") == b"TM0\n00P\n\n"
            tm1 = scip.with_checksum(scip.encode_value(16_000_100, 4))  # clock moved 0.1 s
            assert ser.read_until(b"\n\n") == b"TM1\n00P\n" + tm1 + b"\n\n"
            ser.write(b"TM2\nMD0044072501003\n")
            assert ser.read_until(b"\n\n") == b"TM2\n00P\n\n"
            assert ser.read_until(b"\n\n") == b"MD0044072501003\n00P\n\n"
            for _ in range(3):
                next_scan(emu, clock)
            framer = scip.ScipFramer()
            got: list[bytes] = []
            deadline = time.monotonic() + 3
            while len(got) < 3 and time.monotonic() < deadline:
                got += framer.feed(ser.read(max(1, ser.in_waiting)))
            assert [m.split(b"\n")[0] for m in got] == [
                b"MD0044072501002", b"MD0044072501001", b"MD0044072501000"]


def test_pty_stream_through_link(tmp_path):
    """An endless MD through the pty's symlink: 20 scans, one per revolution, every
    timestamp +100 ms (was at clock rate 20 against the wall clock, and failed under
    load when the emulator fell behind and skipped scans)."""
    link = tmp_path / "ttyURG"
    clock = ManualClock()
    with ScipEmulator(URG, clock) as emu:
        assert emu.serve_pty(link=link) == str(link)
        with serial.serial_for_url(str(link), timeout=5) as ser:
            n = emu.stats.commands
            ser.write(b"MD0044072501000\n")
            processed(emu, n)
            framer = scip.ScipFramer()
            got: list[bytes] = []
            while len(got) < 21:  # one message at a time: a pty holds only a few kB
                if emu.stats.messages_sent <= len(got):
                    next_scan(emu, clock)
                data = ser.read(max(1, ser.in_waiting))
                assert data, f"got {len(got)} of 21 messages"
                got += framer.feed(data)
            assert got[0] == b"MD0044072501000\n00P\n\n"
            ts = [scip.decode_scan(m).timestamp_ms for m in got[1:21]]
            assert (np.diff(ts) == 100).all()
            assert emu.stats.scans_skipped == 0
            ser.write(b"QT\n")
    assert not link.exists()


# --- faults ----------------------------------------------------------------------------
def test_fault_injector_deterministic():
    msg = bytes(range(48, 112)) * 40
    cfg = FaultConfig(seed=3, drop_byte_prob=0.01, corrupt_byte_prob=0.01)
    a = [FaultInjector(cfg).apply(msg, True) for _ in range(2)]
    assert a[0] == a[1]
    assert a[0].dropped > 0 and a[0].corrupted > 0
    assert len(a[0].data) == len(msg) - a[0].dropped
    inj = FaultInjector(FaultConfig(disconnect_at=(1,), disconnect_s=2.0, stall_at=(2,),
                                    stall_s=1.0))
    acts = [inj.apply(msg) for _ in range(3)]
    assert acts[0].data == msg and acts[1].disconnect_s == 2.0 and acts[2].wait_s == 1.0


def test_faults_garble_but_framer_never_yields_corrupt():
    cfg = FaultConfig(seed=5, drop_byte_prob=2e-4, corrupt_byte_prob=2e-4, scans_only=True)
    with ScipEmulator(URG, SimClock(rate=40.0), faults=cfg) as emu:
        c = TcpClient(emu.serve_tcp())
        c.ask(b"MD0044072501000\n")
        msgs = c.read_messages(60, timeout=10)
        for m in msgs:
            f = scip.decode_scan(m)  # every yielded message verifies...
            k = emu.scan_index(f.timestamp_ms)
            assert np.array_equal(f.ranges_mm, emu.expected_ranges_mm(k, f.request))
        assert emu.stats.bytes_dropped + emu.stats.bytes_corrupted > 0
        assert c.framer.rejected > 0
        c.close()


def test_tcp_disconnect_and_return():
    """The link drops at message 3 for 4 s (simulated): connections are refused until the
    clock has moved 4 s, then the device answers, rebooted (laser off)."""
    clock = ManualClock()
    cfg = FaultConfig(disconnect_at=(3,), disconnect_s=4.0)
    with ScipEmulator(URG, clock, faults=cfg) as emu:
        url = emu.serve_tcp()
        c = TcpClient(url)
        c.ask(b"MD0044072501000\n")  # message 0
        next_scan(emu, clock)
        next_scan(emu, clock)
        c.read_messages(2)  # messages 1, 2; message 3 is the disconnect
        clock.advance(emu.device.next_due() - clock.now())
        with pytest.raises(ConnectionError):
            c.read_messages(1)
        c.close()
        assert emu.stats.disconnects == 1
        t_down = clock.now()
        c = TcpClient(url)  # refused while away: the clock has not moved
        with pytest.raises(ConnectionError):
            c.ask(b"BM\n")
        c.close()
        assert not emu.stats.up_times
        clock.advance(4.0)
        c = TcpClient(url)
        assert c.ask(b"BM\n") == [b"BM\n00P\n\n"]  # rebooted: laser was off
        assert clock.now() - t_down == pytest.approx(4.0)
        assert len(emu.stats.up_times) == 1
        c.close()


# --- the reference's own examples, read from the file, byte for byte --------------------
SCIP_MD = Path(__file__).resolve().parent / "data" / "scip2.md"  # see tests/data/README.md
_REQUEST_RE = re.compile(rb"(SCIP2\.0|[A-Z]{2}[0-9A-Za-z]*)(;[A-Za-z0-9 ._+@]*)?\n")


def _reference_text() -> str:
    assert SCIP_MD.exists(), f"{SCIP_MD} (the SCIP 2.0 reference, tests/data) is missing"
    return SCIP_MD.read_text()


def _vectors() -> dict[int, str]:
    """Test vectors of scip2.md §1.10 by number (their text, possibly several lines)."""
    text = _reference_text()
    sec = text[text.index("### 1.10 Test vectors"):]
    found = {int(m[1]): m[2] for m in
             re.finditer(r"^(\d+)\. (.*?)(?=^\d+\. |^\S|\Z)", sec, re.M | re.S)}
    assert set(range(6, 17)) <= set(found), sorted(found)
    return found


def _quoted(vector_text: str) -> list[bytes]:
    """The `...` (and markdown ``...``) spans of a vector, \\n escapes turned into LF."""
    spans = [a or b for a, b in re.findall(r"`` (.+?) ``|`([^`]+)`", vector_text)]
    return [s.replace("\\n", "\n").encode() for s in spans]


def _values(vector_text: str) -> tuple[list[int], int | None]:
    m = re.search(r"with (?:ranges )?(\d+), (\d+), (\d+)(?: and timestamp ([\d,]+))?",
                  vector_text)
    assert m, vector_text
    return [int(m[i]) for i in (1, 2, 3)], int(m[4].replace(",", "")) if m[4] else None


def _wants_scans(line: bytes) -> bool:
    """A distance request, or nothing sent (waiting for the scans of a stream)."""
    return line[:2] in (b"GD", b"GS", b"MD", b"MS") or not line


class _DeviceWire:
    """Host end of a bare ScipDevice on a ManualClock (no transport at all)."""

    def __init__(self, source, timer_offset_ms):
        self.clock = ManualClock()
        self.dev = ScipDevice(URG, self.clock, source, timer_offset_ms=timer_offset_ms)

    def exchange(self, line: bytes, n: int = 1) -> list[bytes]:
        out = self.dev.handle_line(line.rstrip(b"\n"), self.clock.now())
        while len(out) < n:  # scan data: due when the scan completes
            self.clock.advance(URG.scan_period_s)
            out += self.dev.poll(self.clock.now())
        return out

    def close(self):
        pass


class _TcpWire:
    """The same over the emulator's TCP transport (bytes as a host receives them)."""

    def __init__(self, source, timer_offset_ms):
        self.clock = ManualClock()
        self.emu = ScipEmulator(URG, self.clock, source, timer_offset_ms=timer_offset_ms)
        self.client = TcpClient(self.emu.serve_tcp())

    def exchange(self, line: bytes, n: int = 1) -> list[bytes]:
        emu = self.emu
        cmds = emu.stats.commands
        self.client.send(line)
        if line.strip():
            processed(emu, cmds)
        got: list[bytes] = []
        while len(got) < n:
            if emu.stats.messages_sent <= self.client.framer.messages:
                assert _wants_scans(line), f"no reply to {line!r}"
                next_scan(emu, self.clock)  # the clock only moves for scans
            got += self.client.read_messages(1)
        return got

    def close(self):
        self.client.close()
        self.emu.stop()


class _PtyWire:
    """The same through the pseudo-terminal, read with pyserial like /dev/ttyACM0."""

    def __init__(self, source, timer_offset_ms):
        self.clock = ManualClock()
        self.emu = ScipEmulator(URG, self.clock, source, timer_offset_ms=timer_offset_ms)
        self.ser = serial.Serial(self.emu.serve_pty(), 115200, timeout=0.1)
        self.framer = scip.ScipFramer()
        self.queue: list[bytes] = []

    def exchange(self, line: bytes, n: int = 1) -> list[bytes]:
        emu = self.emu
        cmds = emu.stats.commands
        self.ser.write(line)
        if line.strip():
            processed(emu, cmds)
        deadline = time.monotonic() + 5.0
        while len(self.queue) < n:
            # one message at a time: a pty holds only a few kB
            if emu.stats.messages_sent <= self.framer.messages:
                assert _wants_scans(line), f"no reply to {line!r}"
                next_scan(emu, self.clock)  # the clock only moves for scans
            data = self.ser.read(max(1, self.ser.in_waiting))  # written: it is there
            self.queue += self.framer.feed(data)
            assert time.monotonic() < deadline, f"reply to {line!r} not read"
        out, self.queue = self.queue[:n], self.queue[n:]
        return out

    def close(self):
        self.ser.close()
        self.emu.stop()


def _source_with(request: bytes, values_mm: list[int]):
    req = scip.DistanceRequest.parse(request)

    def source(k: int, t: float) -> np.ndarray:
        r = np.full(URG.n_steps, 2.0)
        r[req.start - URG.step_min: req.end - URG.step_min + 1] = np.array(values_mm) / 1000
        return r

    return source


def _replay(wire, tokens: list[bytes]) -> int:
    """Send each quoted request; compare each quoted reply with what came back, byte for
    byte. A reply quoted without a new request ("already on -> ...") answers the previous
    request sent again. Templates (``<t4><sum>``) are skipped. Returns replies checked."""
    last, pending, checked = None, False, 0
    for tok in tokens:
        if b"<" in tok:
            continue
        if tok.endswith(b"\n\n"):
            if not pending:
                got = wire.exchange(last)
            assert got == [tok], (last, got, tok)
            pending, checked = False, checked + 1
        elif _REQUEST_RE.fullmatch(tok):
            got, last, pending = wire.exchange(tok), tok, True
    return checked


@pytest.fixture(params=["device", "tcp", "pty"])
def wire_kind(request):
    return {"device": _DeviceWire, "tcp": _TcpWire, "pty": _PtyWire}[request.param]


def test_reference_exchanges_byte_for_byte(wire_kind):
    """Vectors 10-16 of scip2.md §1.10 (requests, replies and the range values all read
    from the file) come back from the emulator byte for byte."""
    v = _vectors()
    gd_values, ts = _values(v[12])
    gs_values, ts_gs = _values(v[13])
    checked = 0
    # 10, 15, 16: simple commands in one session
    w = wire_kind(None, 0)
    try:
        for n in (10, 15, 16):
            checked += _replay(w, _quoted(v[n]))
    finally:
        w.close()
    # 11: TM1 in adjust mode, the example's timer value 16,000,000 (m2@0)
    w = wire_kind(None, 16_000_000)
    try:
        assert w.exchange(b"TM0\n") == [b"TM0\n00P\n\n"]
        checked += _replay(w, _quoted(v[11]))
    finally:
        w.close()
    # 12, 13: GD / GS with the stated ranges at the requested steps and the timestamp
    for n, values, stamp in ((12, gd_values, ts), (13, gs_values, ts_gs or ts)):
        toks = _quoted(v[n])
        w = wire_kind(_source_with(toks[0], values), stamp)
        try:
            assert w.exchange(b"BM\n") == [b"BM\n00P\n\n"]  # GD/GS need the laser on
            checked += _replay(w, toks)
        finally:
            w.close()
    assert checked == 9  # 4 + 1 + 1 + 1 + 1 + 1 replies; a change in the file shows here


def test_reference_md_remaining_count_echoes(wire_kind):
    """Vector 14: the MD acknowledgement byte for byte, then scan messages whose echoes
    count the remaining scans down, each with status line 99b; an endless request keeps
    its echo."""
    toks = _quoted(_vectors()[14])
    request, ack = toks[0], toks[1]
    first = toks[2].decode()
    echoes = [first] + [first[:-3] + t.decode().lstrip("…") for t in toks[3:5]]
    status, endless = toks[5], toks[6]
    assert status == b"99b" and len(echoes) == 3
    w = wire_kind(None, 0)
    try:
        assert w.exchange(request) == [ack]
        assert ack == request.rstrip(b"\n") + b"\n00P\n\n"
        msgs = w.exchange(b"", 3)  # nothing sent: the three scans as they become due
        assert [m.split(b"\n")[0].decode() for m in msgs] == echoes
        assert all(m.split(b"\n")[1] == status for m in msgs)
        assert [scip.decode_scan(m).ranges_mm.size for m in msgs] == [682] * 3
        msgs = w.exchange(endless + b"\n", 4)[1:]  # the ack, then scans
        assert [m.split(b"\n")[0] for m in msgs] == [endless] * 3
    finally:
        w.close()


def test_reference_info_replies_byte_for_byte(manual_tcp):
    """Vectors 6, 7 and 9: the PP block of §1.5 exactly; VV with the WIKI's version
    strings configured; II at the WIKI's timer value (0x081615 ms) - each line with the
    checksum the reference prints."""
    text = _reference_text()
    block = text[text.index("```\nPP\n00P") + 4:]
    block = block[: block.index("(empty line)")]
    pp_ref = block.encode() + b"\n"
    emu, clock, c = manual_tcp
    assert c.ask(b"PP\n") == [pp_ref]
    v = _vectors()
    vv_lines = _quoted(v[7])
    assert len(vv_lines) == 5
    info = dict(ln[:-2].decode().split(":", 1) for ln in vv_lines)
    version = scip.VersionInfo(info["VEND"], info["PROD"], info["FIRM"], info["PROT"],
                               info["SERI"])
    dev = ScipDevice(URG, ManualClock(), version=version)
    assert dev.handle_line(b"VV", 0.0) == [b"VV\n00P\n" + b"\n".join(vv_lines) + b"\n\n"]
    ii_lines = _quoted(v[9])
    assert [ln[:5] for ln in ii_lines] == [b"LASR:", b"SCSP:", b"MESM:", b"SBPS:", b"TIME:",
                                          b"STAT:"]
    t_ms = int(ii_lines[4][5:-2].decode(), 16)
    dev = ScipDevice(URG, ManualClock(), timer_offset_ms=t_ms)
    modl = pp_ref.split(b"\n")[2]
    assert dev.handle_line(b"II", 0.0) == [b"II\n00P\n" + modl + b"\n" + b"\n".join(ii_lines)
                                           + b"\n\n"]
    # vector 8: a real UG01's VV lines, as this codec's info lines
    for line in _quoted(v[8]):
        key, value = line[:-2].decode().split(":", 1)
        assert scip.info_line(key, value) == line


def test_ss_and_cr_accepted():
    dev = ScipDevice(URG, ManualClock())

    def status(line: bytes) -> str:
        return scip.parse_reply(dev.handle_line(line, 0.0)[0]).status

    assert status(b"SS115200") == "00" and status(b"SS115200") == "03"
    assert scip.parse_state(dev.handle_line(b"II", 0.0)[0]).bitrate == "115200[bps]"
    assert status(b"CR05") == "00" and status(b"CR99") == "00"
    assert status(b"RS") == "00"  # bit rate back to the default
    assert scip.parse_state(dev.handle_line(b"II", 0.0)[0]).bitrate.startswith("19200[bps]")


def test_delay_fault_holds_a_message_back():
    inj = FaultInjector(FaultConfig(delay_prob=1.0, delay_s=0.25))
    act = inj.apply(b"BM\n00P\n\n")
    assert (act.wait_s, act.stalled, act.data) == (0.25, False, b"BM\n00P\n\n")
    with ScipEmulator(URG, SimClock(rate=1.0), faults=FaultConfig(delay_prob=1.0,
                                                                  delay_s=0.25)) as emu:
        c = TcpClient(emu.serve_tcp())
        t0 = time.monotonic()
        assert c.ask(b"BM\n") == [b"BM\n00P\n\n"]  # intact, only late
        assert time.monotonic() - t0 >= 0.25
        assert emu.stats.stalls == 0
        c.close()


# --- issue 15: the spec's step table, HS and DB, and an independent client ---------------
def test_step_table_0_to_768():
    """The SCIP 2.0 specification's step table lists steps 0..768 for the URG-04LX
    (sim/scip_emulator.STEP_TABLE_MAX says which source): requests inside it are
    accepted and steps outside AMIN..AMAX (44..725) carry error code 19 ("non-measurable
    step", SPEC Table 3); beyond 768 the end step is out of range (04)."""
    dev = ScipDevice(URG, ManualClock(), spec_source)
    clock = dev.clock
    assert dev.handle_line(b"BM", 0.0) == [b"BM\n00P\n\n"]
    assert dev.handle_line(b"GD0000076800", 0.0) == []  # accepted: due after one scan
    clock.advance(URG.scan_period_s)
    f = scip.decode_scan(dev.poll(clock.now())[0])
    assert f.ranges_mm.size == 769 and f.steps[[0, -1]].tolist() == [0, 768]
    inside = (f.steps >= 44) & (f.steps <= 725)
    assert (f.ranges_mm[~inside] == 19).all() and (~inside).sum() == 44 + 43
    assert np.array_equal(f.ranges_mm[inside],
                          quantise_ranges(spec_source(0, 0.0), 20, 5600, 3))
    # clusters straddling AMIN: the minimum valid value; all errors: the first code
    dev.handle_line(b"GD0040004905", clock.now())
    clock.advance(URG.scan_period_s)
    g = scip.decode_scan(dev.poll(clock.now())[0])
    assert g.ranges_mm.tolist() == [19, 2000]  # 40-44: code 19 x4 and step 44's no-return
    dev.handle_line(b"GD0041005005", clock.now())
    clock.advance(URG.scan_period_s)
    g = scip.decode_scan(dev.poll(clock.now())[0])
    assert g.ranges_mm.tolist() == [2000, 2000]  # 41-45: step 45's 2 m
    for line, status in ((b"GD0000076900", "04"), (b"MD0769076900000", "04")):
        assert scip.parse_reply(dev.handle_line(line, clock.now())[0]).status == status
    # the UTM-30LX table ends at its AMAX
    utm = ScipDevice(lidar_model("UTM-30LX"), ManualClock())
    assert utm.max_step == 1080
    assert scip.parse_reply(utm.handle_line(b"MD0000108100000", 0.0)[0]).status == "04"


def test_hs_and_db_as_the_reference_describes():
    """HS (high sensitivity 0/1, statuses 01-03) and DB (simulate malfunction 01-05, 10
    ends it) on the URG-04LX firmware the emulator reports (3.4.03 >= 3.2.00 / 3.3.00);
    they answered 0E before."""
    dev = ScipDevice(URG, ManualClock())

    def status(line: bytes) -> str:
        return scip.parse_reply(dev.handle_line(line, 0.0)[0]).status

    assert status(b"HS1") == "00" and dev.high_sensitivity
    assert status(b"HS1") == "02"  # already in that mode
    assert status(b"HS0") == "00" and not dev.high_sensitivity
    assert status(b"HS2") == "01" and status(b"HS") == "0C" and status(b"HS11") == "0D"
    assert status(b"DB03") == "00" and dev.malfunction == 3
    assert "03" in scip.parse_state(dev.handle_line(b"II", 0.0)[0]).status
    assert status(b"DB10") == "00" and dev.malfunction is None
    assert status(b"DB06") == "01" and status(b"DBxx") == "01" and status(b"DB1") == "0C"
    assert status(b"HS1;tag") == "00"  # the tag is echoed as for any command
    dev.handle_line(b"RS", 0.0)
    assert not dev.high_sensitivity  # RS: back to normal sensitivity
    utm = ScipDevice(lidar_model("UTM-30LX"), ManualClock())
    assert scip.parse_reply(utm.handle_line(b"HS1", 0.0)[0]).status == "03"


def test_hokuyolx_client_over_tcp():
    """The independent hokuyolx client (written for Hokuyo's Ethernet sensors) talks to
    the emulator over TCP: PP/VV/II, BM, TM0/1/2, GD over the whole 0..768 step table,
    a 3-scan MD with the remaining count, HS and DB through its request layer (which
    checks echo and status sums) - each result against the emulator's ground truth.

    hokuyolx reads until a chunk happens to end in LF LF, so two messages in the socket
    at once garble it: a helper moves the manual clock to each scan only once hokuyolx
    has asked for it (its request answered) and read everything sent before (nothing
    unread in its socket)."""
    import fcntl
    import struct
    import termios
    import threading

    hokuyolx = pytest.importorskip("hokuyolx")  # a test dependency (pyproject [test])
    clock = ManualClock()

    def unread(sock: socket.socket) -> int:
        return struct.unpack("i", fcntl.ioctl(sock.fileno(), termios.FIONREAD, b"\0" * 4))[0]

    def scan_when(emu: ScipEmulator, ready) -> threading.Thread:
        def run():
            if not emu.wait_for(ready):
                return
            deadline = time.monotonic() + 5
            while unread(lx._sock) and time.monotonic() < deadline:
                time.sleep(0.001)  # polling a condition: hokuyolx reading its reply
            next_scan(emu, clock)
        t = threading.Thread(target=run, daemon=True)
        t.start()
        return t

    with ScipEmulator(URG, clock, flat_wall_source(URG, 1.5, sway_m=0.2)) as emu:
        host, port = emu.serve_tcp().removeprefix("socket://").rsplit(":", 1)
        lx = hokuyolx.HokuyoLX(addr=(host, int(port)), tsync=False, info=True,
                               activate=False, convert_time=False, timeout=5)
        try:
            assert (lx.amin, lx.amax, lx.aforw, lx.ares, lx.dmin, lx.dmax) == (
                44, 725, 384, 1024, 20, 5600)
            assert lx.version()["PROT"] == "SCIP 2.0"
            assert lx.sensor_state()["LASR"] == "OFF"
            assert lx.activate() == (0, hokuyolx.statuses.activation_statuses["00"])
            assert lx.tsync_enter()[0] == "00"
            assert lx.tsync_get() == emu.device.timer_ms(clock.now())
            assert lx.tsync_exit()[0] == "00"
            lx.activate()  # TM0 switched the laser off
            n = emu.stats.commands
            t = scan_when(emu, lambda st: st.commands_answered > n)  # GD answered
            ts, scan = lx.get_dist(0, 768)
            t.join(5)
            req = scip.DistanceRequest("GD", 0, 768)
            assert np.array_equal(scan, emu.expected_ranges_mm(emu.scan_index(ts), req))
            assert scan[:44].tolist() == [19] * 44 and scan[726:].tolist() == [19] * 43
            n = emu.stats.commands
            t = scan_when(emu, lambda st: st.commands_answered > n)  # MD acknowledged
            got = []
            for item in lx.iter_dist(scans=3):
                t.join(5)
                got.append(item)
                if len(got) < 3:
                    t = scan_when(emu, lambda st: True)  # the scan before was taken
            assert [p for _, _, p in got] == [2, 1, 0]
            req = scip.DistanceRequest("MD", 44, 725, 0, 0, 3)
            for scan, ts, _ in got:
                assert np.array_equal(scan, emu.expected_ranges_mm(emu.scan_index(ts), req))
            assert np.diff([ts for _, ts, _ in got]).tolist() == [100, 100]
            assert lx._send_req("HS", "1")[0] == "00"
            assert lx._send_req("HS", "1")[0] == "02"
            assert lx._send_req("DB", "02")[0] == "00"
            assert lx._send_req("DB", "10")[0] == "00"
        finally:
            lx.close()
