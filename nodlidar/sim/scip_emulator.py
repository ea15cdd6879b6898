"""SCIP 2.0 device emulator (Hokuyo URG-04LX and relatives), served over TCP or a pty.

The emulated device answers the SCIP 2.0 command set of the Hokuyo protocol
specification (C-42-03320B): ``SCIP2.0``, ``VV``, ``PP``, ``II``, ``BM``, ``QT``, ``RS``,
``TM0/1/2``, ``SS``, ``CR``, ``GD``/``GS`` and ``MD``/``MS``, with the spec's error
statuses. It encodes everything with :mod:`nodlidar.scip`, the same codec the driver uses.

Time: the device scans continuously, one revolution per ``model.scan_period_s`` of the
shared :class:`~nodlidar.sim.clock.SimClock`; scan ``k`` starts at ``t = k * period`` and
its data are sent when it completes, at ``(k + 1) * period``. The 24-bit millisecond
timer reads ``round(1000 t) + timer_offset_ms`` (``RS`` sets it to zero).

Ranges come from ``range_source(scan_index, t_scan_start_s) -> (n_steps,) [m]`` for all
valid steps ``model.step_min .. model.step_max``; NaN means no return. They are rounded to
mm; NaN becomes ``no_return_code``, ranges beyond DMAX (or beyond 4095 mm in the 2-char
GS/MS encoding) ``out_of_range_code``, ranges below DMIN ``too_near_code``.

Serving: :meth:`ScipEmulator.serve_tcp` returns a ``socket://host:port`` URL and
:meth:`ScipEmulator.serve_pty` a tty path; either works with ``serial.serial_for_url``.
Background threads do the work; :meth:`ScipEmulator.stop` (or leaving the ``with`` block)
ends them. Faults (:class:`~nodlidar.sim.faults.FaultConfig`) act on outgoing messages.
"""

from __future__ import annotations

import errno
import math
import os
import select
import socket
import threading
import time
import tty
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from nodlidar import scip
from nodlidar.errors import ParameterError, require
from nodlidar.lidar import LidarModel, lidar_model
from nodlidar.sim.clock import SimClock
from nodlidar.sim.faults import FaultConfig, FaultInjector

__all__ = [
    "RangeSource",
    "EmulatorStats",
    "ScipDevice",
    "ScipEmulator",
    "constant_source",
    "flat_wall_source",
    "quantise_ranges",
    "cluster_ranges",
    "RANGE_CODES",
    "STEP_TABLE_MAX",
    "OUTSIDE_AREA_CODE",
]

RangeSource = Callable[[int, float], np.ndarray]

#: (no return, beyond DMAX, below DMIN) range error codes per model family (SPEC p.12):
#: URG-04LX 0 = "object possibly at 22 m", 6 = "others"; UTM-30LX 1 = "no object in
#: range", 4 = "object out of range", 2 = "object too near".
RANGE_CODES: dict[str, tuple[int, int, int]] = {
    "URG-04LX": (0, 0, 6),
    "UTM-30LX": (1, 4, 2),
    "UST-10LX": (1, 4, 2),
}

_BITRATES = ("019200", "038400", "057600", "115200", "250000", "500000", "750000")

#: Last step a GD/GS/MD/MS request may name, per model. Source: the step table of the SCIP
#: 2.0 specification (Hokuyo C-42-03320B) as cited in issue 15 - steps 0..768 for the
#: URG-04LX (ARES 1024; the measurable area AMIN..AMAX = 44..725 lies inside it); the
#: UTM-30LX and UST-10LX tables end at their AMAX (1080). Steps requested outside
#: AMIN..AMAX carry :data:`OUTSIDE_AREA_CODE`.
STEP_TABLE_MAX: dict[str, int] = {"URG-04LX": 768, "UTM-30LX": 1080, "UST-10LX": 1080}
#: Error code of a requested step outside the measurable area: 19, "non-measurable step"
#: in the spec's URG-04LX error-code table (SPEC p.12, Table 3; scip2.md §1.7).
OUTSIDE_AREA_CODE = 19
#: Firmware that has ``HS`` (>= 3.2.00) and ``DB`` (>= 3.3.00) (scip2.md §1.8); the
#: emulator reports 3.4.03, the firmware of the real UG01 captures.
_HS_MODELS = ("URG-04LX",)


def constant_source(model: LidarModel, range_m: float = 1.0) -> RangeSource:
    """Every step sees ``range_m`` [m]."""
    ranges = np.full(model.n_steps, float(range_m))
    ranges.setflags(write=False)
    return lambda k, t: ranges


