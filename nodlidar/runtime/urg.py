"""Driver for Hokuyo SCIP 2.0 scanners (URG-04LX and relatives) over serial, USB or TCP.

``UrgDriver(port)`` takes a device path (``/dev/ttyACM0``, an emulator's pty), a pyserial
URL (``socket://host:port``) or an already constructed ``serial.SerialBase``. Nothing is
opened before :meth:`UrgDriver.open` (or ``with``).

Connecting follows the sequence that public drivers use for this family (urg_library's
``connect_urg_device``): terminate any partial command line, ``QT`` to stop a running
stream, ``SCIP2.0`` if the device answers in SCIP 1.1, ``TM2`` if it is in time-adjust
mode (``0E`` to everything else), then ``PP`` for the geometry.

Streams (``MD``/``MS``) are read through :class:`nodlidar.scip.ScipFramer`: only messages
whose every checksum verifies and whose echo matches the request are delivered; lost or
garbled scans are counted in :attr:`UrgDriver.stats`. When nothing arrives for ``timeout``
seconds the link is considered lost: the driver reopens the port, repeats the handshake
and restarts the stream, for up to ``reconnect_timeout_s``.

Units: ranges in metres (``Scan.ranges_m``; raw millimetres/codes in ``Scan.ranges_mm``),
times in seconds of ``time.monotonic()`` on the host, device timestamps in milliseconds.
"""

from __future__ import annotations

import collections
import select
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import numpy as np
import serial

from nodlidar import scip
from nodlidar.errors import DeviceError, ParameterError, ProtocolError
from nodlidar.lidar import LidarModel

__all__ = ["Scan", "DriverStats", "ClockSync", "DeviceInfo", "UrgDriver"]


@dataclass(frozen=True, eq=False)
class Scan:
    """One delivered scan.

    Attributes
    ----------
    seq : int
        Running number of scans delivered by this driver.
    index : int
        Device scan number relative to the first scan of this stream (one per
        revolution); gaps mean scans were skipped (``interval``) or lost.
    request : nodlidar.scip.DistanceRequest
        The echoed request (``count`` = remaining scans for MD/MS).
    steps : numpy.ndarray, shape (n,), int
        First step of each value.
    ranges_m : numpy.ndarray, shape (n,), float64
        Ranges [m]; NaN where the device sent an error code.
    ranges_mm : numpy.ndarray, shape (n,), int32
        Raw values [mm] including the error codes (< DMIN).
    timestamp_ms : int
        Device timer at step 0 [ms], unwrapped beyond 24 bits.
    host_time_s : float
        ``time.monotonic()`` when the message was complete.
    stamp_s : float
        Host-clock estimate of step 0 [s]: from :meth:`UrgDriver.sync_clock` if done,
        else ``host_time_s`` minus one scan period.
    dmin_mm : int
        Values below this are error codes.
    raw : bytes
        The verified SCIP message exactly as received (for recording).
    implausible : numpy.ndarray, shape (n,), bool, or None
        Values the driver's plausibility filter flagged (their ``ranges_m`` are NaN,
        ``ranges_mm`` keeps what the device sent); None without a filter.
    """

    seq: int
    index: int
    request: scip.DistanceRequest
    steps: np.ndarray
    ranges_m: np.ndarray
    ranges_mm: np.ndarray
    timestamp_ms: int
    host_time_s: float
    stamp_s: float
    dmin_mm: int = 20
    raw: bytes = field(default=b"", repr=False)
    implausible: np.ndarray | None = field(default=None, repr=False)

    @property
    def device_time_s(self) -> float:
        """Device timestamp [s] (unwrapped)."""
        return self.timestamp_ms / 1000.0

    @property
    def error_mask(self) -> np.ndarray:
        """``(n,) bool``: the value is an error code."""
        return self.ranges_mm < self.dmin_mm

    @property
    def error_codes(self) -> np.ndarray:
        """``(n,) int``: the error code, or -1 for a valid range."""
        return np.where(self.error_mask, self.ranges_mm, -1)

    @property
    def remaining(self) -> int | None:
        """MD/MS: scans the device still sends (0 for infinite streams)."""
        return self.request.count


