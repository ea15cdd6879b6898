"""Emulated Dynamixel Protocol 2.0 bus: X-series position servos on one line.

The nodding head is pitched by servo 1 and the two mirrors are lifted by servos 2
(left) and 3 (right) by default. Every servo keeps an XM430-like control table
(:data:`nodlidar.dynamixel.CONTROL_TABLE`); motion toward the goal position is an
analytic velocity-limited (or, with a profile acceleration, trapezoidal) profile
evaluated from the shared :class:`~nodlidar.sim.clock.SimClock` when somebody asks,
so there is no integration loop and the servo angle at any simulated time is exact.

The bus is served over a pseudo terminal (:meth:`DxlEmulator.serve_pty`, the slave
path opens like ``/dev/ttyUSB0`` with pyserial or dynamixel-sdk) and/or TCP
(:meth:`DxlEmulator.serve_tcp`, a ``socket://`` URL for ``serial.serial_for_url``).

Modelled: PING, READ, WRITE, REG_WRITE/ACTION, FACTORY_RESET, REBOOT, CLEAR,
SYNC_READ, SYNC_WRITE, FAST_SYNC_READ, BULK_READ, BULK_WRITE, FAST_BULK_READ, broadcast
(PING, WRITE, ACTION, REBOOT, FACTORY_RESET 0x01/0x02), status return level, error
numbers (instruction, CRC, data range, data length, data limit, access, result fail),
EEPROM lock while torque is on, torque gating motion, position limits, moving
flag/status, realtime tick [ms mod 32768]. Instruction semantics follow the ROBOTIS
e-Manual's Protocol 2.0 page and the packet layouts dynamixel-sdk 3.7 sends and parses
(the fast replies: one packet, ``ERR ID DATA CRC`` per servo, each CRC over the frame so
far, unstuffed). REBOOT: torque off, RAM items back to their power-up values, EEPROM kept,
the shaft where it is. FACTORY_RESET: every item back to the servo's
:class:`ServoSpec` values (0xFF also ID 1; 0x01 keeps the ID; 0x02 keeps ID and baud
rate). CLEAR 0x01 (multi-turn) and 0x02 (errors) with the fixed key ``44 58 4C 22``;
refused with result fail while moving. Not modelled: operating modes other than
position control (other modes are stored but still move in position mode), homing
offset, drive-mode reverse, return delay time, baud rate (any baud works),
load/gravity, indirect addresses, control-table backup.

The TCP server listens on loopback unless told otherwise, serves at most
``max_connections`` clients at once (more are closed on accept) and reads at most 4 KiB
at a time into a frame parser that holds at most one maximal frame - a hostile client
costs neither threads nor memory.
"""

from __future__ import annotations

import math
import os
import select
import socket
import threading
import tty
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from nodlidar.dynamixel import (
    BROADCAST_ID,
    CONTROL_TABLE,
    CONTROL_TABLE_SIZE,
    HEADER,
    MAX_ID,
    RAD_PER_TICK,
    RAD_S_PER_VELOCITY_UNIT,
    REALTIME_TICK_MODULO,
    TICKS_PER_REV,
    XM430_W350_MODEL_NUMBER,
    ControlItem,
    CrcError,
    ErrorCode,
    Instruction,
    InstructionPacket,
    PacketParser,
    StatusPacket,
    crc16,
    decode_value,
    encode_value,
    rad_to_ticks,
)
from nodlidar.errors import ParameterError, ProtocolError, require

from .clock import SimClock

__all__ = ["ServoSpec", "DEFAULT_SERVOS", "DxlEmulator", "PROFILE_ACCEL_UNIT_RAD_S2",
           "MAX_TCP_CONNECTIONS"]

PROFILE_ACCEL_UNIT_RAD_S2 = 214.577 * 2.0 * math.pi / 3600.0
"""One unit of profile acceleration (214.577 rev/min^2) in rad/s^2."""

_TICK_S_PER_VEL_UNIT = RAD_S_PER_VELOCITY_UNIT / RAD_PER_TICK
_TICK_S2_PER_ACC_UNIT = PROFILE_ACCEL_UNIT_RAD_S2 / RAD_PER_TICK
_HISTORY = 4096  # motion segments kept per servo for ground-truth queries (~1 MB)
_RAM_START = CONTROL_TABLE["torque_enable"].address  # items below live in EEPROM
_CLEAR_KEY = b"\x44\x58\x4c\x22"  # "DXL\"": CLEAR's fixed parameters after the option
MAX_TCP_CONNECTIONS = 8


