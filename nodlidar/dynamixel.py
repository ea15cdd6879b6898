"""Dynamixel Protocol 2.0 codec: CRC-16, packets, byte stuffing, control table, units.

Pure functions and data, no I/O. Used by the bus emulator
(:mod:`nodlidar.sim.dxl_emulator`) and by the runtime driver
(:mod:`nodlidar.runtime.actuators`).

Packet layout (all multi-byte fields little endian)::

    FF FF FD 00 | ID | LEN_L LEN_H | INST | PARAM... | CRC_L CRC_H

``LEN`` counts the bytes after itself (instruction, stuffed parameters and CRC).
A status packet is an ordinary packet with instruction ``0x55`` whose first
parameter is the error byte. Inside instruction + parameters every occurrence of
``FF FF FD`` is sent as ``FF FF FD FD`` (byte stuffing) so that the header pattern
never appears in a body; the CRC is computed over the packet as sent (stuffed),
header included.

Units: raw Dynamixel ticks appear only here and at the protocol edge. Positions are
4096 ticks per revolution with tick 2048 at 0 rad; velocities are 0.229 rev/min per
unit; the realtime tick is milliseconds modulo 32768.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import overload

import numpy as np
from numpy.typing import ArrayLike

from .errors import ParameterError, ProtocolError, require

__all__ = [
    "HEADER",
    "BROADCAST_ID",
    "MAX_ID",
    "Instruction",
    "ErrorCode",
    "ERROR_ALERT_BIT",
    "CrcError",
    "crc16",
    "stuff",
    "unstuff",
    "InstructionPacket",
    "StatusPacket",
    "Packet",
    "encode_packet",
    "decode_packet",
    "PacketParser",
    "ping_packet",
    "read_packet",
    "write_packet",
    "reg_write_packet",
    "action_packet",
    "sync_read_packet",
    "sync_write_packet",
    "ControlItem",
    "CONTROL_TABLE",
    "CONTROL_TABLE_SIZE",
    "EEPROM_END",
    "XM430_W350_MODEL_NUMBER",
    "item",
    "encode_value",
    "decode_value",
    "TICKS_PER_REV",
    "POSITION_CENTRE_TICKS",
    "RAD_PER_TICK",
    "VELOCITY_UNIT_RPM",
    "RAD_S_PER_VELOCITY_UNIT",
    "REALTIME_TICK_MODULO",
    "ticks_to_rad",
    "rad_to_ticks",
    "velocity_raw_to_rad_s",
    "rad_s_to_velocity_raw",
]

HEADER = b"\xff\xff\xfd\x00"
"""Protocol 2.0 packet header (``FF FF FD`` + reserved ``00``)."""
BROADCAST_ID = 0xFE
MAX_ID = 252
"""Largest ID a device may have (``0xFD``-``0xFF`` are reserved/broadcast)."""
MAX_LENGTH = 1024
"""Largest ``LEN`` field this codec accepts; longer claims are treated as garbage."""

_STUFF_PATTERN = b"\xff\xff\xfd"


class Instruction(enum.IntEnum):
    """Protocol 2.0 instruction codes."""

    PING = 0x01
    READ = 0x02
    WRITE = 0x03
    REG_WRITE = 0x04
    ACTION = 0x05
    FACTORY_RESET = 0x06
    REBOOT = 0x08
    CLEAR = 0x10
    STATUS = 0x55
    SYNC_READ = 0x82
    SYNC_WRITE = 0x83
    FAST_SYNC_READ = 0x8A
    BULK_READ = 0x92
    BULK_WRITE = 0x93
    FAST_BULK_READ = 0x9A


class ErrorCode(enum.IntEnum):
    """Error numbers in the low 7 bits of a status packet's error byte."""

    NONE = 0x00
    RESULT_FAIL = 0x01
    INSTRUCTION = 0x02
    CRC = 0x03
    DATA_RANGE = 0x04
    DATA_LENGTH = 0x05
    DATA_LIMIT = 0x06
    ACCESS = 0x07


ERROR_ALERT_BIT = 0x80
"""Bit 7 of the error byte: the device has a hardware error (see item 70)."""


class CrcError(ProtocolError):
    """A complete frame arrived whose CRC does not match.

    Attributes
    ----------
    packet_id : int
        The ID field of the damaged frame (a device may answer with a CRC error).
    """

    def __init__(self, packet_id: int, got: int, expected: int):
        self.packet_id = packet_id
        self.got = got
        self.expected = expected
        super().__init__(
            f"packet.crc = 0x{got:04X} is invalid for id {packet_id}; "
            f"allowed: 0x{expected:04X} (CRC-16/0x8005 of the frame)"
        )