@dataclass
class DriverStats:
    """Counters (mutable; read them while streaming).

    ``dropped_scans`` counts the revolutions missing between consecutive delivered scans of
    a stream (timestamp gaps, across reconnects too). Scans the device sent after the last
    delivered one (still buffered when the stream stops) and scans lost before the first
    one are not drops: they are outside what the consumer saw.
    """

    scans: int = 0
    dropped_scans: int = 0
    rejected_messages: int = 0
    discarded_bytes: int = 0
    bad_scans: int = 0
    stale_messages: int = 0
    timeouts: int = 0
    reconnects: int = 0
    handshakes: int = 0
    bad_info_replies: int = 0
    #: stream messages with a status other than 99 (scan) or 00 (acknowledgement), dropped
    bad_statuses: int = 0
    #: MD/MS acknowledgements lost (the first scan message stood for them)
    lost_acks: int = 0
    #: range values flagged by the plausibility filter (set to NaN in ``ranges_m``)
    implausible_values: int = 0


@dataclass(frozen=True)
class ClockSync:
    """Device-to-host clock offset from ``TM1`` round trips (min-RTT sample).

    ``host_s = device_ms / 1000 + offset_s``.
    """

    offset_s: float
    rtt_s: float
    samples: int

    def host_time(self, device_ms: float) -> float:
        """Host ``time.monotonic()`` [s] of an unwrapped device time [ms]."""
        return device_ms / 1000.0 + self.offset_s


@dataclass(frozen=True)
class DeviceInfo:
    """``VV``, ``PP`` and ``II`` replies together."""

    version: scip.VersionInfo
    params: scip.SensorParams
    state: scip.SensorState


class _LinkLost(Exception):
    pass


class _Unwrapper:
    """Extends the 24-bit device timer; a backwards jump is taken as a device reset.

    Each reading may come with ``host_s``, the host time [s, in the device timer's time
    scale] it was received. Across a reset (RS, a power cycle: the timer restarts at 0)
    the device time cannot tell how long the device was away; the host times can, so the
    unwrapped timeline goes on by the host time elapsed (1 ms if unknown). Its error is
    the receive jitter; :meth:`UrgDriver.sync_clock` (repeated after a reconnect) takes
    it out of the host stamps.
    """

    def __init__(self) -> None:
        self.last_raw: int | None = None
        self.last: int = 0
        self.last_host_s: float | None = None
        self.base = 0
        self.resets = 0

    def __call__(self, raw: int, host_s: float | None = None) -> int:
        mod = scip.TIMESTAMP_MODULUS_MS
        if self.last_raw is None:
            unwrapped = raw
        else:
            d = (raw - self.last_raw) % mod
            if d >= mod // 2:  # went backwards: the timer was reset (RS, reboot)
                self.resets += 1
                step = 1
                if host_s is not None and self.last_host_s is not None:
                    step = max(1, int(round(1000.0 * (host_s - self.last_host_s))))
                unwrapped = self.last + step
            else:
                unwrapped = self.last + d
        self.base = unwrapped - raw
        self.last_raw, self.last = raw, unwrapped
        if host_s is not None:
            self.last_host_s = host_s
        return unwrapped