@dataclass(frozen=True)
class ServoSpec:
    """Initial configuration of one emulated servo.

    Attributes
    ----------
    id : int
        Bus ID, 0..252.
    name : str
        Label (``"nod"``, ``"mirror_left"``...), for logs and ground truth lookup.
    initial_angle_rad : float
        Shaft angle at power-up [rad], 0 = tick 2048.
    min_angle_rad, max_angle_rad : float
        Position limits [rad] (control items 52/48); goals outside are refused.
    velocity_limit_rad_s : float
        Velocity limit [rad/s] (item 44); also the speed when profile velocity is 0.
    model_number : int
        Reported model number (1020 = XM430-W350).
    firmware_version : int
        Reported firmware version.
    """

    id: int
    name: str = ""
    initial_angle_rad: float = 0.0
    min_angle_rad: float = -math.pi
    max_angle_rad: float = (TICKS_PER_REV - 1 - 2048) * RAD_PER_TICK
    velocity_limit_rad_s: float = 200 * RAD_S_PER_VELOCITY_UNIT
    model_number: int = XM430_W350_MODEL_NUMBER
    firmware_version: int = 46

    def __post_init__(self) -> None:
        require(0 <= self.id <= MAX_ID, "servo.id", self.id, f"0..{MAX_ID}")
        lo, hi = -math.pi, (TICKS_PER_REV - 1 - 2048) * RAD_PER_TICK
        require(
            lo - 1e-9 <= self.min_angle_rad < self.max_angle_rad <= hi + 1e-9,
            "servo.angle_limits_rad",
            (self.min_angle_rad, self.max_angle_rad),
            f"{lo:.4f} <= min < max <= {hi:.4f}",
        )
        require(
            self.min_angle_rad <= self.initial_angle_rad <= self.max_angle_rad,
            "servo.initial_angle_rad",
            self.initial_angle_rad,
            f"within [{self.min_angle_rad:.4f}, {self.max_angle_rad:.4f}]",
        )
        require(
            0 < self.velocity_limit_rad_s <= 1023 * RAD_S_PER_VELOCITY_UNIT,
            "servo.velocity_limit_rad_s",
            self.velocity_limit_rad_s,
            f"(0, {1023 * RAD_S_PER_VELOCITY_UNIT:.3f}]",
        )
        require(
            0 <= self.model_number <= 0xFFFF, "servo.model_number", self.model_number, "0..65535"
        )
        require(
            0 <= self.firmware_version <= 0xFF,
            "servo.firmware_version",
            self.firmware_version,
            "0..255",
        )


DEFAULT_SERVOS = (
    ServoSpec(1, "nod"),
    ServoSpec(2, "mirror_left"),
    ServoSpec(3, "mirror_right"),
)
"""Nod servo (1) and the left/right mirror lift servos (2, 3)."""


class _Segment:
    """Move from ``p0`` at ``t0`` to ``goal`` [ticks]; speed ``v`` [ticks/s], accel ``a``.

    ``a = inf`` gives a constant-velocity ramp; ``v = 0`` holds ``p0``.
    """

    __slots__ = ("t0", "p0", "goal", "v", "a", "ta", "tc", "vpk", "T", "sign")

    def __init__(self, t0: float, p0: float, goal: float, v: float, a: float = math.inf):
        self.t0, self.p0, self.goal = float(t0), float(p0), float(goal)
        d = goal - p0
        self.sign = 1.0 if d >= 0 else -1.0
        dist = abs(d)
        if dist == 0 or v <= 0:
            self.goal = self.p0 if v <= 0 else self.goal
            self.v, self.a, self.ta, self.tc, self.vpk, self.T = 0.0, math.inf, 0.0, 0.0, 0.0, 0.0
            return
        self.v, self.a = float(v), float(a)
        if math.isinf(a):
            self.ta, self.vpk, self.tc = 0.0, self.v, dist / self.v
        elif dist >= v * v / a:
            self.ta, self.vpk = v / a, self.v
            self.tc = (dist - v * v / a) / v
        else:
            self.ta = math.sqrt(dist / a)
            self.vpk = a * self.ta
            self.tc = 0.0
        self.T = 2 * self.ta + self.tc

    @property
    def t_end(self) -> float:
        return self.t0 + self.T

    def position(self, t: np.ndarray) -> np.ndarray:
        tau = np.clip(np.asarray(t, dtype=float) - self.t0, 0.0, self.T)
        if self.T == 0:
            return np.full_like(tau, self.goal)
        if self.ta == 0:
            s = self.vpk * tau
        else:
            a, ta, tc, vpk = self.a, self.ta, self.tc, self.vpk
            s_acc = 0.5 * a * np.minimum(tau, ta) ** 2
            s_cru = vpk * np.clip(tau - ta, 0.0, tc)
            tdec = np.clip(tau - ta - tc, 0.0, ta)
            s_dec = vpk * tdec - 0.5 * a * tdec**2
            s = s_acc + s_cru + s_dec
        return self.p0 + self.sign * s

    def velocity(self, t: float) -> float:
        tau = t - self.t0
        if self.T == 0 or tau <= 0 or tau >= self.T:
            return 0.0
        if self.ta == 0:
            return self.sign * self.vpk
        if tau < self.ta:
            return self.sign * self.a * tau
        if tau < self.ta + self.tc:
            return self.sign * self.vpk
        return self.sign * max(0.0, self.vpk - self.a * (tau - self.ta - self.tc))