# -- CRC-16 -----------------------------------------------------------------------


def _make_crc_table(poly: int = 0x8005) -> tuple[int, ...]:
    table = []
    for byte in range(256):
        reg = byte << 8
        for _ in range(8):
            reg = ((reg << 1) ^ poly) if reg & 0x8000 else (reg << 1)
            reg &= 0xFFFF
        table.append(reg)
    return tuple(table)


_CRC_TABLE = _make_crc_table()


def crc16(data: bytes | bytearray | memoryview, crc: int = 0) -> int:
    """CRC-16 of the Dynamixel Protocol 2.0 (polynomial 0x8005, init 0, MSB first).

    Parameters
    ----------
    data : bytes-like
        Bytes to checksum (the whole frame up to, not including, the CRC field).
    crc : int
        Running value, to continue a previous call.

    Returns
    -------
    int
        16-bit CRC; sent low byte first.
    """
    table = _CRC_TABLE
    for b in bytes(data):
        crc = ((crc << 8) & 0xFFFF) ^ table[((crc >> 8) ^ b) & 0xFF]
    return crc


# -- byte stuffing ----------------------------------------------------------------


def stuff(body: bytes) -> bytes:
    """Insert ``FD`` after every ``FF FF FD`` of an unstuffed instruction+parameter body."""
    if _STUFF_PATTERN not in body:
        return bytes(body)
    out = bytearray()
    for b in body:
        out.append(b)
        if b == 0xFD and len(out) >= 3 and out[-2] == 0xFF and out[-3] == 0xFF:
            # An inserted FD is never FF, so checking the output is the same as
            # checking the original body.
            out.append(0xFD)
    return bytes(out)


def unstuff(body: bytes) -> bytes:
    """Undo :func:`stuff`.

    Raises
    ------
    ProtocolError
        If ``FF FF FD`` appears not followed by the stuffing ``FD``.
    """
    if _STUFF_PATTERN not in body:
        return bytes(body)
    out = bytearray()
    i, n = 0, len(body)
    while i < n:
        b = body[i]
        out.append(b)
        i += 1
        if b == 0xFD and len(out) >= 3 and out[-2] == 0xFF and out[-3] == 0xFF:
            if i < n and body[i] == 0xFD:
                i += 1
            else:
                raise ProtocolError(
                    f"packet.body = {body.hex(' ')} is invalid; allowed: every FF FF FD "
                    "inside a body followed by a stuffing FD"
                )
    return bytes(out)


# -- packets ----------------------------------------------------------------------


def _check_id(name: str, value: int, allow_broadcast: bool) -> None:
    ok = isinstance(value, int) and (
        0 <= value <= MAX_ID or (allow_broadcast and value == BROADCAST_ID)
    )
    require(ok, name, value, f"0..{MAX_ID}" + (" or 254 (broadcast)" if allow_broadcast else ""))


@dataclass(frozen=True)
class InstructionPacket:
    """An instruction sent by the controller.

    Attributes
    ----------
    id : int
        Target device ID, 0..252 or 254 (broadcast).
    instruction : int
        Instruction code (:class:`Instruction`), anything but ``STATUS``.
    params : bytes
        Unstuffed parameters.
    """

    id: int
    instruction: int
    params: bytes = b""

    def __post_init__(self) -> None:
        _check_id("packet.id", self.id, allow_broadcast=True)
        require(
            isinstance(self.instruction, int)
            and 0 <= self.instruction <= 0xFF
            and self.instruction != Instruction.STATUS,
            "packet.instruction",
            self.instruction,
            "0..255 except 0x55 (status)",
        )
        object.__setattr__(self, "params", bytes(self.params))

    def encode(self) -> bytes:
        """Wire bytes (stuffed, with CRC)."""
        return encode_packet(self.id, self.instruction, self.params)