def flat_wall_source(model: LidarModel, distance_m: float = 1.5,
                     sway_m: float = 0.0, sway_period_scans: int = 50) -> RangeSource:
    """A flat wall ``distance_m`` [m] in front (x), optionally swaying with scan index.

    Steps pointing away from the wall (|bearing| >= 90 deg) see no return (NaN).
    """
    cosb = np.cos(model.bearing_from_step(model.steps))

    def source(k: int, t: float) -> np.ndarray:
        d = distance_m + sway_m * math.sin(2 * math.pi * k / sway_period_scans)
        with np.errstate(divide="ignore"):
            r = np.where(cosb > 1e-6, d / np.maximum(cosb, 1e-6), np.nan)
        return r

    return source


def quantise_ranges(ranges_m: np.ndarray, dmin_mm: int, dmax_mm: int, n_chars: int = 3,
                    codes: tuple[int, int, int] = (0, 0, 6)) -> np.ndarray:
    """Ranges [m] -> what the device sends [mm or error code], shape preserved, int64.

    Parameters
    ----------
    ranges_m : numpy.ndarray
        Ranges [m]; NaN = no return.
    dmin_mm, dmax_mm : int
        Measurable range [mm].
    n_chars : int
        3 (GD/MD) or 2 (GS/MS: values above 4095 mm are out of range).
    codes : (int, int, int)
        Error codes for no return, beyond DMAX, below DMIN.
    """
    r = np.asarray(ranges_m, dtype=np.float64)
    no_ret, far, near = codes
    nan = np.isnan(r)
    mm = np.rint(np.where(nan, 0.0, r) * 1000.0)
    top = dmax_mm if n_chars == 3 else min(dmax_mm, 4095)
    out = np.where(mm > top, far, np.where(mm < dmin_mm, near, mm))
    out = np.where(nan, no_ret, out)
    return out.astype(np.int64)