class _Servo:
    """State of one emulated servo (not thread-safe; the bus holds the lock)."""

    def __init__(self, spec: ServoSpec, t_now: float):
        self.spec = spec
        self.table = bytearray(CONTROL_TABLE_SIZE)
        defaults = {
            "model_number": spec.model_number,
            "firmware_version": spec.firmware_version,
            "id": spec.id,
            "baud_rate": 1,  # 57600 bps
            "return_delay_time": 250,
            "operating_mode": 3,  # position control
            "protocol_type": 2,
            "secondary_id": 255,
            "moving_threshold": 10,
            "temperature_limit": 80,
            "max_voltage_limit": 160,
            "min_voltage_limit": 95,
            "pwm_limit": 885,
            "current_limit": 1193,
            "velocity_limit": int(round(spec.velocity_limit_rad_s / RAD_S_PER_VELOCITY_UNIT)),
            "max_position_limit": rad_to_ticks(spec.max_angle_rad),
            "min_position_limit": rad_to_ticks(spec.min_angle_rad),
            "shutdown": 52,
            "status_return_level": 2,
            "velocity_i_gain": 1920,
            "velocity_p_gain": 100,
            "position_p_gain": 800,
            "goal_pwm": 885,
            "goal_current": 1193,
            "present_input_voltage": 120,
            "present_temperature": 30,
        }
        for name, value in defaults.items():
            self._set(name, value)
        self.factory = bytes(self.table)  # what FACTORY_RESET / REBOOT restore
        p0 = spec.initial_angle_rad / RAD_PER_TICK + 2048
        self._set("goal_position", int(round(p0)))
        self.history: deque[_Segment] = deque(maxlen=_HISTORY)
        self.history.append(_Segment(t_now, p0, p0, 0.0))
        self.registered: tuple[int, bytes] | None = None
        self.reboots = 0

    # -- table helpers ------------------------------------------------------------
    def _set(self, name: str, value: int) -> None:
        it = CONTROL_TABLE[name]
        self.table[it.address : it.end] = encode_value(value, it.size, it.signed)

    def get(self, name: str, table: bytes | bytearray | None = None) -> int:
        it = CONTROL_TABLE[name]
        src = self.table if table is None else table
        return decode_value(bytes(src[it.address : it.end]), it.signed)

    @property
    def id(self) -> int:
        return self.get("id")

    @property
    def torque(self) -> bool:
        return bool(self.get("torque_enable"))

    @property
    def segment(self) -> _Segment:
        return self.history[-1]

    def position_ticks(self, t: float) -> float:
        return float(self.segment.position(np.asarray(t)))

    # -- dynamics -----------------------------------------------------------------
    def _speed_ticks_s(self) -> tuple[float, float]:
        vlim = self.get("velocity_limit")
        prof = self.get("profile_velocity")
        v_units = vlim if prof == 0 else min(prof, vlim)
        acc = self.get("profile_acceleration")
        a = math.inf if acc == 0 else acc * _TICK_S2_PER_ACC_UNIT
        return v_units * _TICK_S_PER_VEL_UNIT, a

    def _start(self, t: float, goal: float, moving: bool) -> None:
        p = self.position_ticks(t)
        if moving:
            v, a = self._speed_ticks_s()
            seg = _Segment(t, p, goal, v, a)
        else:
            seg = _Segment(t, p, p, 0.0)
        self.history.append(seg)

    def refresh(self, t: float) -> None:
        """Bring the read-only dynamic items up to simulated time ``t``."""
        seg = self.segment
        p = self.position_ticks(t)
        v = seg.velocity(t)
        moving = self.torque and t < seg.t_end
        self._set("present_position", int(round(p)))
        self._set("position_trajectory", int(round(p)))
        v_units = int(round(v / _TICK_S_PER_VEL_UNIT))
        self._set("present_velocity", v_units)
        self._set("velocity_trajectory", v_units)
        self._set("moving", 1 if moving else 0)
        in_pos = abs(p - self.get("goal_position")) <= 1.0
        status = (1 if in_pos else 0) | (2 if moving else 0)
        if moving:
            status |= 0x10 if self.segment.ta == 0 else 0x30  # rectangular / trapezoidal
        self._set("moving_status", status)
        self._set("realtime_tick", int(math.floor(t * 1000.0)) % REALTIME_TICK_MODULO)
        self._set("registered_instruction", 1 if self.registered else 0)

    def power_up(self, t: float) -> None:
        """REBOOT: torque off (the shaft stays where it is), RAM items back to their
        power-up values, the goal at the present position; EEPROM kept."""
        p = self.position_ticks(t)
        self.table[_RAM_START:] = self.factory[_RAM_START:]
        self._set("goal_position", int(round(p)))
        self.history.append(_Segment(t, p, p, 0.0))
        self.registered = None
        self.reboots += 1

    def factory_reset(self, t: float, option: int) -> None:
        """FACTORY_RESET ``option`` (0xFF all, 0x01 all but the ID, 0x02 all but ID and
        baud rate), then a power-up."""
        keep = {"id": self.id, "baud_rate": self.get("baud_rate")}
        self.table[:_RAM_START] = self.factory[:_RAM_START]
        if option == 0xFF:
            self._set("id", 1)  # the factory ID of every X-series servo
        else:
            self._set("id", keep["id"])
            if option == 0x02:
                self._set("baud_rate", keep["baud_rate"])
        self.power_up(t)

    def moving(self, t: float) -> bool:
        return self.torque and t < self.segment.t_end

    # -- access -------------------------------------------------------------------
    def read(self, t: float, address: int, length: int) -> tuple[int, bytes]:
        if address + length > CONTROL_TABLE_SIZE:
            return ErrorCode.ACCESS, b""
        self.refresh(t)
        return ErrorCode.NONE, bytes(self.table[address : address + length])

    def check_write(self, address: int, data: bytes) -> tuple[int, bytearray | None]:
        """Validate a write; return (error, new table) without applying it."""
        end = address + len(data)
        if end > CONTROL_TABLE_SIZE or not data:
            return ErrorCode.ACCESS, None
        touched = [it for it in CONTROL_TABLE.values() if it.address < end and it.end > address]
        torque_on = self.torque
        for it in touched:
            if not it.writable:
                return ErrorCode.ACCESS, None
            if it.eeprom and torque_on:
                return ErrorCode.ACCESS, None
        new = bytearray(self.table)
        new[address:end] = data
        for it in touched:
            err = self._validate(it, new)
            if err:
                return err, None
        return ErrorCode.NONE, new

    def _validate(self, it: ControlItem, new: bytearray) -> int:
        v = self.get(it.name, new)
        ranges = {
            "id": (0, MAX_ID),
            "baud_rate": (0, 7),
            "return_delay_time": (0, 254),
            "drive_mode": (0, 13),
            "operating_mode": (0, 16),
            "protocol_type": (1, 2),
            "velocity_limit": (0, 1023),
            "max_position_limit": (0, TICKS_PER_REV - 1),
            "min_position_limit": (0, TICKS_PER_REV - 1),
            "torque_enable": (0, 1),
            "led": (0, 1),
            "status_return_level": (0, 2),
            "profile_acceleration": (0, 32767),
            "profile_velocity": (0, 32767),
        }
        if it.name in ranges:
            lo, hi = ranges[it.name]
            if not lo <= v <= hi:
                return ErrorCode.DATA_RANGE
        if it.name == "operating_mode" and v not in (0, 1, 3, 4, 5, 16):
            return ErrorCode.DATA_RANGE
        if it.name == "goal_position":
            lo = self.get("min_position_limit", new)
            hi = self.get("max_position_limit", new)
            if not lo <= v <= hi:
                return ErrorCode.DATA_LIMIT
        return ErrorCode.NONE

    def apply(self, t: float, address: int, length: int, new: bytearray) -> None:
        """Commit a validated table and react to torque and goal changes.

        Writing the goal position (even the same value) with torque on starts a new
        move from the present position at the present profile velocity/acceleration;
        profile changes take effect at the next goal, as on the real servo.
        """
        old_torque = self.torque
        self.table[:] = new
        torque = self.torque
        goal_it = CONTROL_TABLE["goal_position"]
        goal_touched = address < goal_it.end and address + length > goal_it.address
        if torque and not old_torque:
            # torque on: hold the present position (as the real servo does)
            p = self.position_ticks(t)
            self._set("goal_position", int(round(p)))
            self._start(t, p, moving=False)
        elif old_torque and not torque:
            self._start(t, 0.0, moving=False)  # stop where it is
        elif torque and goal_touched:
            self._start(t, float(self.get("goal_position")), moving=True)