@dataclass(frozen=True)
class StatusPacket:
    """A status (reply) packet sent by a device.

    Attributes
    ----------
    id : int
        ID of the replying device, 0..252.
    error : int
        Error byte: error number (:class:`ErrorCode`) in bits 0-6, alert in bit 7.
    params : bytes
        Unstuffed parameters after the error byte.
    """

    id: int
    error: int = 0
    params: bytes = b""
    instruction: int = field(default=Instruction.STATUS, init=False)

    def __post_init__(self) -> None:
        _check_id("status.id", self.id, allow_broadcast=False)
        require(
            isinstance(self.error, int) and 0 <= self.error <= 0xFF,
            "status.error",
            self.error,
            "0..255",
        )
        object.__setattr__(self, "params", bytes(self.params))

    @property
    def error_code(self) -> ErrorCode | int:
        """Error number without the alert bit (an :class:`ErrorCode` when known)."""
        n = self.error & 0x7F
        try:
            return ErrorCode(n)
        except ValueError:
            return n

    @property
    def alert(self) -> bool:
        """True when the device flags a hardware error."""
        return bool(self.error & ERROR_ALERT_BIT)

    def encode(self) -> bytes:
        """Wire bytes (stuffed, with CRC)."""
        return encode_packet(self.id, Instruction.STATUS, bytes([self.error]) + self.params)


Packet = InstructionPacket | StatusPacket


def encode_packet(dev_id: int, instruction: int, params: bytes = b"") -> bytes:
    """Build one wire frame.

    Parameters
    ----------
    dev_id : int
        ID field (0..252, 254).
    instruction : int
        Instruction byte (``0x55`` for a status; its error byte is then ``params[0]``).
    params : bytes
        Unstuffed parameters.

    Returns
    -------
    bytes
        Header, ID, length, stuffed body and CRC.
    """
    body = stuff(bytes([instruction]) + bytes(params))
    length = len(body) + 2
    require(length <= MAX_LENGTH, "packet.length", length, f"<= {MAX_LENGTH}")
    frame = HEADER + bytes([dev_id, length & 0xFF, length >> 8]) + body
    crc = crc16(frame)
    return frame + bytes([crc & 0xFF, crc >> 8])


def _packet_from_fields(dev_id: int, body: bytes) -> Packet:
    instruction, params = body[0], body[1:]
    if instruction == Instruction.STATUS:
        if not params:
            raise ProtocolError(
                f"status.length = 0 is invalid for id {dev_id}; allowed: >= 1 (error byte)"
            )
        if dev_id > MAX_ID:
            raise ProtocolError(f"status.id = {dev_id} is invalid; allowed: 0..{MAX_ID}")
        return StatusPacket(dev_id, params[0], params[1:])
    if dev_id > MAX_ID and dev_id != BROADCAST_ID:
        raise ProtocolError(f"packet.id = {dev_id} is invalid; allowed: 0..{MAX_ID} or 254")
    return InstructionPacket(dev_id, instruction, params)


def decode_packet(frame: bytes) -> Packet:
    """Decode exactly one complete frame.

    Raises
    ------
    ProtocolError
        Bad header, length disagreeing with the frame, bad stuffing; :class:`CrcError`
        for a checksum mismatch.
    """
    frame = bytes(frame)
    if len(frame) < 10 or not frame.startswith(HEADER):
        raise ProtocolError(
            f"packet.frame = {frame[:16].hex(' ')} is invalid; allowed: FF FF FD 00 header "
            "and >= 10 bytes"
        )
    length = frame[5] | (frame[6] << 8)
    if length != len(frame) - 7:
        raise ProtocolError(
            f"packet.length = {length} is invalid; allowed: {len(frame) - 7} (bytes after "
            "the length field)"
        )
    parser = PacketParser()
    parser.feed(frame)
    pkt = parser.next_packet()
    if pkt is None:  # pragma: no cover - guarded by the checks above
        raise ProtocolError(f"packet.frame = {frame.hex(' ')} is invalid; allowed: one frame")
    return pkt