def cluster_ranges(values_mm: np.ndarray, cluster: int, dmin_mm: int) -> np.ndarray:
    """Merge groups of ``cluster`` steps into their minimum valid value (SPEC §8.1).

    A group whose steps are all error codes keeps its first step's code.
    """
    c = max(1, int(cluster))
    v = np.asarray(values_mm, dtype=np.int64)
    if c == 1:
        return v
    n = -(-v.size // c)
    pad = np.full(n * c, np.iinfo(np.int64).max, dtype=np.int64)
    pad[: v.size] = np.where(v >= dmin_mm, v, np.iinfo(np.int64).max)
    m = pad.reshape(n, c).min(axis=1)
    first = v[::c]
    return np.where(m == np.iinfo(np.int64).max, first, m)


@dataclass
class EmulatorStats:
    """Counters of an emulator run (mutable, updated by the emulator threads)."""

    connections: int = 0
    commands: int = 0
    #: command lines whose immediate replies have all been written (transports only);
    #: ``commands`` counts them when they arrive, before any reply is written
    commands_answered: int = 0
    messages_sent: int = 0
    scans_sent: int = 0
    scans_skipped: int = 0
    bytes_dropped: int = 0
    bytes_corrupted: int = 0
    stalls: int = 0
    disconnects: int = 0
    #: TCP connections that waited for the host holding the session to leave
    queued_connections: int = 0
    #: TCP connections refused: another host held the session and one was already waiting
    refused_connections: int = 0
    #: command lines longer than ``max_line_bytes``, dropped (answered 0D)
    long_lines: int = 0
    #: wall-clock (time.monotonic) instants the link came back after a disconnect
    up_times: list[float] = field(default_factory=list)
    #: wall-clock (time.monotonic) instants a stall would end (the device resumes
    #: sending); a host that reconnects during a stall ends it earlier
    stall_ends: list[float] = field(default_factory=list)


@dataclass
class _Stream:
    request: scip.DistanceRequest
    next_k: int
    sent: int = 0


class ScipDevice:
    """The transport-free SCIP 2.0 state machine of one sensor.

    Parameters
    ----------
    model : LidarModel
        Geometry, timing and range limits (reported by ``PP``).
    clock : SimClock
        Time base for scans and the device timer.
    range_source : callable, optional
        ``(scan_index, t_scan_start_s) -> (n_steps,) ranges [m]``; default a flat wall.
    scip1 : bool
        Boot in SCIP 1.1 mode (answers only ``SCIP2.0``, others with status ``E``).
    timer_offset_ms : int
        Device timer at clock time 0 [ms].
    codes : (int, int, int), optional
        Range error codes (no return, beyond DMAX, below DMIN); default per model.
    max_backlog_scans : int
        If the link is this many scans behind, skip to the newest complete scan.
    """

    def __init__(self, model: LidarModel, clock: SimClock, range_source: RangeSource | None = None,
                 *, scip1: bool = False, timer_offset_ms: int = 0,
                 codes: tuple[int, int, int] | None = None, max_backlog_scans: int = 2,
                 version: scip.VersionInfo | None = None):
        self.model = model
        self.clock = clock
        self.range_source = range_source or flat_wall_source(model)
        self.boot_scip1 = bool(scip1)
        self.codes = codes or RANGE_CODES.get(model.name, (0, 0, 6))
        self.params = scip.SensorParams.from_lidar_model(model)
        self.version = version or scip.VersionInfo(
            vendor="Hokuyo Automatic Co.,Ltd.", product=f"SOKUIKI Sensor {model.name}",
            firmware="3.4.03(17/Dec./2012)", protocol="SCIP 2.0", serial="H0000001")
        self.period_s = model.scan_period_s
        self.max_step = max(STEP_TABLE_MAX.get(model.name, model.step_max), model.step_max)
        self.max_backlog_scans = int(max_backlog_scans)
        self._timer_base_ms = -int(timer_offset_ms)
        self._cache: OrderedDict[int, np.ndarray] = OrderedDict()
        self.stats = EmulatorStats()
        self.power_on()

    # -- state ------------------------------------------------------------------------
    def power_on(self) -> None:
        """(Re)boot: laser off, no stream, default speed/bit rate (timer keeps running)."""
        self.scip1 = self.boot_scip1
        self.laser_on = False
        self.adjust_mode = False
        self.bitrate = "019200"
        self.motor_level = 0
        self.high_sensitivity = False
        self.malfunction: int | None = None  # DB: the simulated malfunction number
        self.stream: _Stream | None = None
        self._pending_gd: list[tuple[int, scip.DistanceRequest]] = []

    def link_reset(self) -> None:
        """A new host connection: stop sending scans (the link they were for is gone)."""
        self.stream = None
        self._pending_gd.clear()

    def reset_timer(self, t: float) -> None:
        """Make the timer read 0 at simulated time ``t`` [s] (``RS``, a power cycle).

        :meth:`scan_index` then maps the new timer's timestamps."""
        self._timer_base_ms = int(round(t * 1000.0))

    def timer_ms(self, t: float) -> int:
        """Device timer at simulated time ``t`` [ms], 24-bit."""
        return (int(round(t * 1000.0)) - self._timer_base_ms) % scip.TIMESTAMP_MODULUS_MS

    def scan_index(self, timestamp_ms: int) -> int:
        """Scan number ``k`` whose (unwrapped) timestamp is ``timestamp_ms``."""
        return int(round((timestamp_ms + self._timer_base_ms) / (1000.0 * self.period_s)))

    # -- ranges ----------------------------------------------------------------------
    def source_ranges_m(self, k: int) -> np.ndarray:
        """Ranges [m] of all valid steps in scan ``k``, shape ``(n_steps,)`` (cached)."""
        r = self._cache.get(k)
        if r is None:
            r = np.asarray(self.range_source(k, k * self.period_s), dtype=np.float64)
            if r.shape != (self.model.n_steps,):
                raise ParameterError("range_source.shape", r.shape, f"({self.model.n_steps},)")
            self._cache[k] = r
            while len(self._cache) > 8:
                self._cache.popitem(last=False)
        return r

    def expected_ranges_mm(self, k: int, request: scip.DistanceRequest) -> np.ndarray:
        """The values the device sends for scan ``k`` under ``request`` [mm/codes]."""
        m = self.model
        q = quantise_ranges(self.source_ranges_m(k), self.params.dmin_mm, self.params.dmax_mm,
                            request.n_chars, self.codes)
        if request.start < m.step_min or request.end > m.step_max:
            # steps of the spec's table outside the measurable area: error code
            full = np.full(self.max_step + 1, OUTSIDE_AREA_CODE, dtype=np.int64)
            full[m.step_min: m.step_max + 1] = q
            sel = full[request.start: request.end + 1]
        else:
            sel = q[request.start - m.step_min: request.end - m.step_min + 1]
        return cluster_ranges(sel, request.cluster, self.params.dmin_mm)

    def _scan_message(self, k: int, req: scip.DistanceRequest, status: str,
                      remaining: int | None) -> bytes:
        return scip.encode_scan_reply(req.echo(remaining), status,
                                      self.timer_ms(k * self.period_s),
                                      self.expected_ranges_mm(k, req), req.n_chars)

    # -- commands ---------------------------------------------------------------------
    def handle_line(self, line: bytes, now: float) -> list[bytes]:
        """Process one command line (terminator stripped); return the immediate replies."""
        echo = line.rstrip(b"\r\n")
        if not echo:
            return []
        self.stats.commands += 1
        if self.scip1:
            if echo == b"SCIP2.0":
                self.scip1 = False
                return [scip.encode_message(echo, "0", scip1=True)]
            return [scip.encode_message(echo, "E", scip1=True)]
        try:
            text = echo.decode("ascii")
        except UnicodeDecodeError:
            return [scip.encode_message(echo.decode("ascii", "replace").encode("ascii", "replace"),
                                        "0E")]

        def reply(status: str, body=()) -> list[bytes]:
            return [scip.encode_message(echo, status, body)]

        code, params, tag = scip.split_command(text)
        if tag is not None:
            if len(tag) > 16:
                return reply("0G")
            if not scip._TAG_RE.fullmatch(tag):
                return reply("0H")
        if self.adjust_mode and code != "TM":
            return reply("0E")
        if code == "SCIP2.0":
            return reply("0E")  # already in SCIP 2.0 (UG01 behaviour)
        if code in ("VV", "PP", "II", "BM", "QT", "RS"):
            if params:
                return reply("0D")
            if code == "VV":
                return [scip.encode_info_reply(echo, self.version.items())]
            if code == "PP":
                return [scip.encode_info_reply(echo, self.params.items())]
            if code == "II":
                return [scip.encode_info_reply(echo, self._state(now).items())]
            if code == "BM":
                if self.laser_on:
                    return reply("02")
                self.laser_on = True
                return reply("00")
            if code == "QT":
                self.stream = None
                self._pending_gd.clear()
                self.laser_on = False
                return reply("00")
            # RS: laser off, motor speed and bit rate to default, timer reset (SPEC §8.5)
            self.power_on()
            self.scip1 = False
            self.reset_timer(now)
            return reply("00")
        if code == "TM":
            if params == "0":
                if self.adjust_mode:
                    return reply("02")
                self.adjust_mode = True
                self.laser_on = False
                self.stream = None
                self._pending_gd.clear()
                return reply("00")
            if params == "1":
                if not self.adjust_mode:
                    return reply("04")
                ts = scip.with_checksum(scip.encode_value(self.timer_ms(now), 4))
                return reply("00", [ts])
            if params == "2":
                if not self.adjust_mode:
                    return reply("03")
                self.adjust_mode = False
                return reply("00")
            return reply("01")
        if code == "SS":
            if len(params) != 6 or not params.isdigit():
                return reply("01") if len(params) == 6 else reply("0C" if len(params) < 6
                                                                  else "0D")
            if params not in _BITRATES:
                return reply("02")
            if params == self.bitrate:
                return reply("03")
            self.bitrate = params
            return reply("00")
        if code == "CR":
            if len(params) != 2 or not params.isdigit():
                return reply("01") if len(params) == 2 else reply("0C" if len(params) < 2
                                                                  else "0D")
            level = int(params)
            if not (0 <= level <= 10 or level == 99):
                return reply("02")
            self.motor_level = 0 if level == 99 else level
            return reply("00")
        if code == "HS":  # high sensitivity 0/1, URG-04LX firmware >= 3.2.00 (SPEC §8)
            if len(params) != 1:
                return reply("0C" if not params else "0D")
            if self.model.name not in _HS_MODELS:
                return reply("03")
            if params not in ("0", "1"):
                return reply("01")
            if (params == "1") == self.high_sensitivity:
                return reply("02")
            self.high_sensitivity = params == "1"
            return reply("00")
        if code == "DB":
            # simulate malfunction 01-05, 10 ends it (URG-04LX firmware >= 3.3.00); the
            # reference gives no more than the accepted parameters and statuses 00-05, so
            # the emulator records the state (II STAT shows it) and keeps scanning
            if len(params) != 2:
                return reply("0C" if len(params) < 2 else "0D")
            if not params.isdigit():
                return reply("01")
            n = int(params)
            if n == 10:
                self.malfunction = None
                return reply("00")
            if not 1 <= n <= 5:
                return reply("01")
            self.malfunction = n
            return reply("00")
        if code in ("GD", "GS", "MD", "MS"):
            try:
                req = scip.DistanceRequest.parse(echo)
            except scip.ScipRequestError as e:
                return reply(e.status)
            if req.end > self.max_step:  # the step table, not AMIN..AMAX (see STEP_TABLE_MAX)
                return reply("04")
            k_next = math.ceil(now / self.period_s - 1e-9)
            if not req.is_multi:
                if not self.laser_on:
                    return reply("10")
                self._pending_gd.append((k_next, req))
                return []
            self.laser_on = True
            self.stream = _Stream(req, k_next)
            return reply("00")
        return reply("0E")

    def _state(self, now: float) -> scip.SensorState:
        # texts as in the URG-04LX II example of the URG wiki (scip2.md §1.10 vector 9),
        # "<-Default setting by user" while speed / bit rate are at their defaults
        streaming = self.stream is not None
        default = "<-Default setting by user"
        return scip.SensorState(
            model=self.params.model, laser="ON" if self.laser_on else "OFF",
            motor_speed=f"Initial({round(self.model.rpm)}[rpm]){default}" if self.motor_level == 0
            else f"Level {self.motor_level}",
            measure_mode="Measuring by Sensitive Mode" if streaming else "IDLE",
            bitrate=f"{int(self.bitrate)}[bps]" + (default if self.bitrate == "019200" else ""),
            time=f"{self.timer_ms(now):06X}",
            status="Sensor works well." if self.malfunction is None
            else f"Simulated malfunction {self.malfunction:02d} (DB).")

    # -- scans -----------------------------------------------------------------------
    def next_due(self) -> float | None:
        """Simulated time the next scan message is due, or None."""
        t = [(k + 1) * self.period_s for k, _ in self._pending_gd]
        if self.stream is not None:
            t.append((self.stream.next_k + 1) * self.period_s)
        return min(t) if t else None

    def poll(self, now: float) -> list[bytes]:
        """Scan messages due by ``now`` (GD replies and MD/MS scans), oldest first."""
        out: list[tuple[int, bytes]] = []
        if self._pending_gd:
            keep = []
            for k, req in self._pending_gd:
                if (k + 1) * self.period_s <= now + 1e-9:
                    out.append((k, self._scan_message(k, req, "00", None)))
                else:
                    keep.append((k, req))
            self._pending_gd = keep
        s = self.stream
        while s is not None and (s.next_k + 1) * self.period_s <= now + 1e-9:
            step = (s.request.interval or 0) + 1
            newest = math.floor(now / self.period_s + 1e-9) - 1
            behind = (newest - s.next_k) // step
            if behind > self.max_backlog_scans:
                self.stats.scans_skipped += behind
                s.next_k += behind * step
            count = s.request.count or 0
            remaining = 0 if count == 0 else count - s.sent - 1
            out.append((s.next_k, self._scan_message(s.next_k, s.request, "99", remaining)))
            s.sent += 1
            s.next_k += step
            if count and s.sent >= count:
                self.stream = s = None
                self.laser_on = False
        out.sort(key=lambda x: x[0])
        self.stats.scans_sent += len(out)
        return [m for _, m in out]


# ---------------------------------------------------------------------------------------
# transports
# ---------------------------------------------------------------------------------------
class _LinkClosed(Exception):
    pass


def _hung_up(sock: socket.socket) -> bool:
    """Has the peer of ``sock`` closed its end (or is ``sock`` closed)?"""
    try:
        p = select.poll()
        p.register(sock.fileno(), select.POLLRDHUP | select.POLLHUP | select.POLLERR)
        return bool(p.poll(0))
    except (OSError, ValueError):  # closed meanwhile
        return True


class _FdLink:
    """Non-blocking read/write on a file descriptor (socket or pty master)."""

    def __init__(self, fd: int, stop: threading.Event, sock: socket.socket | None = None):
        self.fd = fd
        self.sock = sock
        self.stop = stop
        os.set_blocking(fd, False)

    def read(self, timeout: float) -> bytes:
        r, _, _ = select.select([self.fd], [], [], max(0.0, timeout))
        if not r:
            return b""
        try:
            data = os.read(self.fd, 65536)
        except BlockingIOError:
            return b""
        except OSError as e:
            raise _LinkClosed(str(e)) from None
        if not data:
            raise _LinkClosed("eof")
        return data

    def write(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            if self.stop.is_set():
                raise _LinkClosed("stopped")
            try:
                n = os.write(self.fd, view)
                view = view[n:]
            except BlockingIOError:
                select.select([], [self.fd], [], 0.05)
            except OSError as e:
                if e.errno == errno.EAGAIN:
                    continue
                raise _LinkClosed(str(e)) from None


class ScipEmulator:
    """A SCIP 2.0 sensor served over TCP or a pseudo-terminal, in background threads.

    Parameters
    ----------
    model : LidarModel, optional
        Default the URG-04LX.
    clock : SimClock, optional
        Default a real-time :class:`SimClock`.
    range_source : callable, optional
        ``(scan_index, t_scan_start_s) -> (n_steps,) [m]``; default
        :func:`flat_wall_source`.
    faults : FaultConfig, optional
        Link faults to inject on outgoing messages.
    scip1 : bool
        Boot (and reboot after a disconnect) in SCIP 1.1 mode.
    reboot_resets_timer : bool
        A disconnect is a power cycle: the device comes back with its timer restarted at
        0 (a real URG unplugged and plugged in). Default False: the timer runs on.
    host : str
        Address :meth:`serve_tcp` listens on by default (loopback).
    port : int
        TCP port :meth:`serve_tcp` listens on by default (0 = any free port; a real
        Ethernet URG uses 10940).
    max_line_bytes : int
        Longest command line kept [bytes]. A longer one is dropped up to its line end and
        answered at once with status ``0D`` (command too long), its echo cut to 64
        characters; the longest valid SCIP 2.0 command is 32 bytes.
    **device_kw
        Passed to :class:`ScipDevice` (``timer_offset_ms``, ``codes``, ...).

    Notes
    -----
    Nothing is opened in the constructor; call :meth:`serve_tcp` or :meth:`serve_pty`
    (one transport per emulator), and :meth:`stop` or use ``with``. Over TCP one host at
    a time holds the session (as a real Ethernet URG): a second connection waits, unanswered,
    until the first host hangs up (``stats.queued_connections``; so commands run one after
    the other always find the device), a third is closed at once
    (``stats.refused_connections``). It used to take the session over silently.
    """

    def __init__(self, model: LidarModel | None = None, clock: SimClock | None = None,
                 range_source: RangeSource | None = None, *, faults: FaultConfig | None = None,
                 scip1: bool = False, reboot_resets_timer: bool = False,
                 host: str = "127.0.0.1", port: int = 0, max_line_bytes: int = 256,
                 **device_kw: Any):
        require(isinstance(host, str) and bool(host), "emulator.host", host,
                "an address such as 127.0.0.1")
        require(isinstance(port, int) and not isinstance(port, bool) and 0 <= port <= 65535,
                "emulator.port", port, "an integer 0..65535 (0 = any free port)")
        require(isinstance(max_line_bytes, int) and 32 <= max_line_bytes <= 1 << 20,
                "emulator.max_line_bytes", max_line_bytes, "an integer 32..1048576")
        self.host, self.tcp_port = host, port
        self.max_line_bytes = max_line_bytes
        self.model = model or lidar_model("URG-04LX")
        self.reboot_resets_timer = bool(reboot_resets_timer)
        self.clock = clock or SimClock()
        self.device = ScipDevice(self.model, self.clock, range_source, scip1=scip1, **device_kw)
        self.faults = FaultInjector(faults)
        self.stats = self.device.stats
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._lock = threading.Lock()
        self._session_stop: threading.Event | None = None
        self._session_thread: threading.Thread | None = None
        self._session_sock: socket.socket | None = None
        self._sent = threading.Condition()  # notified after every message and session end
        self._down_until = -math.inf
        self._listener: socket.socket | None = None
        self.url: str | None = None
        self.pty_path: str | None = None
        self._pty_link: Path | None = None
        self._pty_fds: tuple[int, int] | None = None
        self._pty_down: float | None = None
        self._up_pending = False

    # -- public -----------------------------------------------------------------------
    def serve_tcp(self, host: str | None = None, port: int | None = None) -> str:
        """Listen on ``host:port`` (default the constructor's ``host`` and ``port``; port 0
        = any free port); return ``socket://host:port``.

        One client at a time: while a host holds the session, the next connection waits
        (unanswered) and any further one is closed at once; once the host has hung up,
        the waiting one is served.
        """
        self._check_unused()
        host = self.host if host is None else host
        port = self.tcp_port if port is None else port
        ls = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        ls.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        ls.bind((host, port))
        ls.listen(4)
        ls.settimeout(0.05)
        self._listener = ls
        self.url = f"socket://{host}:{ls.getsockname()[1]}"
        self._spawn(self._accept_loop, "scip-emu-accept")
        return self.url

    def serve_pty(self, link: str | os.PathLike | None = None) -> str:
        """Serve on a new pseudo-terminal in raw mode; return the slave tty path.

        Parameters
        ----------
        link : path, optional
            Also maintain a symlink there to the current slave. After a simulated
            disconnect the device comes back on a *new* pty; only the link stays valid,
            so use it as the port when reconnection matters. If given, it is returned.
        """
        self._check_unused()
        self._pty_link = Path(link) if link is not None else None
        self._open_pty()
        self._spawn(self._pty_loop, "scip-emu-pty")
        return str(self._pty_link) if self._pty_link is not None else str(self.pty_path)

    @property
    def port(self) -> str:
        """What to pass to a driver: the TCP URL, the pty link, or the pty path."""
        if self.url:
            return self.url
        if self._pty_link is not None:
            return str(self._pty_link)
        if self.pty_path:
            return self.pty_path
        raise ParameterError("emulator.port", None, "call serve_tcp() or serve_pty() first")

    def stop(self) -> None:
        """Stop all threads and close every descriptor (idempotent)."""
        self._stop.set()
        if self._session_stop is not None:
            self._session_stop.set()
        for t in self._threads:
            t.join(timeout=5.0)
        if self._session_thread is not None:
            self._session_thread.join(timeout=5.0)
        if self._listener is not None:
            self._listener.close()
            self._listener = None
        self._close_pty()
        if self._pty_link is not None and self._pty_link.is_symlink():
            self._pty_link.unlink()

    def __enter__(self) -> ScipEmulator:
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    def scan_index(self, timestamp_ms: int) -> int:
        """Scan number of an (unwrapped) device timestamp [ms]."""
        return self.device.scan_index(timestamp_ms)

    def wait_for(self, predicate: Callable[[EmulatorStats], bool], timeout: float = 5.0
                 ) -> bool:
        """Block until ``predicate(self.stats)`` holds (checked after every message the
        emulator sends, connection change and session end); False after ``timeout`` [s,
        wall]. For tests: wait on what the device did instead of sleeping."""
        with self._sent:
            return self._sent.wait_for(lambda: predicate(self.stats), timeout)

    def _notify(self) -> None:
        with self._sent:
            self._sent.notify_all()

    def expected_ranges_mm(self, k: int, request: scip.DistanceRequest) -> np.ndarray:
        """Ground truth of scan ``k`` as the device encodes it for ``request``."""
        return self.device.expected_ranges_mm(k, request)

    # -- internals --------------------------------------------------------------------
    def _check_unused(self) -> None:
        require(self.url is None and self.pty_path is None and not self._stop.is_set(),
                "emulator.transport", self.url or self.pty_path, "one serve_*() per emulator")

    def _spawn(self, target, name: str) -> None:
        t = threading.Thread(target=target, name=name, daemon=True)
        self._threads.append(t)
        t.start()

    def _start_session(self, link: _FdLink, stop: threading.Event,
                       on_end: Callable[[], None], new_link: bool = True) -> None:
        with self._lock:
            old_stop, old_thread = self._session_stop, self._session_thread
            if old_stop is not None:
                old_stop.set()
            if old_thread is not None:
                old_thread.join(timeout=5.0)
            if new_link:
                self.device.link_reset()
            self._session_stop = stop
            t = threading.Thread(target=self._session, args=(link, stop, on_end),
                                 name="scip-emu-session", daemon=True)
            self._session_thread = t
            t.start()

    def _session(self, link: _FdLink, stop: threading.Event, on_end: Callable[[], None]) -> None:
        dev = self.device
        clock = self.clock
        buf = bytearray()
        skipping = False  # inside an over-long line: drop bytes up to its end
        try:
            while not stop.is_set() and not self._stop.is_set():
                due = dev.next_due()
                now = clock.now()
                wait = 0.01 if due is None else min(0.01, max(0.0, (due - now) / clock.rate))
                data = link.read(wait)
                if data:
                    buf += data.replace(b"\r\n", b"\n").replace(b"\r", b"\n")
                    while True:
                        i = buf.find(b"\n")
                        if i < 0:
                            if len(buf) > self.max_line_bytes:  # bounded: answer now
                                if not skipping and not self._too_long(link, buf, stop):
                                    return
                                skipping = True
                                buf.clear()
                            break
                        if skipping or i > self.max_line_bytes:
                            if not skipping and not self._too_long(link, buf[:i], stop):
                                return
                            skipping = False
                            del buf[: i + 1]
                            continue
                        line = bytes(buf[:i])
                        del buf[: i + 1]
                        for msg in dev.handle_line(line, clock.now()):
                            if not self._emit(link, msg, False, stop):
                                return
                        if line.strip(b"\r"):  # as ScipDevice counts stats.commands
                            self.stats.commands_answered += 1
                        self._notify()  # the command is processed (wait_for)
                for msg in dev.poll(clock.now()):
                    if not self._emit(link, msg, True, stop):
                        return
        except _LinkClosed:
            pass
        finally:
            on_end()
            self._notify()

    def _too_long(self, link: _FdLink, line: bytes | bytearray, stop: threading.Event) -> bool:
        """Answer an over-long command line with ``0D`` (echo: its first 64 characters,
        non-printable bytes as ``?``); False if the link went down."""
        self.stats.long_lines += 1
        head = bytes(c if 0x20 <= c < 0x7F else 0x3F for c in bytes(line[:64]))
        return self._emit(link, scip.encode_message(head, "0D"), False, stop)

    def _emit(self, link: _FdLink, msg: bytes, is_scan: bool, stop: threading.Event) -> bool:
        """Send one message through the fault layer; False if the link went down."""
        act = self.faults.apply(msg, is_scan)
        st = self.stats
        st.bytes_dropped += act.dropped
        st.bytes_corrupted += act.corrupted
        if act.disconnect_s is not None:
            st.disconnects += 1
            self._down_until = self.clock.now() + act.disconnect_s
            self._go_down(act.disconnect_s)
            return False
        if act.wait_s > 0:
            if act.stalled:
                st.stalls += 1
                st.stall_ends.append(time.monotonic() + act.wait_s / self.clock.rate)
            if not self.clock.sleep_until(self.clock.now() + act.wait_s, stop):
                return False
        link.write(act.data)
        st.messages_sent += 1
        self._notify()
        return True

    def _go_down(self, down_s: float) -> None:
        """Link lost: the device reboots and is reachable again after ``down_s``."""
        self.device.power_on()
        if self.reboot_resets_timer:  # the timer reads 0 when the device is back
            self.device.reset_timer(self.clock.now() + down_s)
        if self._listener is None:  # pty: the pty loop re-creates the terminal
            self._pty_down = down_s
        else:
            self._up_pending = True

    # TCP ----------------------------------------------------------------------------
    def _accept_loop(self) -> None:
        ls = self._listener
        assert ls is not None  # serve_tcp() made it
        queued: socket.socket | None = None  # one host waiting for the session
        try:
            while not self._stop.is_set():
                if self._up_pending and self.clock.now() >= self._down_until:
                    self._up_pending = False
                    self.stats.up_times.append(time.monotonic())
                if queued is not None:
                    if self.clock.now() < self._down_until or _hung_up(queued):
                        queued.close()  # the device went away, or the host gave up
                        queued = None
                    elif not self._session_busy():
                        self._serve(queued)
                        queued = None
                try:
                    conn, _ = ls.accept()
                except TimeoutError:
                    continue
                except OSError:
                    return
                if self.clock.now() < self._down_until:
                    conn.close()  # the device is away: refuse the host
                    continue
                if queued is None and not self._session_busy():
                    self._serve(conn)
                elif queued is None:  # wait until the host holding the session leaves
                    queued = conn
                    self.stats.queued_connections += 1
                    self._notify()
                else:  # one host at a time, one waiting (a real Ethernet URG serves one)
                    self.stats.refused_connections += 1  # counted before the host sees it
                    conn.close()
                    self._notify()
        finally:
            if queued is not None:
                queued.close()

    def _serve(self, conn: socket.socket) -> None:
        if self._up_pending:
            self._up_pending = False
            self.stats.up_times.append(time.monotonic())
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.stats.connections += 1
        stop = threading.Event()
        link = _FdLink(conn.fileno(), stop, sock=conn)
        self._session_sock = conn
        self._start_session(link, stop, conn.close)
        self._notify()

    def _session_busy(self) -> bool:
        """Does a live host hold the TCP session? (False once it has hung up, even if
        the session thread has not noticed yet, e.g. inside a stall.)"""
        t, sock = self._session_thread, self._session_sock
        if t is None or not t.is_alive() or sock is None:
            return False
        return not _hung_up(sock)

    # pty ----------------------------------------------------------------------------
    def _open_pty(self) -> None:
        master, slave = os.openpty()
        tty.setraw(slave)
        self._pty_fds = (master, slave)
        self.pty_path = os.ttyname(slave)
        if self._pty_link is not None:
            tmp = self._pty_link.with_name(self._pty_link.name + ".new")
            if tmp.is_symlink() or tmp.exists():
                tmp.unlink()
            tmp.symlink_to(self.pty_path)
            os.replace(tmp, self._pty_link)

    def _close_pty(self) -> None:
        if self._pty_fds is not None:
            for fd in self._pty_fds:
                try:
                    os.close(fd)
                except OSError:
                    pass
            self._pty_fds = None

    def _pty_loop(self) -> None:
        while not self._stop.is_set():
            stop = threading.Event()
            ended = threading.Event()
            self.stats.connections += 1
            assert self._pty_fds is not None  # serve_pty() opened it
            link = _FdLink(self._pty_fds[0], stop)
            self._start_session(link, stop, ended.set, new_link=False)
            while not ended.wait(0.05):
                if self._stop.is_set():
                    return
            down = self._pty_down
            self._pty_down = None
            if self._stop.is_set():
                return
            self._close_pty()
            if down is None:  # session ended for another reason: keep the device up
                self._open_pty()
                continue
            if not self.clock.sleep_until(self.clock.now() + down, self._stop):
                return
            self._open_pty()
            self.stats.up_times.append(time.monotonic())