def _bulk_blocks(p: bytes, *, with_data: bool):
    """``(id, address, length)`` blocks of a BULK_READ, or ``(id, address, data)`` of a
    BULK_WRITE; nothing if the parameters do not split into whole blocks."""
    blocks: list[tuple[int, int, Any]] = []
    k = 0
    while k < len(p):
        if k + 5 > len(p):
            return []
        sid, address, length = p[k], decode_value(p[k + 1:k + 3]), decode_value(p[k + 3:k + 5])
        k += 5
        if with_data:
            if length == 0 or k + length > len(p):
                return []
            blocks.append((sid, address, bytes(p[k:k + length])))
            k += length
        else:
            blocks.append((sid, address, length))
    return blocks


class _FastReply:
    """The single status packet of a FAST_SYNC_READ / FAST_BULK_READ (ID 0xFE): per
    servo ``ERR ID DATA CRC``, each CRC over the frame up to it (the last one is the
    packet's), not byte-stuffed - the layout dynamixel-sdk parses."""

    def __init__(self, frame: bytes):
        self.frame = frame

    @classmethod
    def build(cls, blocks: list[tuple[int, int, bytes]]) -> _FastReply:
        length = 1 + sum(len(d) + 4 for _, _, d in blocks)  # instruction + blocks (+ CRC)
        frame = bytearray(HEADER + bytes([BROADCAST_ID, length & 0xFF, length >> 8,
                                          Instruction.STATUS]))
        for err, sid, data in blocks:
            frame += bytes([err, sid]) + data
            crc = crc16(frame)
            frame += bytes([crc & 0xFF, crc >> 8])
        return cls(bytes(frame))

    def encode(self) -> bytes:
        return self.frame