class PacketParser:
    """Incremental frame parser for a byte stream.

    Bytes that are not part of a frame are skipped (``garbage_bytes`` counts them);
    a frame with a bad CRC is dropped and reported by :meth:`next_packet` raising
    :class:`CrcError` (the parser stays usable: call again for the next frame).
    """

    def __init__(self) -> None:
        self._buf = bytearray()
        self.garbage_bytes = 0
        self.crc_errors = 0

    def feed(self, data: bytes) -> None:
        """Append received bytes."""
        self._buf += data

    @property
    def pending(self) -> int:
        """Bytes buffered but not yet consumed."""
        return len(self._buf)

    def clear(self) -> None:
        """Drop everything buffered."""
        self._buf.clear()

    def _skip(self, n: int) -> None:
        del self._buf[:n]
        self.garbage_bytes += n

    def next_packet(self) -> Packet | None:
        """Return the next complete frame, or None if more bytes are needed.

        Raises
        ------
        CrcError
            The next complete frame has a bad CRC (it has been discarded).
        ProtocolError
            The next frame has a valid CRC but an impossible content (discarded).
        """
        buf = self._buf
        while True:
            start = buf.find(HEADER)
            if start < 0:
                # keep a possible partial header at the end
                keep = 0
                for k in (3, 2, 1):
                    if len(buf) >= k and buf[-k:] == HEADER[:k]:
                        keep = k
                        break
                self._skip(len(buf) - keep)
                return None
            if start:
                self._skip(start)
            if len(buf) < 7:
                return None
            length = buf[5] | (buf[6] << 8)
            if length < 3 or length > MAX_LENGTH:
                self._skip(1)  # not a real header; resync after it
                continue
            total = 7 + length
            # A header cannot occur inside a real frame before its CRC (the body is
            # stuffed, an ID is <= 254, a length <= MAX_LENGTH): a candidate with one is
            # garbage, skipped without a CRC - resync stays linear in the bytes fed.
            inner = buf.find(HEADER, 1, min(len(buf), total - 2))
            if inner > 0:
                self._skip(inner)
                continue
            if len(buf) < total:
                return None
            frame = bytes(buf[:total])
            got = frame[-2] | (frame[-1] << 8)
            expected = crc16(frame[:-2])
            if got != expected:
                # Drop only the header so a real frame hidden inside is still found.
                self._skip(1)
                self.crc_errors += 1
                raise CrcError(frame[4], got, expected)
            del buf[:total]
            return _packet_from_fields(frame[4], unstuff(frame[7:-2]))

    def packets(self, *, skip_bad: bool = True) -> Iterator[Packet]:
        """Yield every complete frame buffered; bad frames are skipped unless asked."""
        while True:
            try:
                pkt = self.next_packet()
            except ProtocolError:
                if skip_bad:
                    continue
                raise
            if pkt is None:
                return
            yield pkt


# -- instruction builders ---------------------------------------------------------


def ping_packet(dev_id: int = BROADCAST_ID) -> InstructionPacket:
    """PING ``dev_id`` (broadcast by default: every device answers, in ID order)."""
    return InstructionPacket(dev_id, Instruction.PING)


def read_packet(dev_id: int, address: int, length: int) -> InstructionPacket:
    """READ ``length`` bytes from ``address`` of device ``dev_id``."""
    _check_addr(address, length)
    return InstructionPacket(
        dev_id, Instruction.READ, address.to_bytes(2, "little") + length.to_bytes(2, "little")
    )


def write_packet(dev_id: int, address: int, data: bytes) -> InstructionPacket:
    """WRITE ``data`` at ``address`` of device ``dev_id`` (254 = all, no reply)."""
    _check_addr(address, len(data))
    return InstructionPacket(dev_id, Instruction.WRITE, address.to_bytes(2, "little") + data)


def reg_write_packet(dev_id: int, address: int, data: bytes) -> InstructionPacket:
    """REG_WRITE: like WRITE but held until ACTION."""
    _check_addr(address, len(data))
    return InstructionPacket(dev_id, Instruction.REG_WRITE, address.to_bytes(2, "little") + data)


def action_packet(dev_id: int = BROADCAST_ID) -> InstructionPacket:
    """ACTION: apply registered writes."""
    return InstructionPacket(dev_id, Instruction.ACTION)


def sync_read_packet(address: int, length: int, ids: Sequence[int]) -> InstructionPacket:
    """SYNC_READ ``length`` bytes at ``address`` from each of ``ids`` (replies in order)."""
    _check_addr(address, length)
    require(len(ids) > 0, "sync_read.ids", list(ids), "at least one ID")
    for i in ids:
        _check_id("sync_read.ids", i, allow_broadcast=False)
    return InstructionPacket(
        BROADCAST_ID,
        Instruction.SYNC_READ,
        address.to_bytes(2, "little") + length.to_bytes(2, "little") + bytes(ids),
    )


def sync_write_packet(address: int, length: int, data: Mapping[int, bytes]) -> InstructionPacket:
    """SYNC_WRITE ``length`` bytes at ``address``: ``data[id]`` to each device (no reply)."""
    _check_addr(address, length)
    require(len(data) > 0, "sync_write.data", dict(data), "at least one ID")
    params = bytearray(address.to_bytes(2, "little") + length.to_bytes(2, "little"))
    for i, d in data.items():
        _check_id("sync_write.ids", i, allow_broadcast=False)
        require(len(d) == length, f"sync_write.data[{i}]", bytes(d), f"exactly {length} bytes")
        params.append(i)
        params += d
    return InstructionPacket(BROADCAST_ID, Instruction.SYNC_WRITE, bytes(params))


