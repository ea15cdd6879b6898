"""Servo driver for the nodding head and the mirror lifts (Dynamixel Protocol 2.0).

Runs over pyserial's ``serial_for_url``, so a tty (``/dev/ttyUSB0``), the bus
emulator's pty path or its ``socket://127.0.0.1:PORT`` URL all work.

* :class:`DynamixelBus` - transactions, ping/discover, items by name, angles in
  radians and rates in rad/s (ticks only at this edge).
* :class:`NodProfile` + :class:`NodController` - the linear nod ramp: the head sweeps
  back and forth between two pitch limits at a constant rate, driven with goal
  position + profile velocity.
* :class:`MirrorLiftProfile` + :class:`MirrorLift` - lift / reset the mirrors.
* :class:`PositionSampler` - background present-position sampling into a bounded
  :class:`SampleBuffer`, each sample stamped with host time and the servo's realtime
  tick; :func:`interpolate_angle` then gives every lidar beam its own nod angle.

Times come from ``time_source`` (default :func:`time.monotonic`); with the emulator
pass ``clock.now`` so samples are in simulated seconds. Poll periods and sleeps are
wall-clock seconds.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import TYPE_CHECKING, Literal, NamedTuple

import numpy as np
import serial

from nodlidar.dynamixel import (
    BROADCAST_ID,
    CONTROL_TABLE,
    MAX_ID,
    RAD_PER_TICK,
    CrcError,
    ErrorCode,
    Instruction,
    InstructionPacket,
    PacketParser,
    StatusPacket,
    decode_value,
    encode_value,
    item,
    ping_packet,
    rad_s_to_velocity_raw,
    rad_to_ticks,
    read_packet,
    sync_read_packet,
    sync_write_packet,
    ticks_to_rad,
    velocity_raw_to_rad_s,
    write_packet,
)
from nodlidar.errors import DeviceError, ParameterError, ProtocolError, require

# the pure servo-angle math lives in servo_angles (no pyserial); re-exported here
from .servo_angles import (
    MAX_ANGLE_RAD,
    MAX_RATE_RAD_S,
    MIN_ANGLE_RAD,
    MirrorLiftProfile,
    NodProfile,
    interpolate_angle,
    lift_profiles,
    unwrap_tick_ms,
)

if TYPE_CHECKING:
    from ..design import Design

__all__ = [
    "NOD_ID",
    "BusLineError",
    "MIRROR_LEFT_ID",
    "MIRROR_RIGHT_ID",
    "PingInfo",
    "ServoState",
    "DynamixelBus",
    "NodProfile",
    "NodController",
    "MirrorLiftProfile",
    "MirrorLift",
    "LIFT_ARRIVAL_RAD",
    "Samples",
    "SampleBuffer",
    "PositionSampler",
    "interpolate_angle",
    "lift_profiles",
    "unwrap_tick_ms",
]

NOD_ID = 1
MIRROR_LEFT_ID = 2
MIRROR_RIGHT_ID = 3

try:  # pyserial's tty calls raise termios.error (not an OSError) on a vanished pty
    from termios import error as _TermiosError
except ImportError:  # pragma: no cover - Windows
    class _TermiosError(Exception):  # type: ignore[no-redef]
        pass

_LINE_ERRORS = (serial.SerialException, OSError, _TermiosError)


class BusLineError(DeviceError):
    """The servo bus's line itself failed (port vanished, closed, I/O error): retrying
    will not help."""


_MIN_ANGLE = MIN_ANGLE_RAD
_MAX_ANGLE = MAX_ANGLE_RAD
_MAX_RATE = MAX_RATE_RAD_S
# READ 120..135 in one go: realtime tick, moving, moving status, pwm, current,
# present velocity, present position.
_STATE_ADDR, _STATE_LEN = 120, 16


class PingInfo(NamedTuple):
    """Answer to a PING: servo ID, model number, firmware version."""

    id: int
    model_number: int
    firmware_version: int


class ServoState(NamedTuple):
    """One consistent snapshot of a servo (a single READ).

    Attributes
    ----------
    host_time_s : float
        Time source [s] at the middle of the transaction.
    tick_ms : int
        Servo realtime tick [ms], wraps at 32768.
    moving : bool
        Servo "moving" flag.
    velocity_rad_s : float
        Present velocity [rad/s].
    angle_rad : float
        Present position [rad] (0 at tick 2048).
    """

    host_time_s: float
    tick_ms: int
    moving: bool
    velocity_rad_s: float
    angle_rad: float


def _error_name(err: int) -> str:
    n = err & 0x7F
    try:
        name = ErrorCode(n).name.lower()
    except ValueError:
        name = f"error {n}"
    return name + (" + hardware alert" if err & 0x80 else "")


class DynamixelBus:
    """A Protocol 2.0 bus on a serial line.

    Parameters
    ----------
    url : str
        Anything ``serial.serial_for_url`` opens: a tty path, a pty path, ``socket://``.
    baudrate : int
        Line speed [bit/s] (ignored by pty/socket transports).
    timeout_s : float
        Wall-clock time [s] to wait for a status packet.
    retries : int
        Extra attempts after a timeout or damaged reply.
    time_source : callable
        Returns the time [s] used to stamp states and samples, and for the controller
        timeouts; pass the simulator clock's ``now`` when running on the emulator.

    Notes
    -----
    Thread-safe: one lock serialises transactions, so the nod controller, the
    sampler and the mirror lift may share one bus. Nothing is opened until
    :meth:`open` / ``with``.
    """

    def __init__(
        self,
        url: str,
        *,
        baudrate: int = 57600,
        timeout_s: float = 0.1,
        retries: int = 2,
        time_source: Callable[[], float] = time.monotonic,
    ):
        require(isinstance(url, str) and url != "", "bus.url", url, "a tty path or URL")
        require(baudrate > 0, "bus.baudrate", baudrate, "> 0")
        require(timeout_s > 0, "bus.timeout_s", timeout_s, "> 0")
        require(retries >= 0, "bus.retries", retries, ">= 0")
        self.url = url
        self.baudrate = int(baudrate)
        self.timeout_s = float(timeout_s)
        self.retries = int(retries)
        self.time_source = time_source
        self._ser: serial.SerialBase | None = None
        self._parser = PacketParser()
        self._lock = threading.RLock()

    # -- connection ---------------------------------------------------------------
    def open(self) -> DynamixelBus:
        """Open the line (idempotent)."""
        with self._lock:
            if self._ser is None:
                try:
                    self._ser = serial.serial_for_url(
                        self.url, baudrate=self.baudrate, timeout=0.002
                    )
                    self._ser.reset_input_buffer()
                except (*_LINE_ERRORS, ValueError) as e:
                    if self._ser is not None:
                        try:
                            self._ser.close()
                        except _LINE_ERRORS:
                            pass
                        self._ser = None
                    raise BusLineError(f"bus.url = {self.url!r} cannot be opened: "
                                       f"{e or type(e).__name__}") from e
        return self

    def close(self) -> None:
        """Close the line (idempotent)."""
        with self._lock:
            if self._ser is not None:
                try:
                    self._ser.close()
                finally:
                    self._ser = None

    @property
    def is_open(self) -> bool:
        return self._ser is not None

    def __enter__(self) -> DynamixelBus:
        return self.open()

    def __exit__(self, *exc) -> None:
        self.close()

    # -- transactions -------------------------------------------------------------
    def _receive(self, deadline: float, want: int | None,
                 accept: Callable[[StatusPacket], bool] | None = None) -> list[StatusPacket]:
        """Read status packets until ``want`` arrived (None: until the deadline); packets
        ``accept`` refuses (a late reply to an earlier attempt) are dropped."""
        ser = self._ser
        assert ser is not None
        got: list[StatusPacket] = []
        while want is None or len(got) < want:
            for pkt in self._parser.packets(skip_bad=False):
                if isinstance(pkt, StatusPacket) and (accept is None or accept(pkt)):
                    got.append(pkt)
            if want is not None and len(got) >= want:
                break
            if time.monotonic() >= deadline:
                break
            data = ser.read(max(1, ser.in_waiting))
            if data:
                self._parser.feed(data)
        return got

    def transact(
        self, packet: InstructionPacket, expect: int | None = 1,
        accept: Callable[[StatusPacket], bool] | None = None,
    ) -> tuple[list[StatusPacket], float]:
        """Send one instruction and collect its replies.

        Parameters
        ----------
        packet : InstructionPacket
            Instruction to send.
        expect : int or None
            Number of status packets to wait for (0: none, e.g. broadcast writes;
            None: everything until the timeout, e.g. broadcast ping).
        accept : callable, optional
            Which status packets answer this instruction; others (a late reply to an
            earlier attempt that timed out) are dropped.

        Returns
        -------
        replies : list of StatusPacket
        host_time_s : float
            Time source [s] halfway between sending and the last reply.

        Raises
        ------
        DeviceError
            No (complete) reply after all retries, or the line failed.
        """
        frame = packet.encode()
        try:
            name = Instruction(packet.instruction).name
        except ValueError:  # an instruction this module has no name for
            name = f"instruction 0x{packet.instruction:02X}"
        what = f"{name} to id {packet.id}"
        last: Exception | None = None
        with self._lock:
            if self._ser is None:
                raise BusLineError(f"bus.url = {self.url!r} is not open; call open() first")
            for _ in range(self.retries + 1):
                try:
                    self._ser.reset_input_buffer()
                    self._parser.clear()
                    t0 = self.time_source()
                    self._ser.write(frame)
                    if expect == 0:
                        return [], t0
                    got = self._receive(time.monotonic() + self.timeout_s, expect, accept)
                    t1 = self.time_source()
                except CrcError as e:
                    last = e
                    continue
                except ProtocolError as e:  # pragma: no cover - defensive
                    last = e
                    continue
                except _LINE_ERRORS as e:
                    raise BusLineError(f"bus.url = {self.url!r} failed during {what}: "
                                       f"{e or type(e).__name__}") from e
                if expect is None:
                    return got, 0.5 * (t0 + t1)
                if len(got) >= expect:
                    # a late reply to an earlier (timed-out) attempt reaches the line
                    # before this one's: the device answers in order, so ours are last
                    return got[-expect:], 0.5 * (t0 + t1)
                last = None
            reason = f" ({last})" if last else ""
            raise DeviceError(
                f"servo reply to {what} missing after {self.retries + 1} attempt(s) of "
                f"{self.timeout_s} s{reason}; allowed: a status packet within bus.timeout_s"
            )

    def _check(self, st: StatusPacket, servo_id: int, what: str) -> StatusPacket:
        if st.id != servo_id:
            raise DeviceError(f"servo {servo_id}: reply to {what} came from id {st.id}")
        if st.error & 0x7F:
            raise DeviceError(f"servo {servo_id}: {what} refused with {_error_name(st.error)}")
        return st

    # -- raw access ---------------------------------------------------------------
    def ping(self, servo_id: int) -> PingInfo:
        """PING one servo; raises :class:`DeviceError` if it does not answer."""
        _check_id(servo_id)
        (st,), _ = self.transact(ping_packet(servo_id), accept=_reply_of(servo_id, 3))
        self._check(st, servo_id, "PING")
        if len(st.params) < 3:
            raise DeviceError(f"servo {servo_id}: PING reply has {len(st.params)} params, not 3")
        return PingInfo(st.id, decode_value(st.params[:2]), st.params[2])

    def discover(self, ids: Iterable[int] | None = None) -> list[PingInfo]:
        """Find servos: broadcast PING (``ids=None``) or PING each of ``ids``.

        Returns the servos that answered, sorted by ID.
        """
        if ids is None:
            replies, _ = self.transact(ping_packet(BROADCAST_ID), expect=None)
            found = {
                st.id: PingInfo(st.id, decode_value(st.params[:2]), st.params[2])
                for st in replies
                if len(st.params) >= 3 and not st.error & 0x7F
            }
            return [found[k] for k in sorted(found)]
        out = []
        with self._lock:  # no other thread sees the temporary retries = 0
            saved = self.retries
            try:
                self.retries = 0
                for i in ids:
                    try:
                        out.append(self.ping(i))
                    except DeviceError:
                        pass
            finally:
                self.retries = saved
        return sorted(out)

    def read_bytes(self, servo_id: int, address: int, length: int) -> tuple[bytes, float]:
        """READ raw bytes; return them and the transaction time [s]."""
        _check_id(servo_id)
        (st,), t = self.transact(read_packet(servo_id, address, length),
                                 accept=_reply_of(servo_id, length))
        self._check(st, servo_id, f"READ {length} B @ {address}")
        if len(st.params) != length:
            raise DeviceError(
                f"servo {servo_id}: READ @ {address} returned {len(st.params)} B, not {length}"
            )
        return st.params, t

    def write_bytes(self, servo_id: int, address: int, data: bytes) -> None:
        """WRITE raw bytes (``servo_id=254``: broadcast, no reply awaited)."""
        if servo_id == BROADCAST_ID:
            self.transact(write_packet(servo_id, address, data), expect=0)
            return
        _check_id(servo_id)
        (st,), _ = self.transact(write_packet(servo_id, address, data),
                                 accept=_reply_of(servo_id, 0))
        self._check(st, servo_id, f"WRITE {data.hex(' ')} @ {address}")

    def read(self, servo_id: int, name: str) -> int:
        """Read a control-table item by name (raw integer value)."""
        it = item(name)
        data, _ = self.read_bytes(servo_id, it.address, it.size)
        return decode_value(data, it.signed)

    def write(self, servo_id: int, name: str, value: int) -> None:
        """Write a control-table item by name (raw integer value)."""
        it = item(name)
        try:
            self.write_bytes(servo_id, it.address, encode_value(value, it.size, it.signed))
        except DeviceError as e:
            raise DeviceError(f"servo {servo_id}: {name} = {value} refused: {e}") from e

    def sync_read(self, name: str, ids: Sequence[int]) -> dict[int, int]:
        """SYNC_READ one item from several servos; returns ``{id: raw value}``."""
        it = item(name)
        replies, _ = self.transact(sync_read_packet(it.address, it.size, list(ids)), len(ids))
        out = {}
        for st in replies:
            self._check(st, st.id, f"SYNC_READ {name}")
            out[st.id] = decode_value(st.params, it.signed)
        missing = set(ids) - set(out)
        if missing:
            raise DeviceError(f"servos {sorted(missing)} did not answer SYNC_READ {name}")
        return out

    def sync_write(self, name: str, values: Mapping[int, int]) -> None:
        """SYNC_WRITE one item to several servos (``{id: raw value}``, no reply)."""
        it = item(name)
        data = {i: encode_value(v, it.size, it.signed) for i, v in values.items()}
        self.transact(sync_write_packet(it.address, it.size, data), expect=0)

    # -- SI helpers ---------------------------------------------------------------
    def set_torque(self, servo_id: int, on: bool) -> None:
        """Enable (hold/move) or disable (free) a servo."""
        self.write(servo_id, "torque_enable", 1 if on else 0)

    def torque(self, servo_id: int) -> bool:
        """True if torque is enabled."""
        return bool(self.read(servo_id, "torque_enable"))

    def set_goal_angle(self, servo_id: int, angle_rad: float) -> None:
        """Command a goal angle [rad] (0 = tick 2048)."""
        require(
            _MIN_ANGLE <= angle_rad <= _MAX_ANGLE,
            "servo.goal_angle_rad",
            angle_rad,
            f"[{_MIN_ANGLE:.4f}, {_MAX_ANGLE:.4f}] and within the servo's position limits",
        )
        self.write(servo_id, "goal_position", rad_to_ticks(angle_rad))

    def goal_angle(self, servo_id: int) -> float:
        """Commanded goal angle [rad]."""
        return ticks_to_rad(self.read(servo_id, "goal_position"))

    def present_angle(self, servo_id: int) -> float:
        """Present angle [rad]."""
        return ticks_to_rad(self.read(servo_id, "present_position"))

    def present_angles(self, ids: Sequence[int]) -> dict[int, float]:
        """Present angles [rad] of several servos (one SYNC_READ)."""
        return {i: ticks_to_rad(v) for i, v in self.sync_read("present_position", ids).items()}

    def set_profile_velocity(self, servo_id: int, rate_rad_s: float) -> float:
        """Set the profile velocity [rad/s]; return the rate actually set (quantised).

        0 means "as fast as the velocity limit allows".
        """
        require(
            0 <= rate_rad_s <= _MAX_RATE,
            "servo.profile_velocity_rad_s",
            rate_rad_s,
            f"[0, {_MAX_RATE:.3f}] rad/s",
        )
        raw = rad_s_to_velocity_raw(rate_rad_s)
        if rate_rad_s > 0:
            raw = max(raw, 1)
        self.write(servo_id, "profile_velocity", raw)
        return velocity_raw_to_rad_s(raw)

    def present_velocity(self, servo_id: int) -> float:
        """Present velocity [rad/s]."""
        return velocity_raw_to_rad_s(self.read(servo_id, "present_velocity"))

    def is_moving(self, servo_id: int) -> bool:
        """The servo's moving flag."""
        return bool(self.read(servo_id, "moving"))

    def read_state(self, servo_id: int) -> ServoState:
        """Realtime tick, moving flag, velocity and angle in one READ."""
        data, t = self.read_bytes(servo_id, _STATE_ADDR, _STATE_LEN)

        def field(name: str) -> int:
            it = CONTROL_TABLE[name]
            off = it.address - _STATE_ADDR
            return decode_value(data[off : off + it.size], it.signed)

        return ServoState(
            host_time_s=t,
            tick_ms=field("realtime_tick"),
            moving=bool(field("moving")),
            velocity_rad_s=velocity_raw_to_rad_s(field("present_velocity")),
            angle_rad=ticks_to_rad(field("present_position")),
        )