class UrgDriver:
    """SCIP 2.0 scanner driver.

    Parameters
    ----------
    port : str or serial.SerialBase
        Device path, pyserial URL (``socket://127.0.0.1:10940``) or a port object.
    baudrate : int
        Serial bit rate [bit/s] (ignored by USB CDC-ACM and TCP).
    timeout : float
        Seconds to wait for a reply, or between scans of a stream, before treating the
        device as gone.
    reconnect : bool
        Reopen and resume on link loss (streams and single scans).
    reconnect_timeout_s : float
        Give up (raise :class:`~nodlidar.errors.DeviceError`) if the device does not come
        back within this many seconds.
    plausibility : nodlidar.scip.RangePlausibility, optional
        Flag ranges the 6-bit checksums let through but the sensor cannot have measured
        (values > DMAX, isolated spikes the previous scan does not confirm): they become
        NaN in ``Scan.ranges_m``, are marked in ``Scan.implausible`` and counted in
        ``stats.implausible_values``. Off by default (about 3 in 10 000 clean values
        flagged; see the class).
    """

    def __init__(self, port: str | serial.SerialBase, baudrate: int = 115200,
                 timeout: float = 1.0, *, reconnect: bool = True,
                 reconnect_timeout_s: float = 30.0,
                 plausibility: scip.RangePlausibility | None = None):
        if not isinstance(port, (str, serial.SerialBase)):
            raise ParameterError("urg.port", port, "a device path, pyserial URL or SerialBase")
        if not timeout > 0:
            raise ParameterError("urg.timeout", timeout, "> 0 s")
        self.port = port
        self.baudrate = int(baudrate)
        self.timeout = float(timeout)
        self.reconnect = bool(reconnect)
        self.reconnect_timeout_s = float(reconnect_timeout_s)
        if plausibility is not None and not isinstance(plausibility, scip.RangePlausibility):
            raise ParameterError("urg.plausibility", plausibility,
                                 "None or a nodlidar.scip.RangePlausibility")
        self.plausibility = plausibility
        self._previous: tuple[tuple, int, np.ndarray] | None = None  # (request, ts, mm)
        self.stats = DriverStats()
        self.params: scip.SensorParams | None = None
        self.clock_sync: ClockSync | None = None
        self._ser: serial.SerialBase | None = None
        self._fd: int | None = None
        self._framer = scip.ScipFramer()
        self._inbox: collections.deque[tuple[scip.ScipReply, float]] = collections.deque()
        self._unwrap = _Unwrapper()
        self._sync_source: Callable[[], float] | None = None
        self._sync_samples = 10
        self._tag_no = 0
        self._seq = 0

    # -- connection -------------------------------------------------------------------
    @property
    def is_open(self) -> bool:
        """True between :meth:`open` and :meth:`close`."""
        return self._ser is not None and self._ser.is_open

    def open(self) -> UrgDriver:
        """Open the port, bring the device to SCIP 2.0 idle, read ``PP``; return self."""
        self._open_port()
        try:
            try:
                self._handshake()
            except _LinkLost:
                # the most common mistake: the wrong port or baud rate - nothing answers
                junk = self._framer.discarded_bytes
                what = (f"no valid SCIP reply from {self._port_name()} within "
                        f"{self.timeout:g} s ({junk} bytes received that are not SCIP 2.0)"
                        if junk else
                        f"no SCIP reply from {self._port_name()} within {self.timeout:g} s")
                raise DeviceError(f"{what}: check the port and baud rate") from None
            self.params = self.parameters()
        except BaseException:
            self._close_port()
            raise
        return self

    def close(self) -> None:
        """Stop any stream (best effort) and close the port."""
        ser = self._ser
        if ser is not None and ser.is_open:
            try:
                ser.write(b"QT\n")
                ser.flush()
            except (serial.SerialException, OSError):
                pass
        self._close_port()

    def __enter__(self) -> UrgDriver:
        return self.open()

    def __exit__(self, *exc) -> None:
        self.close()

    def _port_name(self) -> str:
        return self.port if isinstance(self.port, str) else str(getattr(self.port, "port", "port"))

    def _open_port(self) -> None:
        if isinstance(self.port, str):
            ser = serial.serial_for_url(self.port, baudrate=self.baudrate, timeout=0,
                                        write_timeout=max(self.timeout, 1.0))
        else:
            ser = self.port
            if not ser.is_open:
                ser.open()
            ser.timeout = 0
        self._ser = ser
        try:
            self._fd = ser.fileno()
        except (AttributeError, NotImplementedError, serial.SerialException, OSError):
            self._fd = None
        self._framer = scip.ScipFramer()
        self._inbox.clear()

    def _close_port(self) -> None:
        ser, self._ser, self._fd = self._ser, None, None
        if ser is not None:
            try:
                ser.close()
            except (serial.SerialException, OSError):
                pass

    def _reconnect(self, why: str) -> None:
        """Reopen and handshake until it works or ``reconnect_timeout_s`` passes."""
        if not self.reconnect:
            raise DeviceError(f"urg link lost ({why}); reconnect disabled")
        self.stats.reconnects += 1
        deadline = time.monotonic() + self.reconnect_timeout_s
        pause = 0.02
        last: Exception | None = None
        while True:
            self._close_port()
            try:
                self._open_port()
                self._handshake()
                if self._sync_source is not None:
                    # the device may have been power cycled (its timer restarted): measure
                    # the clock offset again before any scan is stamped with it
                    self._sync(self._sync_samples, self._sync_source)
                return
            except (serial.SerialException, OSError, DeviceError, _LinkLost) as e:
                last = e
            if time.monotonic() + pause > deadline:
                self._close_port()
                raise DeviceError(
                    f"urg device at {self.port!r} did not come back within "
                    f"{self.reconnect_timeout_s} s (last error: {last})")
            time.sleep(pause)
            pause = min(pause * 2, 0.2)

    # -- bytes and messages -----------------------------------------------------------
    def _write(self, data: bytes) -> None:
        if self._ser is None:
            raise DeviceError("urg port is not open; call open() first")
        try:
            self._ser.write(data)
        except serial.SerialTimeoutException as e:
            raise _LinkLost(f"write timed out: {e}") from None

    def _pump(self, wait_s: float) -> None:
        """Read what arrives within ``wait_s`` and frame it."""
        ser = self._ser
        if ser is None:
            raise DeviceError("urg port is not open; call open() first")
        if self._fd is not None:
            r, _, _ = select.select([self._fd], [], [], max(0.0, wait_s))
            if not r:
                return
            data = ser.read(1 << 16)
        else:
            ser.timeout = max(0.001, wait_s)
            data = ser.read(max(1, ser.in_waiting))
        if not data:
            return
        t = time.monotonic()
        f = self._framer
        rej, disc = f.rejected, f.discarded_bytes
        for m in f.feed_replies(data):
            self._inbox.append((m, t))
        self.stats.rejected_messages += f.rejected - rej
        self.stats.discarded_bytes += f.discarded_bytes - disc

    def _next_message(self, deadline: float) -> tuple[scip.ScipReply, float] | None:
        """Next verified message and its receive time, or None at ``deadline``."""
        while True:
            if self._inbox:
                return self._inbox.popleft()
            left = deadline - time.monotonic()
            if left <= 0:
                return None
            self._pump(min(left, 0.05))

    def _request(self, line: bytes, timeout: float | None = None) -> scip.ScipReply:
        """Send one command line; return the reply whose echo matches it exactly."""
        echo = line.rstrip(b"\r\n").decode("ascii")
        self._write(line)
        deadline = time.monotonic() + (self.timeout if timeout is None else timeout)
        while True:
            got = self._next_message(deadline)
            if got is None:
                self.stats.timeouts += 1
                raise _LinkLost(f"no reply to {echo!r} within {self.timeout} s")
            reply, _ = got
            if reply.echo == echo:
                return reply
            self.stats.stale_messages += 1

    def _handshake(self) -> None:
        """Bring the device from any state (streaming, SCIP 1.1, TM mode) to idle SCIP 2.0."""
        self.stats.handshakes += 1
        self._write(b"\n")  # terminate a partial command line, if any
        deadline = time.monotonic() + 0.02
        while self._next_message(deadline) is not None:
            self.stats.stale_messages += 1
        for _ in range(6):
            reply = self._request(b"QT\n")
            if reply.scip1:
                self._request(b"SCIP2.0\n")
                continue
            if reply.status == "0E":
                self._request(b"TM2\n")
                continue
            if reply.status == "00":
                return
        raise DeviceError(f"urg handshake: QT answered {reply.status!r}; allowed: '00'")

    def _call(self, line: bytes, allowed: tuple[str, ...] = ("00",)) -> scip.ScipReply:
        """Request with reconnect-and-retry on link loss; check the status."""
        for attempt in range(3):
            try:
                return scip.check_status(self._request(line), allowed)
            except (_LinkLost, serial.SerialException, OSError) as e:
                if attempt == 2:
                    raise DeviceError(f"urg {line.strip()!r}: {e}") from None
                self._reconnect(str(e))
        raise AssertionError("unreachable")

    # -- info and simple commands -----------------------------------------------------
    def version(self) -> scip.VersionInfo:
        """``VV``: vendor, product, firmware, protocol, serial number."""
        return scip.parse_version(self._call(b"VV\n"))

    def parameters(self) -> scip.SensorParams:
        """``PP``: model, DMIN/DMAX, ARES, AMIN/AMAX/AFRT, SCAN.

        The step geometry every scan is decoded with comes from here, so a reply with a
        line that verifies under no checksum rule (a garbled digit) is asked for again, up
        to 3 times; only then is it accepted (with the codec's
        :class:`~nodlidar.scip.ScipChecksumWarning`).
        """
        for attempt in range(3):
            reply = self._call(b"PP\n")
            if attempt == 2 or all(scip.info_line_verifies(ln) for ln in reply.body):
                try:
                    return scip.parse_params(reply)
                except ProtocolError:
                    if attempt == 2:
                        raise
            self.stats.bad_info_replies += 1
        raise AssertionError("unreachable")

    def state(self) -> scip.SensorState:
        """``II``: laser, motor, mode, bit rate, time, status text."""
        return scip.parse_state(self._call(b"II\n"))

    def info(self) -> DeviceInfo:
        """``VV``, ``PP`` and ``II`` at once."""
        return DeviceInfo(self.version(), self.parameters(), self.state())

    @property
    def model(self) -> LidarModel:
        """The connected device as a :class:`~nodlidar.lidar.LidarModel` (from ``PP``)."""
        return self._params().to_lidar_model()

    def laser_on(self) -> None:
        """``BM`` (already on is fine)."""
        self._call(b"BM\n", ("00", "02"))

    def laser_off(self) -> None:
        """``QT``: laser off, stream stopped."""
        self._call(b"QT\n")

    def reset(self) -> None:
        """``RS``: laser off, motor speed and bit rate to default, timer to zero."""
        self._call(b"RS\n")
        self._unwrap = _Unwrapper()
        self.clock_sync = None
        self._sync_source = None

    def _params(self) -> scip.SensorParams:
        if self.params is None:
            self.params = self.parameters()
        return self.params

    # -- clock ------------------------------------------------------------------------
    def sync_clock(self, samples: int = 10,
                   time_source: Callable[[], float] = time.monotonic) -> ClockSync:
        """Estimate the device-to-host clock offset with ``TM0``/``TM1``/``TM2``.

        ``time_source`` is the host clock to map to (default ``time.monotonic``; pass the
        actuators' time source so scan stamps and servo samples share one clock).

        Each ``TM1`` round trip gives ``offset = (t_send + t_recv) / 2 - t_device``; the
        sample with the smallest round-trip time is kept (its error is at most half
        that RTT plus the 1 ms timer resolution). Switches the laser off.

        After a reconnect the driver repeats the measurement with the same ``samples`` and
        ``time_source`` (a power-cycled device restarts its timer at zero).
        """
        if samples < 1:
            raise ParameterError("urg.sync_clock.samples", samples, ">= 1")
        for attempt in range(3):
            try:
                self._sync(samples, time_source)
                break
            except (_LinkLost, serial.SerialException, OSError) as e:
                if attempt == 2:
                    raise DeviceError(f"urg clock sync: {e}") from None
                self._reconnect(str(e))
        self._sync_source, self._sync_samples = time_source, int(samples)
        assert self.clock_sync is not None  # set by _sync
        return self.clock_sync

    def _sync(self, samples: int, time_source: Callable[[], float]) -> None:
        """TM0, ``samples`` x TM1, TM2 -> :attr:`clock_sync` (raises like ``_request``)."""
        self._request_ok(b"TM0\n", ("00", "02"))
        best: tuple[float, float] | None = None
        try:
            for _ in range(samples):
                t0 = time_source()
                reply = self._request_ok(b"TM1\n", ("00",))
                t1 = time_source()
                if not reply.body:
                    raise ProtocolError("urg TM1 reply has no time line; allowed: 4 chars + sum")
                dev_ms = self._unwrap(scip.decode_value(scip.verify_line(reply.body[0])),
                                      0.5 * (t0 + t1))
                rtt = t1 - t0
                if best is None or rtt < best[0]:
                    best = (rtt, 0.5 * (t0 + t1) - dev_ms / 1000.0)
        finally:
            self._request_ok(b"TM2\n", ("00", "03"))
        assert best is not None  # samples >= 1
        self.clock_sync = ClockSync(offset_s=best[1], rtt_s=best[0], samples=samples)

    def _request_ok(self, line: bytes, allowed: tuple[str, ...]) -> scip.ScipReply:
        """One request, status checked, no reconnect (the caller handles link loss)."""
        return scip.check_status(self._request(line), allowed)

    def _step0_host_time(self) -> float:
        """Host time [s] of step 0 of a scan complete now, in the clock the device timer is
        synced to (``time.monotonic`` if none): a scan arrives one revolution after its
        step 0 (its timestamp)."""
        return (self._sync_source or time.monotonic)() - 60.0 / self._params().scan_rpm

    # -- scans ------------------------------------------------------------------------
    def _request_for(self, command: str, start: int | None, end: int | None, cluster: int,
                     interval: int | None, count: int | None, tag: str | None
                     ) -> scip.DistanceRequest:
        p = self._params()
        start = p.amin if start is None else int(start)
        end = p.amax if end is None else int(end)
        if not p.amin <= start <= end <= p.amax:
            raise ParameterError("urg.steps", (start, end), f"{p.amin} <= start <= end <= {p.amax}")
        return scip.DistanceRequest(command, start, end, int(cluster), interval, count, tag)

    def _make_scan(self, frame: scip.ScanFrame, t_rx: float, ts: int, index: int,
                   raw: bytes = b"") -> Scan:
        p = self._params()
        period_ms = 60000.0 / p.scan_rpm
        stamp = (self.clock_sync.host_time(ts) if self.clock_sync is not None
                 else t_rx - period_ms / 1000.0)
        rm = frame.ranges_mm
        ranges_m = scip.ranges_mm_to_m(rm, p.dmin_mm)
        flags = None
        if self.plausibility is not None:
            r = frame.request
            key = (r.command, r.start, r.end, r.cluster)
            prev = self._previous
            # the previous scan of the same steps, if at most 1 s old
            if prev is not None and prev[0] == key and 0 < ts - prev[1] <= 1000:
                previous, period_s = prev[2], (ts - prev[1]) / 1000.0
            else:
                previous, period_s = None, period_ms / 1000.0
            flags = self.plausibility.flag(rm, dmin_mm=p.dmin_mm, dmax_mm=p.dmax_mm,
                                           previous_mm=previous, period_s=period_s)
            ranges_m[flags] = np.nan
            self.stats.implausible_values += int(flags.sum())
            self._previous = (key, ts, rm)
        scan = Scan(seq=self._seq, index=index, request=frame.request, steps=frame.steps,
                    ranges_m=ranges_m, ranges_mm=rm,
                    timestamp_ms=ts, host_time_s=t_rx, stamp_s=stamp, dmin_mm=p.dmin_mm,
                    raw=raw, implausible=flags)
        self._seq += 1
        self.stats.scans += 1
        return scan

    def scan(self, start: int | None = None, end: int | None = None, cluster: int = 1, *,
             command: str = "GD") -> Scan:
        """One scan with ``GD`` (or ``GS``): laser on, wait for the next complete scan.

        Parameters
        ----------
        start, end : int, optional
            Steps (default AMIN..AMAX).
        cluster : int
            Steps merged per value (minimum range).
        command : {"GD", "GS"}
            3-char (to 262 m) or 2-char (to 4.095 m) encoding.
        """
        if command not in ("GD", "GS"):
            raise ParameterError("urg.scan.command", command, "GD or GS")
        req = self._request_for(command, start, end, cluster, None, None, None)
        for attempt in range(3):
            try:
                self._call(b"BM\n", ("00", "02"))
                reply = self._request(req.encode(), timeout=self.timeout + 0.3)
                frame = scip.decode_scan(reply)
                ts = self._unwrap(frame.timestamp_ms, self._step0_host_time())
                return self._make_scan(frame, time.monotonic(), ts, 0, reply.raw)
            except ProtocolError:
                self.stats.bad_scans += 1
            except (_LinkLost, serial.SerialException, OSError) as e:
                if attempt == 2:
                    raise DeviceError(f"urg {req.line()}: {e}") from None
                self._reconnect(str(e))
        raise DeviceError(f"urg {req.line()}: no valid scan in 3 attempts")

    def stream(self, start: int | None = None, end: int | None = None, cluster: int = 1,
               interval: int = 0, count: int = 0, *, command: str = "MD") -> Iterator[Scan]:
        """Iterate over scans of an ``MD`` (or ``MS``) stream.

        Parameters
        ----------
        start, end : int, optional
            Steps (default AMIN..AMAX).
        cluster : int
            Steps merged per value.
        interval : int
            Scans skipped between transmissions (0..9).
        count : int
            Scans to deliver; 0 = until the iterator is closed. Above 99 the driver runs
            an endless stream and stops it itself.
        command : {"MD", "MS"}

        Notes
        -----
        Closing the iterator (``break``) sends ``QT``. On link loss the driver reconnects
        and restarts the stream; scans missed meanwhile count in ``stats.dropped_scans``.
        """
        if command not in ("MD", "MS"):
            raise ParameterError("urg.stream.command", command, "MD or MS")
        if not (isinstance(count, (int, np.integer)) and count >= 0):
            raise ParameterError("urg.stream.count", count, "an integer >= 0")
        dev_count = int(count) if count <= 99 else 0
        base = self._request_for(command, start, end, cluster, interval, dev_count, None)
        return self._stream(base, int(count), dev_count)

    def _start_stream(self, base: scip.DistanceRequest, n: int) -> scip.DistanceRequest:
        """Send the MD/MS request and wait for its acknowledgement.

        The acknowledgement can be lost (garbled) while the device starts streaming: a
        scan message of this request then stands for it and is kept for the consumer.
        An error status in the acknowledgement (e.g. ``50`` hardware trouble) raises
        :class:`~nodlidar.scip.ScipStatusError`.
        """
        self._tag_no += 1
        req = scip.DistanceRequest(base.command, base.start, base.end, base.cluster,
                                   base.interval, n, f"n{self._tag_no}")
        echo = req.line()
        self._write(req.encode())
        deadline = time.monotonic() + self.timeout
        while True:
            got = self._next_message(deadline)
            if got is None:
                self.stats.timeouts += 1
                raise _LinkLost(f"no reply to {echo!r} within {self.timeout} s")
            reply = got[0]
            if reply.echo == echo and reply.status != "99":
                scip.check_status(reply, ("00",))
                return req
            if reply.status == "99" and self._same_stream(reply, req):
                self.stats.lost_acks += 1
                self._inbox.appendleft(got)  # the first scan: deliver it
                return req
            self.stats.stale_messages += 1

    @staticmethod
    def _same_stream(reply: scip.ScipReply, req: scip.DistanceRequest) -> bool:
        """Is ``reply``'s echo one of ``req``'s scan echoes (any remaining count)?"""
        e = reply.echo
        body = req.line(0)
        return (reply.code == req.command and len(e) == len(body)
                and e[:13] == body[:13] and e[15:] == body[15:])

    def _stream(self, base: scip.DistanceRequest, total: int, dev_count: int) -> Iterator[Scan]:
        every = (base.interval or 0) + 1
        period_ms = 60000.0 / self._params().scan_rpm
        delivered = 0
        first_ms: float | None = None
        last_index = -1
        last_stamp: float | None = None   # host stamp of the last scan delivered [s]
        resets_seen = self._unwrap.resets
        device_left = dev_count  # scans the device still owes (finite requests)
        req = None
        try:
            while True:
                try:
                    if req is None:
                        req = self._start_stream(base, device_left if dev_count else 0)
                    last_rx = time.monotonic()
                    while total == 0 or delivered < total:
                        got = self._next_message(last_rx + self.timeout)
                        if got is None:
                            self.stats.timeouts += 1
                            raise _LinkLost(f"no scan within {self.timeout} s")
                        reply, t_rx = got
                        fr = self._match(reply, req)
                        if fr is None:
                            continue
                        last_rx = t_rx
                        ts = self._unwrap(fr.timestamp_ms, self._step0_host_time())
                        if first_ms is None:
                            first_ms = ts
                        if (self._unwrap.resets != resets_seen and last_stamp is not None
                                and self.clock_sync is not None):
                            # the device timer restarted (a power cycle): the unwrapped
                            # timeline bridged the gap by receive times, whose jitter a
                            # loaded host stretches past half a period; the clock syncs on
                            # both sides (the new one made at the reconnect) are bounded
                            # by their RTTs, so the gap is counted from the two stamps
                            gap = (self.clock_sync.host_time(ts) - last_stamp) * 1000.0
                            first_ms = ts - (last_index + round(gap / period_ms)) * period_ms
                        resets_seen = self._unwrap.resets
                        index = int(round((ts - first_ms) / period_ms))
                        if index <= last_index:
                            self.stats.stale_messages += 1
                            continue
                        if last_index >= 0:
                            self.stats.dropped_scans += max(0, (index - last_index) // every - 1)
                        last_index = index
                        scan = self._make_scan(fr, t_rx, ts, index, reply.raw)
                        last_stamp = scan.stamp_s if self.clock_sync is not None else None
                        if dev_count:
                            device_left = fr.remaining or 0
                        delivered += 1
                        yield scan
                        if dev_count and fr.remaining == 0:
                            req = None
                            return
                    return
                except (_LinkLost, serial.SerialException, OSError) as e:
                    if dev_count and device_left == 0:
                        return
                    self._reconnect(str(e))
                    req = None
        finally:
            if req is not None and self.is_open:
                try:
                    self._request(b"QT\n")
                except (_LinkLost, serial.SerialException, OSError, DeviceError):
                    pass

    def _match(self, reply: scip.ScipReply, req: scip.DistanceRequest) -> scip.ScanFrame | None:
        """The scan frame if ``reply`` belongs to the stream ``req``, else None."""
        code = reply.code
        if code != req.command:
            self.stats.stale_messages += 1
            return None
        if reply.status == "00":  # a repeated acknowledgement
            self.stats.stale_messages += 1
            return None
        if reply.status != "99":
            # '98' (laser back to normal), a documented error status (21-97) or one the
            # checksum let through ('9y'): dropped like a bad checksum. A device that
            # really stopped sends nothing more: the timeout restarts the stream and the
            # new acknowledgement then carries the error status, raised from there.
            self.stats.bad_statuses += 1
            return None
        try:
            fr = scip.decode_scan(reply)
        except ProtocolError:
            self.stats.bad_scans += 1
            return None
        r = fr.request
        if (r.start, r.end, r.cluster, r.interval, r.tag) != (
                req.start, req.end, req.cluster, req.interval, req.tag):
            self.stats.stale_messages += 1
            return None
        if req.count and not (r.count or 0) < req.count:
            self.stats.bad_scans += 1
            return None
        return fr