def _check_addr(address: int, length: int) -> None:
    require(0 <= address <= 0xFFFF, "control.address", address, "0..65535")
    require(0 < length <= 0xFFFF, "control.length", length, "1..65535 bytes")


# -- control table ----------------------------------------------------------------


@dataclass(frozen=True)
class ControlItem:
    """One control-table item of an X-series servo.

    Attributes
    ----------
    name : str
        Snake-case item name.
    address : int
        First byte address.
    size : int
        Size [bytes]: 1, 2 or 4.
    writable : bool
        False for read-only items.
    signed : bool
        True if the value is two's complement.
    """

    name: str
    address: int
    size: int
    writable: bool = True
    signed: bool = False

    def __post_init__(self) -> None:
        require(self.size in (1, 2, 4), f"control.{self.name}.size", self.size, "1, 2 or 4")
        require(self.address >= 0, f"control.{self.name}.address", self.address, ">= 0")

    @property
    def eeprom(self) -> bool:
        """True for the EEPROM area (writable only while torque is off)."""
        return self.address < EEPROM_END

    @property
    def end(self) -> int:
        """One past the last byte."""
        return self.address + self.size


EEPROM_END = 64
"""Addresses below this are EEPROM (locked while torque is enabled)."""
XM430_W350_MODEL_NUMBER = 1020

_ITEMS = [
    ControlItem("model_number", 0, 2, writable=False),
    ControlItem("model_information", 2, 4, writable=False),
    ControlItem("firmware_version", 6, 1, writable=False),
    ControlItem("id", 7, 1),
    ControlItem("baud_rate", 8, 1),
    ControlItem("return_delay_time", 9, 1),
    ControlItem("drive_mode", 10, 1),
    ControlItem("operating_mode", 11, 1),
    ControlItem("secondary_id", 12, 1),
    ControlItem("protocol_type", 13, 1),
    ControlItem("homing_offset", 20, 4, signed=True),
    ControlItem("moving_threshold", 24, 4),
    ControlItem("temperature_limit", 31, 1),
    ControlItem("max_voltage_limit", 32, 2),
    ControlItem("min_voltage_limit", 34, 2),
    ControlItem("pwm_limit", 36, 2),
    ControlItem("current_limit", 38, 2),
    ControlItem("velocity_limit", 44, 4),
    ControlItem("max_position_limit", 48, 4),
    ControlItem("min_position_limit", 52, 4),
    ControlItem("shutdown", 63, 1),
    ControlItem("torque_enable", 64, 1),
    ControlItem("led", 65, 1),
    ControlItem("status_return_level", 68, 1),
    ControlItem("registered_instruction", 69, 1, writable=False),
    ControlItem("hardware_error_status", 70, 1, writable=False),
    ControlItem("velocity_i_gain", 76, 2),
    ControlItem("velocity_p_gain", 78, 2),
    ControlItem("position_d_gain", 80, 2),
    ControlItem("position_i_gain", 82, 2),
    ControlItem("position_p_gain", 84, 2),
    ControlItem("goal_pwm", 100, 2, signed=True),
    ControlItem("goal_current", 102, 2, signed=True),
    ControlItem("goal_velocity", 104, 4, signed=True),
    ControlItem("profile_acceleration", 108, 4),
    ControlItem("profile_velocity", 112, 4),
    ControlItem("goal_position", 116, 4, signed=True),
    ControlItem("realtime_tick", 120, 2, writable=False),
    ControlItem("moving", 122, 1, writable=False),
    ControlItem("moving_status", 123, 1, writable=False),
    ControlItem("present_pwm", 124, 2, writable=False, signed=True),
    ControlItem("present_current", 126, 2, writable=False, signed=True),
    ControlItem("present_velocity", 128, 4, writable=False, signed=True),
    ControlItem("present_position", 132, 4, writable=False, signed=True),
    ControlItem("velocity_trajectory", 136, 4, writable=False, signed=True),
    ControlItem("position_trajectory", 140, 4, writable=False, signed=True),
    ControlItem("present_input_voltage", 144, 2, writable=False),
    ControlItem("present_temperature", 146, 1, writable=False),
]