def _reply_of(servo_id: int, n_params: int) -> Callable[[StatusPacket], bool]:
    """Accepts the status packet of ``servo_id`` with ``n_params`` parameters (or an error,
    which carries none): anything else on the line is a late reply to an earlier attempt."""
    return lambda st: st.id == servo_id and (len(st.params) == n_params or bool(st.error & 0x7F))


def _check_id(servo_id: int) -> None:
    require(
        isinstance(servo_id, int) and 0 <= servo_id <= MAX_ID,
        "servo.id",
        servo_id,
        f"0..{MAX_ID}",
    )


# -- nod ramp ---------------------------------------------------------------------


class NodController:
    """Drive the nod servo through the :class:`NodProfile` ramp in a background thread.

    The servo first moves to ``lower`` (at ``approach_rate_rad_s``), then the goal
    alternates between ``upper`` and ``lower`` with the profile velocity set to the
    nod rate, so the servo's own velocity profile makes the linear ramp; the goal is
    flipped when the present angle is within ``tolerance_rad`` of it.

    Parameters
    ----------
    bus : DynamixelBus
        Open bus (shared with the sampler is fine).
    profile : NodProfile
        Pitch limits and rate.
    servo_id : int
        Nod servo ID.
    tolerance_rad : float
        Arrival tolerance [rad].
    poll_interval_s : float
        Wall-clock polling period [s].
    approach_rate_rad_s : float or None
        Rate for the initial move to ``lower`` (default: the nod rate).
    stall_timeout_s : float
        If a ramp takes longer than its nominal time plus this [time-source s] and the
        servo has not come closer to the goal for this long, the controller stops with
        a :class:`DeviceError`.
    """

    def __init__(
        self,
        bus: DynamixelBus,
        profile: NodProfile,
        *,
        servo_id: int = NOD_ID,
        tolerance_rad: float = 2.5 * RAD_PER_TICK,
        poll_interval_s: float = 0.002,
        approach_rate_rad_s: float | None = None,
        stall_timeout_s: float = 2.0,
    ):
        _check_id(servo_id)
        require(tolerance_rad > 0, "nod.tolerance_rad", tolerance_rad, "> 0")
        require(poll_interval_s >= 0, "nod.poll_interval_s", poll_interval_s, ">= 0")
        require(stall_timeout_s > 0, "nod.stall_timeout_s", stall_timeout_s, "> 0")
        if approach_rate_rad_s is not None:
            require(
                0 < approach_rate_rad_s <= _MAX_RATE,
                "nod.approach_rate_rad_s",
                approach_rate_rad_s,
                f"(0, {_MAX_RATE:.3f}]",
            )
        self.bus = bus
        self.profile = profile
        self.servo_id = servo_id
        self.tolerance_rad = float(tolerance_rad)
        self.poll_interval_s = float(poll_interval_s)
        self.approach_rate_rad_s = approach_rate_rad_s or profile.rate_rad_s
        self.stall_timeout_s = float(stall_timeout_s)
        self.effective_rate_rad_s: float | None = None
        self.sweeps = 0
        self.turns: deque[tuple[float, float]] = deque(maxlen=10_000)
        """(time [s], new goal [rad]) each time the goal is flipped."""
        self.error: BaseException | None = None
        self.read_errors = 0
        """Polls that got no valid reply (each after the bus's own retries)."""
        self.max_missed_polls = 5
        self.last_state: ServoState | None = None
        """The servo state the controller read last (tests on a manual clock wait on it)."""
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._cond = threading.Condition()

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def start(self) -> NodController:
        """Start nodding (returns immediately)."""
        require(not self.running, "nod.state", "running", "stopped before start()")
        self._stop.clear()
        self.error = None
        self._thread = threading.Thread(target=self._run, name="nod-controller", daemon=True)
        self._thread.start()
        return self

    def stop(self, *, torque_off: bool = False) -> None:
        """Stop nodding (the servo holds its angle unless ``torque_off``).

        Raises
        ------
        DeviceError
            If the controller thread had failed.
        """
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        if torque_off and self.bus.is_open:
            self.bus.set_torque(self.servo_id, False)
        if self.error is not None:
            err, self.error = self.error, None
            raise DeviceError(f"nod controller failed: {err}") from err

    def __enter__(self) -> NodController:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def wait_sweeps(self, n: int, timeout_s: float = 10.0) -> bool:
        """Block until ``n`` ramps are complete (wall-clock ``timeout_s``)."""
        with self._cond:
            return (
                self._cond.wait_for(
                    lambda: self.sweeps >= n or self.error is not None or self._stop.is_set(),
                    timeout=timeout_s,
                )
                and self.sweeps >= n
            )

    def _move(self, goal: float, nominal_s: float) -> bool:
        """Go to ``goal``; True when reached, False if stopped."""
        bus, sid = self.bus, self.servo_id
        t_before = bus.time_source()
        bus.set_goal_angle(sid, goal)
        t_cmd = 0.5 * (t_before + bus.time_source())
        self.turns.append((t_cmd, goal))
        deadline = t_cmd + nominal_s + self.stall_timeout_s
        misses = 0
        best = math.inf
        while not self._stop.is_set():
            try:
                st = bus.read_state(sid)
            except BusLineError:
                raise
            except DeviceError:
                # one unanswered poll (a busy host, a glitch) is not a stalled servo; the
                # stall deadline below still ends a ramp that never arrives
                misses += 1
                self.read_errors += 1
                if misses > self.max_missed_polls:
                    raise
                continue
            misses = 0
            self.last_state = st
            dist = abs(st.angle_rad - goal)
            if dist <= self.tolerance_rad:
                return True
            if dist < best - self.tolerance_rad:
                # still closing in: a late start (a retried goal write, a busy host) is not
                # a stall; a servo that stops short is one stall_timeout_s later
                best = dist
                deadline = max(deadline, st.host_time_s + self.stall_timeout_s)
            if st.host_time_s > deadline:
                raise DeviceError(
                    f"servo {sid}: nod goal {goal:.4f} rad not reached (at "
                    f"{st.angle_rad:.4f} rad, no progress for {self.stall_timeout_s:g} s after "
                    f"the nominal {nominal_s:.2f} s)"
                )
            if self.poll_interval_s:
                self._stop.wait(self.poll_interval_s)
        return False

    def _run(self) -> None:
        p, bus, sid = self.profile, self.bus, self.servo_id
        try:
            bus.set_torque(sid, True)
            start = bus.present_angle(sid)
            bus.set_profile_velocity(sid, self.approach_rate_rad_s)
            if not self._move(p.lower_rad, abs(start - p.lower_rad) / self.approach_rate_rad_s):
                return
            self.effective_rate_rad_s = bus.set_profile_velocity(sid, p.rate_rad_s)
            nominal = p.amplitude_rad / self.effective_rate_rad_s
            goal = p.upper_rad
            while not self._stop.is_set():
                if not self._move(goal, nominal):
                    return
                with self._cond:
                    self.sweeps += 1
                    self._cond.notify_all()
                goal = p.lower_rad if goal == p.upper_rad else p.upper_rad
        except Exception as e:  # reported by stop()
            self.error = e
        finally:
            with self._cond:
                self._cond.notify_all()