class DxlEmulator:
    """A Dynamixel Protocol 2.0 bus with several emulated X-series servos.

    Parameters
    ----------
    clock : SimClock
        Shared simulated clock [s]; motion and the realtime tick follow it.
    servos : iterable of ServoSpec
        Servos on the bus (default: nod 1, left mirror 2, right mirror 3).

    Notes
    -----
    No I/O happens until :meth:`serve_pty` / :meth:`serve_tcp`; :meth:`close` (or
    leaving the ``with`` block) stops every server thread. Packets can also be
    handled in-process with :meth:`handle_packet` / :meth:`handle_bytes`.
    """

    def __init__(self, clock: SimClock, servos: Iterable[ServoSpec] = DEFAULT_SERVOS):
        specs = list(servos)
        ids = [s.id for s in specs]
        require(len(set(ids)) == len(ids), "emulator.servo_ids", ids, "unique IDs")
        require(len(ids) > 0, "emulator.servos", ids, "at least one servo")
        self.clock = clock
        t = clock.now()
        self._servos: dict[int, _Servo] = {s.id: _Servo(s, t) for s in specs}
        self._by_name = {s.name: s.id for s in specs if s.name}
        self._lock = threading.RLock()
        self._handled = threading.Condition(self._lock)
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._closers: list = []
        self.packets_handled = 0
        self.crc_errors = 0
        self.connections = 0
        """TCP clients being served now."""
        self.refused_connections = 0
        """TCP clients closed on accept because ``max_connections`` were being served."""

    # -- ground truth -------------------------------------------------------------
    @property
    def servo_ids(self) -> list[int]:
        """IDs currently on the bus, ascending."""
        with self._lock:
            return sorted(self._servos)

    def _servo(self, servo: int | str) -> _Servo:
        sid = self._by_name.get(servo, servo) if isinstance(servo, str) else servo
        # the ID may have been changed over the bus: look up by spec too
        with self._lock:
            if sid in self._servos:
                return self._servos[sid]
            for s in self._servos.values():
                if s.spec.id == sid:
                    return s
        raise ParameterError(
            "servo", servo, f"one of IDs {self.servo_ids} or names {sorted(self._by_name)}"
        )

    def joint_angle(self, servo: int | str, t: ArrayLike | None = None) -> float | np.ndarray:
        """True shaft angle [rad] of a servo at simulated time(s) ``t`` [s].

        Parameters
        ----------
        servo : int or str
            Bus ID or name (``"nod"``, ``"mirror_left"``, ``"mirror_right"``).
        t : float or array_like, optional
            Simulated time(s) [s]; default now. Past times are answered from the
            motion history (the last 4096 commanded moves); future times assume no
            further commands.

        Returns
        -------
        float or ndarray
            Angle [rad], 0 at tick 2048, same shape as ``t``.
        """
        s = self._servo(servo)
        with self._lock:
            tt = np.asarray(self.clock.now() if t is None else t, dtype=float)
            # only the segments from the one in force at the earliest query on (recent
            # queries - every simulated scan - cost a few segments, not the history)
            t_min = float(np.min(tt)) if tt.size else math.inf
            segs = []
            for g in reversed(s.history):
                segs.append(g)
                if g.t0 <= t_min:
                    break
            segs.reverse()
        starts = [g.t0 for g in segs]
        out = np.empty(tt.shape, dtype=float)
        flat_t = tt.reshape(-1)
        flat_o = out.reshape(-1)
        idx = np.searchsorted(np.asarray(starts), flat_t, side="right") - 1
        idx = np.clip(idx, 0, len(segs) - 1)
        for k in np.unique(idx):
            m = idx == k
            flat_o[m] = segs[k].position(flat_t[m])
        out = (out - 2048.0) * RAD_PER_TICK
        return float(out) if out.ndim == 0 else out

    def joint_angles(self, t: float | None = None) -> dict[int, float]:
        """True angle [rad] of every servo at simulated time ``t`` (default now)."""
        t = self.clock.now() if t is None else t
        # a scalar time: each angle is already a float (float() for the type checker)
        return {sid: float(self.joint_angle(sid, t)) for sid in self.servo_ids}

    def set_angle(self, servo: int | str, angle_rad: float) -> None:
        """Force a servo shaft to ``angle_rad`` now (as if moved by hand, torque off)."""
        s = self._servo(servo)
        with self._lock:
            t = self.clock.now()
            p = angle_rad / RAD_PER_TICK + 2048
            s.history.append(_Segment(t, p, p, 0.0))
            s._set("torque_enable", 0)

    # -- protocol -----------------------------------------------------------------
    def handle_packet(self, pkt: InstructionPacket) -> list[StatusPacket]:
        """Execute one instruction; return the status packets the bus would send."""
        with self._handled:
            self.packets_handled += 1
            t = self.clock.now()
            out = self._dispatch(pkt, t)
            self._handled.notify_all()
            return out

    def wait_handled(self, n: int, timeout_s: float = 10.0) -> bool:
        """Block until ``n`` packets have been handled in all (wall ``timeout_s``); for
        tests that send an instruction without a reply (broadcast) and must know it has
        taken effect before they move a manual clock."""
        with self._handled:
            return self._handled.wait_for(lambda: self.packets_handled >= n, timeout_s)

    def _reply(self, s: _Servo, error: int, params: bytes = b"", *, is_read: bool = False):
        level = s.get("status_return_level")
        if level == 0 or (level == 1 and not is_read):
            return []
        return [StatusPacket(s.id, error, params if not error else b"")]

    def _targets(self, dev_id: int) -> list[_Servo]:
        if dev_id == BROADCAST_ID:
            return [self._servos[k] for k in sorted(self._servos)]
        s = self._servos.get(dev_id)
        return [s] if s is not None else []

    def _do_write(self, s: _Servo, t: float, address: int, data: bytes) -> int:
        err, new = s.check_write(address, data)
        if err or new is None:  # new is None only with an error
            return err
        old_id = s.id
        s.apply(t, address, len(data), new)
        if s.id != old_id:
            self._servos.pop(old_id)
            self._servos[s.id] = s
        return ErrorCode.NONE

    def _dispatch(self, pkt: InstructionPacket, t: float) -> list[StatusPacket]:
        ins, p, bc = pkt.instruction, pkt.params, pkt.id == BROADCAST_ID
        targets = self._targets(pkt.id)
        if ins == Instruction.PING:
            out = []
            for s in targets:
                info = encode_value(s.get("model_number"), 2) + bytes([s.get("firmware_version")])
                out.append(StatusPacket(s.id, 0, info))  # ping always answers
            return out
        if not targets:
            return []
        if ins in (Instruction.READ,):
            if bc:
                return []
            s = targets[0]
            if len(p) != 4:
                return self._reply(s, ErrorCode.DATA_LENGTH, is_read=True)
            address, length = decode_value(p[:2]), decode_value(p[2:])
            err, data = s.read(t, address, length)
            return self._reply(s, err, data, is_read=True)
        if ins in (Instruction.WRITE, Instruction.REG_WRITE):
            out = []
            for s in targets:
                if len(p) < 3:
                    err = ErrorCode.DATA_LENGTH
                elif ins == Instruction.WRITE:
                    err = self._do_write(s, t, decode_value(p[:2]), p[2:])
                else:
                    err, _ = s.check_write(decode_value(p[:2]), p[2:])
                    if not err:
                        s.registered = (decode_value(p[:2]), bytes(p[2:]))
                if not bc:
                    out += self._reply(s, err)
            return out
        if ins == Instruction.ACTION:
            out = []
            for s in targets:
                err = ErrorCode.NONE
                if s.registered is not None:
                    address, data = s.registered
                    s.registered = None
                    err = self._do_write(s, t, address, data)
                if not bc:
                    out += self._reply(s, err)
            return out
        if ins == Instruction.SYNC_READ:
            if not bc or len(p) < 5:
                return []
            address, length = decode_value(p[:2]), decode_value(p[2:4])
            out = []
            for sid in p[4:]:
                srv = self._servos.get(sid)
                if srv is None:
                    continue
                err, data = srv.read(t, address, length)
                out += self._reply(srv, err, data, is_read=True)
            return out
        if ins == Instruction.SYNC_WRITE:
            if not bc or len(p) < 6:
                return []
            address, length = decode_value(p[:2]), decode_value(p[2:4])
            body = p[4:]
            if length == 0 or len(body) % (length + 1):
                return []
            for k in range(0, len(body), length + 1):
                srv = self._servos.get(body[k])
                if srv is not None:
                    self._do_write(srv, t, address, body[k + 1 : k + 1 + length])
            return []
        if ins == Instruction.BULK_WRITE:
            if bc:
                for sid, address, data in _bulk_blocks(p, with_data=True):
                    srv = self._servos.get(sid)
                    if srv is not None:
                        self._do_write(srv, t, address, data)
            return []
        if ins in (Instruction.BULK_READ, Instruction.FAST_BULK_READ):
            if not bc:
                return []
            reads = [(sid, a, n) for sid, a, n in _bulk_blocks(p, with_data=False)]
            return self._bulk_read(t, reads, fast=ins == Instruction.FAST_BULK_READ)
        if ins == Instruction.FAST_SYNC_READ:
            if not bc or len(p) < 5:
                return []
            address, length = decode_value(p[:2]), decode_value(p[2:4])
            return self._bulk_read(t, [(sid, address, length) for sid in p[4:]], fast=True)
        if ins == Instruction.REBOOT:
            out = []
            for s in targets:
                if not bc:
                    out += self._reply(s, ErrorCode.NONE)  # answered before restarting
                s.power_up(t)
            return out
        if ins == Instruction.FACTORY_RESET:
            option = p[0] if len(p) == 1 else None
            out = []
            for s in targets:
                if bc:
                    # a broadcast may not reset IDs (they would all become 1)
                    if option in (0x01, 0x02):
                        self._rekeyed(s, lambda s=s: s.factory_reset(t, option))
                    continue
                if option is None:
                    out += self._reply(s, ErrorCode.DATA_LENGTH)
                elif option not in (0x01, 0x02, 0xFF):
                    out += self._reply(s, ErrorCode.DATA_RANGE)
                else:
                    out += self._reply(s, ErrorCode.NONE)
                    self._rekeyed(s, lambda s=s: s.factory_reset(t, option))
            return out
        if ins == Instruction.CLEAR:
            out = []
            for s in targets:
                if len(p) != 5:
                    err = ErrorCode.DATA_LENGTH
                elif p[0] not in (0x01, 0x02) or p[1:] != _CLEAR_KEY:
                    err = ErrorCode.DATA_RANGE
                elif s.moving(t):
                    err = ErrorCode.RESULT_FAIL  # only a stopped servo may be cleared
                else:
                    err = ErrorCode.NONE
                    if p[0] == 0x02:
                        s._set("hardware_error_status", 0)
                    # 0x01: the emulated position never leaves one turn: nothing to reset
                if not bc:
                    out += self._reply(s, err)
            return out
        # unknown / unsupported instruction
        if bc:
            return []
        return [StatusPacket(targets[0].id, ErrorCode.INSTRUCTION)]

    def _rekeyed(self, s: _Servo, change) -> None:
        """Run ``change`` (which may change the servo's ID) and file the servo under its ID."""
        old = s.id
        change()
        if s.id != old:
            self._servos.pop(old, None)
            self._servos[s.id] = s

    def _bulk_read(self, t: float, reads, *, fast: bool) -> list:
        """Replies to (FAST_)SYNC/BULK_READ of ``(id, address, length)``: one status per
        servo in the order asked, or (fast) one packet carrying every servo's block."""
        out: list = []
        blocks = []
        for sid, address, length in reads:
            s = self._servos.get(sid)
            if s is None:
                continue  # absent: no reply (the client times out or sees a short packet)
            err, data = s.read(t, address, length)
            if fast:
                blocks.append((err, s.id, data if not err else bytes(length)))
            else:
                out += self._reply(s, err, data, is_read=True)
        if fast and blocks:
            out.append(_FastReply.build(blocks))
        return out

    def handle_bytes(self, data: bytes, parser: PacketParser) -> bytes:
        """Feed received bytes through ``parser``; return the reply bytes to send."""
        parser.feed(data)
        out = bytearray()
        while True:
            try:
                pkt = parser.next_packet()
            except CrcError as e:
                with self._lock:
                    self.crc_errors += 1
                    s = self._servos.get(e.packet_id)
                    if s is not None:
                        out += b"".join(r.encode() for r in self._reply(s, ErrorCode.CRC))
                continue
            except ProtocolError:
                continue
            if pkt is None:
                break
            if isinstance(pkt, StatusPacket):
                continue  # another device talking (or our own echo): ignore
            for r in self.handle_packet(pkt):
                out += r.encode()
        return bytes(out)

    # -- transports ---------------------------------------------------------------
    def _spawn(self, target, name: str) -> None:
        th = threading.Thread(target=target, name=name, daemon=True)
        self._threads.append(th)
        th.start()

    def serve_pty(self) -> str:
        """Serve the bus on a new pseudo terminal; return the slave path (raw mode).

        The path opens like a USB-serial adapter (``serial.Serial(path)``,
        ``dynamixel_sdk.PortHandler(path)``); any baud rate is accepted.
        """
        master, slave = os.openpty()
        tty.setraw(slave)
        os.set_blocking(master, False)
        path = os.ttyname(slave)
        self._closers += [lambda: os.close(master), lambda: os.close(slave)]

        def run() -> None:
            parser = PacketParser()
            while not self._stop.is_set():
                try:
                    r, _, _ = select.select([master], [], [], 0.05)
                    if not r:
                        continue
                    data = os.read(master, 4096)
                except (OSError, ValueError):
                    if self._stop.is_set():
                        return
                    continue
                if not data:
                    continue
                reply = self.handle_bytes(data, parser)
                if reply:
                    try:
                        os.write(master, reply)
                    except (BlockingIOError, OSError):
                        pass  # nobody is reading: drop, as a real line would

        self._spawn(run, f"dxl-pty-{path}")
        return path

    def serve_tcp(self, host: str = "127.0.0.1", port: int = 0, *,
                  max_connections: int = MAX_TCP_CONNECTIONS) -> str:
        """Serve the bus on TCP; return a ``socket://host:port`` URL for pyserial.

        Parameters
        ----------
        host : str
            Interface to listen on: loopback by default (``0.0.0.0`` exposes the bus to
            the network - a choice the caller makes).
        port : int
            TCP port; 0 picks a free one.
        max_connections : int
            Clients served at once (each its own frame parser and thread); a client
            beyond that is closed as soon as it is accepted (``refused_connections``
            counts them).
        """
        require(isinstance(max_connections, int) and 1 <= max_connections <= 1024,
                "max_connections", max_connections, "1..1024")
        require(isinstance(port, int) and 0 <= port <= 65535, "servo port", port,
                "0..65535 (0 = any free port)")
        srv = socket.create_server((host, port))  # OSError (in use, no such address): as is
        srv.settimeout(0.05)
        self._closers.append(srv.close)
        host_, port_ = srv.getsockname()[:2]
        active = threading.BoundedSemaphore(max_connections)

        def serve_conn(conn: socket.socket) -> None:
            parser = PacketParser()  # holds at most one maximal frame (MAX_LENGTH)
            try:
                conn.settimeout(0.05)
                conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                with conn:
                    while not self._stop.is_set():
                        try:
                            data = conn.recv(4096)
                        except TimeoutError:
                            continue
                        except OSError:
                            return
                        if not data:
                            return
                        reply = self.handle_bytes(data, parser)
                        if reply:
                            try:
                                conn.sendall(reply)
                            except OSError:
                                return
            finally:
                with self._lock:
                    self.connections -= 1
                active.release()

        def accept_loop() -> None:
            while not self._stop.is_set():
                try:
                    conn, _ = srv.accept()
                except TimeoutError:
                    continue
                except OSError:
                    return
                if not active.acquire(blocking=False):
                    with self._lock:
                        self.refused_connections += 1
                    conn.close()
                    continue
                with self._lock:
                    self.connections += 1
                # finished connection threads leave the list (no growth over many clients)
                self._threads = [th for th in self._threads if th.is_alive()]
                self._spawn(lambda c=conn: serve_conn(c), f"dxl-tcp-conn-{port_}")

        self._spawn(accept_loop, f"dxl-tcp-{port_}")
        return f"socket://{host_}:{port_}"

    def close(self) -> None:
        """Stop every server thread and release the pty/socket."""
        self._stop.set()
        for th in list(self._threads):
            th.join(timeout=2.0)
        for c in self._closers:
            try:
                c()
            except OSError:
                pass
        self._closers.clear()
        self._threads.clear()
        self._stop = threading.Event()

    def __enter__(self) -> DxlEmulator:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