CONTROL_TABLE: dict[str, ControlItem] = {it.name: it for it in _ITEMS}
"""XM430-W350-like control table (Protocol 2.0), by item name."""
CONTROL_TABLE_SIZE = 147
"""Bytes of control table modelled (addresses 0..146; indirect addresses not modelled)."""


def item(name: str) -> ControlItem:
    """Look up a control-table item by name (``ParameterError`` if unknown)."""
    try:
        return CONTROL_TABLE[name]
    except KeyError:
        raise ParameterError("control.item", name, ", ".join(CONTROL_TABLE)) from None


def encode_value(value: int, size: int, signed: bool = False) -> bytes:
    """Little-endian bytes of an integer item value.

    Raises
    ------
    ParameterError
        If ``value`` does not fit ``size`` bytes.
    """
    value = int(value)
    if signed:
        lo, hi = -(1 << (8 * size - 1)), (1 << (8 * size - 1)) - 1
    else:
        lo, hi = 0, (1 << (8 * size)) - 1
    require(lo <= value <= hi, "control.value", value, f"{lo}..{hi} ({size} bytes)")
    return value.to_bytes(size, "little", signed=signed)


def decode_value(data: bytes, signed: bool = False) -> int:
    """Integer from little-endian bytes."""
    return int.from_bytes(bytes(data), "little", signed=signed)


# -- units ------------------------------------------------------------------------

TICKS_PER_REV = 4096
POSITION_CENTRE_TICKS = 2048
RAD_PER_TICK = 2.0 * math.pi / TICKS_PER_REV
VELOCITY_UNIT_RPM = 0.229
RAD_S_PER_VELOCITY_UNIT = VELOCITY_UNIT_RPM * 2.0 * math.pi / 60.0
REALTIME_TICK_MODULO = 32768
"""The realtime tick [ms] counts 0..32767 and wraps."""


@overload
def ticks_to_rad(ticks: float) -> float: ...
@overload
def ticks_to_rad(ticks: np.ndarray) -> np.ndarray: ...
@overload
def ticks_to_rad(ticks: ArrayLike) -> float | np.ndarray: ...
def ticks_to_rad(ticks: ArrayLike) -> float | np.ndarray:
    """Position ticks -> angle [rad] (tick 2048 = 0 rad). Scalars or arrays."""
    out = (np.asarray(ticks, dtype=float) - POSITION_CENTRE_TICKS) * RAD_PER_TICK
    return float(out) if out.ndim == 0 else out


@overload
def rad_to_ticks(angle_rad: float) -> int: ...
@overload
def rad_to_ticks(angle_rad: np.ndarray) -> np.ndarray: ...
@overload
def rad_to_ticks(angle_rad: ArrayLike) -> int | np.ndarray: ...
def rad_to_ticks(angle_rad: ArrayLike) -> int | np.ndarray:
    """Angle [rad] -> nearest position tick (int, or int64 array)."""
    out = np.rint(np.asarray(angle_rad, dtype=float) / RAD_PER_TICK) + POSITION_CENTRE_TICKS
    return int(out) if out.ndim == 0 else out.astype(np.int64)


@overload
def velocity_raw_to_rad_s(raw: float) -> float: ...
@overload
def velocity_raw_to_rad_s(raw: np.ndarray) -> np.ndarray: ...
@overload
def velocity_raw_to_rad_s(raw: ArrayLike) -> float | np.ndarray: ...
def velocity_raw_to_rad_s(raw: ArrayLike) -> float | np.ndarray:
    """Velocity units (0.229 rev/min) -> angular rate [rad/s]. Scalars or arrays."""
    out = np.asarray(raw, dtype=float) * RAD_S_PER_VELOCITY_UNIT
    return float(out) if out.ndim == 0 else out


@overload
def rad_s_to_velocity_raw(rate_rad_s: float) -> int: ...
@overload
def rad_s_to_velocity_raw(rate_rad_s: np.ndarray) -> np.ndarray: ...
@overload
def rad_s_to_velocity_raw(rate_rad_s: ArrayLike) -> int | np.ndarray: ...
def rad_s_to_velocity_raw(rate_rad_s: ArrayLike) -> int | np.ndarray:
    """Angular rate [rad/s] -> nearest velocity unit (int, or int64 array)."""
    out = np.rint(np.asarray(rate_rad_s, dtype=float) / RAD_S_PER_VELOCITY_UNIT)
    return int(out) if out.ndim == 0 else out.astype(np.int64)