# -- mirror lift ------------------------------------------------------------------


Side = Literal["left", "right", "both"]


#: How close to its goal a mirror servo counts as arrived [rad] (``MirrorLift.wait``): three
#: encoder ticks. A capture starts sampling once the mirrors are this close, so its first
#: samples may still be closing the last ticks.
LIFT_ARRIVAL_RAD = 3 * RAD_PER_TICK


class MirrorLift:
    """Lift or reset (deploy) the left/right mirrors.

    Parameters
    ----------
    bus : DynamixelBus
        Open bus.
    left, right : MirrorLiftProfile, optional
        Angles of each side (``right`` defaults to ``left``).
    design : Design, optional
        Solved design: the profiles of the sides not given come from
        :func:`~nodlidar.runtime.servo_angles.lift_profiles` (its lift angle, the sign each
        side's servo turns). One of ``left`` or ``design`` is needed: a lift angle with no
        design would be a guess, and a wrong sign swings the glass towards the lidar.
    left_id, right_id : int
        Servo IDs.
    tolerance_rad : float
        Arrival tolerance [rad] when waiting.
    """

    def __init__(
        self,
        bus: DynamixelBus,
        left: MirrorLiftProfile | None = None,
        right: MirrorLiftProfile | None = None,
        *,
        design: Design | None = None,
        left_id: int = MIRROR_LEFT_ID,
        right_id: int = MIRROR_RIGHT_ID,
        tolerance_rad: float = LIFT_ARRIVAL_RAD,
    ):
        _check_id(left_id)
        _check_id(right_id)
        require(left_id != right_id, "mirror.right_id", right_id, f"!= left_id ({left_id})")
        require(tolerance_rad > 0, "mirror.tolerance_rad", tolerance_rad, "> 0")
        if design is not None:
            dl, dr = lift_profiles(design)
            left, right = left or dl, right or dr
        if left is None:
            raise ParameterError("mirror.left", None,
                                 "a MirrorLiftProfile or design= (MirrorLiftProfile.for_design)")
        self.bus = bus
        self.profiles = {"left": left, "right": right or left}
        self.ids = {"left": left_id, "right": right_id}
        self.tolerance_rad = float(tolerance_rad)

    def _sides(self, side: Side) -> list[str]:
        if side == "both":
            return ["left", "right"]
        if side in ("left", "right"):
            return [side]
        raise ParameterError("mirror.side", side, "'left', 'right' or 'both'")

    def _go(self, side: Side, attr: str, wait: bool, timeout_s: float) -> None:
        targets = {}
        for s in self._sides(side):
            prof, sid = self.profiles[s], self.ids[s]
            self.bus.set_torque(sid, True)
            self.bus.set_profile_velocity(sid, prof.rate_rad_s)
            goal = getattr(prof, attr)
            self.bus.set_goal_angle(sid, goal)
            targets[s] = goal
        if wait:
            self.wait(targets, timeout_s)

    def lift(self, side: Side = "both", *, wait: bool = True, timeout_s: float = 10.0) -> None:
        """Move the mirror(s) to the lifted angle; optionally wait [time-source s]."""
        self._go(side, "lifted_rad", wait, timeout_s)

    def reset(self, side: Side = "both", *, wait: bool = True, timeout_s: float = 10.0) -> None:
        """Move the mirror(s) back to the deployed angle; optionally wait."""
        self._go(side, "deployed_rad", wait, timeout_s)

    def angles(self) -> dict[str, float]:
        """Present angle [rad] of each side."""
        by_id = self.bus.present_angles([self.ids["left"], self.ids["right"]])
        return {s: by_id[i] for s, i in self.ids.items()}

    def wait(self, targets: Mapping[str, float], timeout_s: float = 10.0) -> None:
        """Block until each side is within tolerance of ``targets[side]`` [rad].

        Raises
        ------
        DeviceError
            Not reached within ``timeout_s`` [time-source s].
        """
        t_end = self.bus.time_source() + timeout_s
        while True:
            now = self.angles()
            if all(abs(now[s] - g) <= self.tolerance_rad for s, g in targets.items()):
                return
            if self.bus.time_source() > t_end:
                raise DeviceError(
                    f"mirror.angles = {now} did not reach {dict(targets)} within {timeout_s} s"
                )
            time.sleep(0.002)

    def state(self) -> dict[str, str]:
        """``"lifted"``, ``"deployed"`` or ``"between"`` for each side."""
        out = {}
        for s, a in self.angles().items():
            p = self.profiles[s]
            if abs(a - p.lifted_rad) <= self.tolerance_rad:
                out[s] = "lifted"
            elif abs(a - p.deployed_rad) <= self.tolerance_rad:
                out[s] = "deployed"
            else:
                out[s] = "between"
        return out


# -- sampling ---------------------------------------------------------------------


class Samples(NamedTuple):
    """Arrays of position samples (oldest first).

    Attributes
    ----------
    host_time_s : ndarray of float
        Time source [s] at the middle of each READ.
    tick_ms : ndarray of int64
        Servo realtime tick [ms] (wraps at 32768; see :func:`unwrap_tick_ms`).
    angle_rad : ndarray of float
        Present angle [rad].
    """

    host_time_s: np.ndarray
    tick_ms: np.ndarray
    angle_rad: np.ndarray


class SampleBuffer:
    """Thread-safe buffer of timestamped samples (oldest first).

    Parameters
    ----------
    capacity : int or None
        ``None`` (default): every sample is kept until :meth:`prune` drops it - nothing
        is lost, and memory stays bounded when the consumer prunes behind what it has
        used (the live capture prunes behind the oldest scan not yet assembled). An int:
        a ring of the newest ``capacity`` samples; older ones are overwritten
        (``dropped`` counts them).
    """

    def __init__(self, capacity: int | None = None):
        if capacity is not None:
            require(capacity >= 2, "samples.capacity", capacity, ">= 2 (or None: unbounded)")
        self.capacity = None if capacity is None else int(capacity)
        size = self.capacity or 1024
        self._t = np.empty(size)
        self._tick = np.empty(size, dtype=np.int64)
        self._a = np.empty(size)
        self._lo = 0  # unbounded mode: first live sample in the arrays
        self._hi = 0  # unbounded mode: one past the last
        self._n = 0  # total appended
        self._pruned = 0
        self._lock = threading.Lock()

    @property
    def total(self) -> int:
        """Samples appended so far (kept, pruned or dropped)."""
        return self._n

    @property
    def pruned(self) -> int:
        """Samples removed by :meth:`prune` so far."""
        return self._pruned

    def append(self, host_time_s: float, tick_ms: int, angle_rad: float) -> None:
        """Add one sample."""
        with self._lock:
            if self.capacity is not None:
                i = self._n % self.capacity
            else:
                if self._hi == len(self._t):
                    self._make_room()
                i = self._hi
                self._hi += 1
            self._t[i], self._tick[i], self._a[i] = host_time_s, tick_ms, angle_rad
            self._n += 1

    def _make_room(self) -> None:
        # move the live samples to the front; grow only when more than half is live,
        # so a pruned buffer reuses its arrays (amortised O(1) per append)
        live = self._hi - self._lo
        size = len(self._t) * 2 if live > len(self._t) // 2 else len(self._t)
        for name in ("_t", "_tick", "_a"):
            old = getattr(self, name)
            new = np.empty(size, dtype=old.dtype) if size != len(old) else old
            new[:live] = old[self._lo:self._hi]
            setattr(self, name, new)
        self._lo, self._hi = 0, live

    def __len__(self) -> int:
        if self.capacity is None:
            return self._hi - self._lo
        return min(self._n, self.capacity)

    @property
    def last_time_s(self) -> float:
        """Time [s] of the newest sample (-inf when empty)."""
        with self._lock:
            if self._n == 0 or len(self) == 0:
                return -math.inf
            i = self._hi - 1 if self.capacity is None else (self._n - 1) % self.capacity
            return float(self._t[i])

    @property
    def dropped(self) -> int:
        """Samples overwritten so far (ring mode; always 0 when unbounded)."""
        return 0 if self.capacity is None else max(0, self._n - self.capacity)

    def _copy(self) -> Samples:
        if self.capacity is None:
            sl = slice(self._lo, self._hi)
            return Samples(self._t[sl].copy(), self._tick[sl].copy(), self._a[sl].copy())
        n = min(self._n, self.capacity)
        idx = np.arange(self._n - n, self._n) % self.capacity
        return Samples(self._t[idx].copy(), self._tick[idx].copy(), self._a[idx].copy())

    def snapshot(self, since_s: float | None = None) -> Samples:
        """Copy of the buffered samples (only those with time >= ``since_s`` if given)."""
        with self._lock:
            out = self._copy()
        if since_s is not None:
            k = int(np.searchsorted(out.host_time_s, since_s, side="left"))
            out = Samples(out.host_time_s[k:], out.tick_ms[k:], out.angle_rad[k:])
        return out

    def snapshot_around(self, t_s: float) -> Samples:
        """The samples an interpolation at times >= ``t_s`` [s] needs: from the last
        sample at or before ``t_s`` (with any samples sharing its time) to the newest.

        Interpolating on this snapshot gives the same angles at ``t >= t_s`` as on the
        whole buffer (see :func:`interpolate_angle`; duplicate times keep the first).
        """
        with self._lock:
            out = self._copy()
        k = _first_needed(out.host_time_s, t_s)
        return Samples(out.host_time_s[k:], out.tick_ms[k:], out.angle_rad[k:])

    def prune(self, before_s: float) -> int:
        """Drop the samples no interpolation at times >= ``before_s`` [s] needs (keeps the
        last sample at or before it); returns how many were dropped. Unbounded mode only
        (a ring forgets by itself)."""
        if self.capacity is not None:
            return 0
        with self._lock:
            k = _first_needed(self._t[self._lo:self._hi], before_s)
            self._lo += k
            self._pruned += k
        return k

    def clear(self) -> None:
        with self._lock:
            self._n = self._lo = self._hi = self._pruned = 0


def _first_needed(t: np.ndarray, t_s: float) -> int:
    """Index of the first sample an interpolation at ``t >= t_s`` needs in sorted ``t``."""
    j = int(np.searchsorted(t, t_s, side="right")) - 1
    if j <= 0:
        return 0
    return int(np.searchsorted(t, t[j], side="left"))


class PositionSampler:
    """Sample a servo's present position in a background thread.

    Parameters
    ----------
    bus : DynamixelBus
        Open bus (shared with controllers is fine).
    servo_id : int
        Servo to sample (default: the nod servo).
    period_s : float
        Wall-clock period between READs [s] (0: as fast as the bus allows).
    capacity : int or None
        ``None`` (default): keep every sample until the consumer prunes it
        (:meth:`prune`); an int: a ring of the newest ``capacity`` samples.

    Notes
    -----
    A failed READ is counted in ``errors`` (last one in ``last_error``) and sampling
    goes on; a line that is gone (the port vanished, the bus was closed) ends the thread
    with the :class:`DeviceError` in :attr:`error`, for the owner to report once (the
    session raises it from the capture). Samples are in :attr:`buffer`.
    """

    def __init__(
        self,
        bus: DynamixelBus,
        servo_id: int = NOD_ID,
        *,
        period_s: float = 0.002,
        capacity: int | None = None,
    ):
        _check_id(servo_id)
        require(period_s >= 0, "sampler.period_s", period_s, ">= 0")
        self.bus = bus
        self.servo_id = servo_id
        self.period_s = float(period_s)
        self.buffer = SampleBuffer(capacity)
        self.errors = 0
        self.last_error: Exception | None = None
        self.error: DeviceError | None = None
        """Set when sampling stopped for good (the line failed)."""
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def start(self) -> PositionSampler:
        """Start sampling (returns immediately)."""
        require(not self.running, "sampler.state", "running", "stopped before start()")
        self._stop.clear()
        self.error = None
        self._thread = threading.Thread(target=self._run, name="dxl-sampler", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop sampling and join the thread."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None

    def __enter__(self) -> PositionSampler:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def samples(self, since_s: float | None = None) -> Samples:
        """Snapshot of the buffer (see :meth:`SampleBuffer.snapshot`)."""
        return self.buffer.snapshot(since_s)

    def prune(self, before_s: float) -> int:
        """Forget samples no interpolation at times >= ``before_s`` [s] needs."""
        return self.buffer.prune(before_s)

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                st = self.bus.read_state(self.servo_id)
                self.buffer.append(st.host_time_s, st.tick_ms, st.angle_rad)
            except DeviceError as e:
                self.errors += 1
                self.last_error = e
                if isinstance(e, BusLineError) or not self.bus.is_open:
                    self.error = e  # the line is gone: retrying only repeats the error
                    return
            except Exception as e:  # never a thread traceback: the owner reports it
                self.error = DeviceError(f"servo {self.servo_id} sampler failed: {e!r}")
                return
            if self.period_s:
                self._stop.wait(self.period_s)
