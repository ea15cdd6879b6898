"""SCIP 2.0 codec (Hokuyo URG/UTM/UST laser scanners): pure functions and types, no I/O.

The device and host exchange LF-terminated text lines (Hokuyo, "Communication Protocol
Specification For SCIP2.0 Standard", C-42-03320B, §6-§9):

* host -> sensor: ``<2-char command>[parameters][;<string>]<LF|CR|CRLF>``;
* sensor -> host: the echo of the command line, a status line ``<2 chars><sum>``, zero or
  more data lines ``<content><sum>`` and an empty line, i.e. every message ends ``LF LF``.

The checksum of a line is ``(sum of the content bytes) & 0x3F`` plus ``0x30``. Numbers are
sent in 2-, 3- or 4-character groups of 6 bits each (``+0x30``), MSB first. Range data are
cut into lines of 64 characters, so values straddle line ends: the data lines are joined
(without their sums) before decoding, which here is a single numpy operation over the whole
block.

Units: ranges stay in integer millimetres (``*_mm``) as the protocol sends them, device
timestamps in integer milliseconds (``*_ms``, a 24-bit counter). Conversion to metres
happens at the codec edge (:func:`ranges_mm_to_m`, :meth:`SensorParams.to_lidar_model`).
"""

from __future__ import annotations

import dataclasses
import functools
import re
import warnings
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from .errors import DeviceError, ParameterError, ProtocolError, require
from .lidar import LIDAR_MODELS, LidarModel

__all__ = [
    "LF",
    "DATA_LINE_CHARS",
    "TIMESTAMP_MODULUS_MS",
    "ScipChecksumWarning",
    "ScipStatusError",
    "ScipRequestError",
    "checksum",
    "with_checksum",
    "verify_line",
    "encode_value",
    "decode_value",
    "encode_values",
    "decode_values",
    "encode_data_block",
    "decode_data_block",
    "encode_message",
    "encode_scan_reply",
    "encode_info_reply",
    "info_line",
    "info_line_verifies",
    "split_command",
    "command",
    "DistanceRequest",
    "gd_command",
    "gs_command",
    "md_command",
    "ms_command",
    "ScipReply",
    "ScipFramer",
    "parse_reply",
    "parse_status_line",
    "status_meaning",
    "check_status",
    "ScanFrame",
    "decode_scan",
    "parse_info",
    "VersionInfo",
    "SensorParams",
    "SensorState",
    "parse_version",
    "parse_params",
    "parse_state",
    "RANGE_ERROR_CODES_URG04LX",
    "RANGE_ERROR_CODES_UTM30LX",
    "range_error_mask",
    "range_error_meaning",
    "ranges_mm_to_m",
    "RangePlausibility",
]

LF = b"\n"
#: Encoded characters per data line before the sum (SPEC p.11, 13).
DATA_LINE_CHARS = 64
#: The device timer is 24 bits wide with 1 ms resolution (SPEC p.12).
TIMESTAMP_MODULUS_MS = 1 << 24

_CHAR0 = 0x30
_STATUS_RE = re.compile(rb"[0-9A-Z]{2}")
_CHAR_MAX = 0x6F
_TAG_RE = re.compile(r"[A-Za-z0-9 ._+@]*")
_TAG_MAX = 16
_BAD_CHAR = "scip data character is invalid; allowed: '0'..'o' (0x30-0x6F)"
#: the 64 valid data characters: ``bytes.translate(None, _DATA_CHARS)`` leaves the others
_DATA_CHARS = bytes(range(_CHAR0, _CHAR_MAX + 1))
#: n_chars -> (place values of a group's characters, their sum times 0x30): a group's
#: value is its raw character codes times the place values, less that offset - one matrix
#: product, exact in float32 up to 3 characters (0x6F * 4161 < 2**24), float64 for 4
_GROUP_WEIGHTS = {
    n: ((64.0 ** np.arange(n - 1, -1, -1)).astype(np.float32 if n < 4 else np.float64),
        _CHAR0 * (64 ** n - 1) // 63)
    for n in (1, 2, 3, 4)
}
#: n_chars -> the place values of :data:`_GROUP_WEIGHTS` and a weight for one LF (0x0A)
#: that stands for the offset: 10 times it is -offset + f with 0 < f < 1, so the product
#: of a group's characters and an LF is the value + f, exactly (every partial sum is a
#: multiple of 1/32 below 2**19 in float32), and the cast to int32 (which truncates) gives
#: the value: no subtraction (tests/test_scip_codec.py checks every group up to 3 chars)
_LF_WEIGHTS = {
    n: np.append(w, -round((off - 0.5) / 10 * 64) / 64).astype(w.dtype)
    for n, (w, off) in _GROUP_WEIGHTS.items()
}


class ScipChecksumWarning(UserWarning):
    """A lenient (VV/PP/II text) line did not verify under any known checksum rule."""


class ScipStatusError(DeviceError):
    """The device answered a command with an error status.

    Attributes
    ----------
    command : str
        The 2-character command (``"GD"``, ``"BM"`` ...).
    status : str
        The 2-character status code (``"10"``, ``"0E"`` ...), or 1 char in SCIP 1.1 style.
    meaning : str
        The spec's meaning of that status for that command.
    """

    def __init__(self, command: str, status: str, meaning: str | None = None,
                 allowed: Sequence[str] = ("00", "99")):
        self.command = command
        self.status = status
        self.allowed = tuple(allowed)
        self.meaning = meaning if meaning is not None else status_meaning(command, status)
        ok = " or ".join(repr(a) for a in self.allowed) or "none"
        super().__init__(f"{command}: device status {status!r} ({self.meaning}); allowed: {ok}")


class ScipRequestError(ProtocolError):
    """A command line is malformed; ``status`` is what a SCIP 2.0 device answers."""

    def __init__(self, status: str, field_name: str, value: object, allowed: str):
        self.status = status
        self.field = field_name
        self.value = value
        self.allowed = allowed
        super().__init__(f"{field_name} = {value!r} is invalid; allowed: {allowed}")


# ---------------------------------------------------------------------------------------
# checksums and character encodings (SPEC §6, §7)
# ---------------------------------------------------------------------------------------
def checksum(content: bytes | str) -> bytes:
    """Checksum character of a line's content.

    Parameters
    ----------
    content : bytes or str
        Line content without the sum and without LF (ASCII).

    Returns
    -------
    bytes
        One byte in ``b"0"..b"o"``: ``(sum(content) & 0x3F) + 0x30``.
    """
    if isinstance(content, str):
        content = content.encode("ascii")
    return bytes(((sum(content) & 0x3F) + _CHAR0,))


def with_checksum(content: bytes | str) -> bytes:
    """``content`` followed by its checksum character (no LF)."""
    if isinstance(content, str):
        content = content.encode("ascii")
    return content + checksum(content)


def verify_line(line: bytes) -> bytes:
    """Strictly check a ``<content><sum>`` line; return the content.

    Raises
    ------
    ProtocolError
        If the line is empty or its last byte is not the content's checksum.
    """
    if len(line) < 1:
        raise ProtocolError("scip line = b'' is invalid; allowed: content followed by a sum")
    content, got = line[:-1], line[-1:]
    want = checksum(content)
    if got != want:
        raise ProtocolError(
            f"scip checksum of {bytes(line)[:70]!r} = {got!r} is invalid; allowed: {want!r}"
        )
    return bytes(content)


def encode_value(value: int, n_chars: int) -> bytes:
    """Encode one non-negative integer in ``n_chars`` 6-bit characters (SPEC §6).

    Raises
    ------
    ParameterError
        If ``n_chars`` is not 2, 3 or 4, or ``value`` does not fit.
    """
    return encode_values(np.asarray([value]), n_chars)


def decode_value(chars: bytes | str) -> int:
    """Decode one 2/3/4-character group (any length 1..4) to an integer.

    Raises
    ------
    ProtocolError
        Wrong length or a character outside ``'0'..'o'``.
    """
    if isinstance(chars, str):
        if not chars.isascii():
            raise ProtocolError(f"scip value = {chars[:8]!r} is invalid; allowed: '0'..'o'")
        chars = chars.encode("ascii")
    if not 1 <= len(chars) <= 4:
        raise ProtocolError(f"scip value = {bytes(chars)[:8]!r} is invalid; allowed: 1 to 4 "
                            "characters")
    return _decode_int(chars)


def _check_nchars(n_chars: int) -> None:
    if n_chars not in (1, 2, 3, 4):
        raise ParameterError("scip.n_chars", n_chars, "2, 3 or 4 (1 also accepted)")


def encode_values(values: np.ndarray | Sequence[int], n_chars: int) -> bytes:
    """Encode integers as concatenated ``n_chars``-character groups (vectorised).

    Parameters
    ----------
    values : array_like of int, shape (n,)
        Values in ``0 .. 64**n_chars - 1`` (e.g. ranges in mm).
    n_chars : int
        2 (GS/MS ranges), 3 (GD/MD ranges) or 4 (timestamps).

    Returns
    -------
    bytes
        ``n * n_chars`` ASCII characters.
    """
    _check_nchars(n_chars)
    v = np.asarray(values)
    if v.size and not np.issubdtype(v.dtype, np.integer):
        raise ParameterError("scip.values.dtype", str(v.dtype), "an integer array")
    v = v.astype(np.int64).ravel()
    top = 1 << (6 * n_chars)
    if v.size and (v.min() < 0 or v.max() >= top):
        bad = v[(v < 0) | (v >= top)][0]
        raise ParameterError("scip.value", int(bad), f"0..{top - 1} for {n_chars}-char encoding")
    shifts = 6 * np.arange(n_chars - 1, -1, -1)
    chars = ((v[:, None] >> shifts[None, :]) & 0x3F) + _CHAR0
    return chars.astype(np.uint8).tobytes()


def decode_values(data: bytes | bytearray | memoryview | np.ndarray, n_chars: int) -> np.ndarray:
    """Decode a joined block of ``n_chars``-character groups (vectorised).

    Parameters
    ----------
    data : bytes or numpy.ndarray of uint8
        The concatenated data characters, sums and LFs already removed.
    n_chars : int
        Characters per value (2, 3 or 4).

    Returns
    -------
    numpy.ndarray, shape (len(data) // n_chars,), int32

    Raises
    ------
    ProtocolError
        If the length is not a multiple of ``n_chars`` or a character is outside
        ``'0'..'o'``.
    """
    _check_nchars(n_chars)
    a = data if isinstance(data, np.ndarray) else np.frombuffer(data, dtype=np.uint8)
    if a.size % n_chars:
        raise ProtocolError(
            f"scip data length = {a.size} is invalid; allowed: a multiple of {n_chars}"
        )
    if a.dtype != np.uint8:  # any other integer array: range first, then the byte path
        if a.size and (a.min() < _CHAR0 or a.max() > _CHAR_MAX):
            raise ProtocolError(_BAD_CHAR)
        a = a.astype(np.uint8)
    return _decode_digits(a, n_chars)


def _decode_digits(a: np.ndarray, n_chars: int) -> np.ndarray:
    """:func:`decode_values` of a uint8 array whose size is a multiple of ``n_chars``."""
    # every character in '0'..'o': deleting those leaves nothing (one C pass over bytes)
    if a.tobytes().translate(None, _DATA_CHARS):
        raise ProtocolError(_BAD_CHAR)
    return _group_values(a, n_chars)


def _group_values(chars: np.ndarray, n_chars: int) -> np.ndarray:
    """Values of groups of valid characters (not checked here).

    Parameters
    ----------
    chars : numpy.ndarray of uint8, shape (m * n_chars,) or (m, n_chars)
        Character codes in ``'0'..'o'``, each group's most significant first.
    n_chars : int
        Characters per group (1-4).

    Returns
    -------
    numpy.ndarray, shape (m,), int32
    """
    w, offset = _GROUP_WEIGHTS[n_chars]
    v = chars.reshape(-1, n_chars).dot(w).astype(np.int32)  # .dot: less overhead than @
    v -= offset  # the 0x30 of each character, times its place value
    return v


def _decode_int(chars: bytes) -> int:
    """One 1-4 character group to an int in plain Python (the timestamp: no arrays)."""
    v = 0
    for c in chars:
        c -= _CHAR0
        if not 0 <= c <= 0x3F:
            raise ProtocolError(_BAD_CHAR)
        v = (v << 6) | c
    return v


def _line_sums(block: np.ndarray) -> np.ndarray:
    """Checksum chars of each row of a 2-D uint8 array."""
    return ((block.sum(axis=1, dtype=np.int64) & 0x3F) + _CHAR0).astype(np.uint8)


def encode_data_block(encoded: bytes, width: int = DATA_LINE_CHARS) -> bytes:
    """Cut encoded characters into ``width``-char lines, each + sum + LF (vectorised).

    Returns ``b""`` for empty input (no data lines).
    """
    a = np.frombuffer(encoded, dtype=np.uint8)
    n_full, rest = divmod(a.size, width)
    parts = []
    if n_full:
        full = a[: n_full * width].reshape(n_full, width)
        lines = np.empty((n_full, width + 2), dtype=np.uint8)
        lines[:, :width] = full
        lines[:, width] = _line_sums(full)
        lines[:, width + 1] = 0x0A
        parts.append(lines.tobytes())
    if rest:
        tail = bytes(a[n_full * width:])
        parts.append(with_checksum(tail) + LF)
    return b"".join(parts)


class _Layout(NamedTuple):
    """Where the lines of one shape of LF-terminated ``<content><sum>`` block lie."""

    n_lines: int
    #: (2 * n_lines,) intp: each line's first byte and its sum's position, the boundaries
    #: for one ``np.add.reduceat``: content sums at even, sum + LF at odd entries
    bounds: np.ndarray
    #: (n_content,) intp: positions of the content bytes, in order (sums and LFs left out)
    content: np.ndarray
    #: what ``block[first_lf::stride]`` is when the LFs sit where this layout has them
    lf_stride: bytes


def _layout_from_lf(lf: np.ndarray, lf_stride: bytes = b"") -> _Layout:
    bounds = np.empty(2 * lf.size, dtype=np.intp)
    bounds[0] = 0
    bounds[2::2] = lf[:-1] + 1
    bounds[1::2] = lf - 1
    keep = np.ones(int(lf[-1]) + 1, dtype=bool)
    keep[lf] = False
    keep[lf - 1] = False
    return _Layout(int(lf.size), bounds, np.flatnonzero(keep), lf_stride)


#: (block length, first line length) -> the layout a device sends: any first line (the
#: timestamp), then lines of DATA_LINE_CHARS + sum + LF, the last one shorter
_DEVICE_LAYOUTS: dict[tuple[int, int], _Layout] = {}
_DEVICE_LAYOUTS_MAX = 64


def _device_layout(buf: bytes, start: int, end: int) -> _Layout | None:
    """The layout of the block ``buf[start:end]`` if it is the device's (LFs exactly
    there), else None."""
    n, first = end - start, buf.find(LF, start, end)
    first = first - start if first >= 0 else -1
    lay = _DEVICE_LAYOUTS.get((n, first))
    if lay is None:
        if first < 2:  # no LF, or an empty first line: left to the general path
            return None
        w = DATA_LINE_CHARS + 2
        lf = list(range(first, n, w))
        if lf[-1] != n - 1:
            if n - 1 - lf[-1] < 3:  # a last line without content: the general path
                return None
            lf.append(n - 1)
        if len(_DEVICE_LAYOUTS) >= _DEVICE_LAYOUTS_MAX:
            _DEVICE_LAYOUTS.clear()  # bounded whatever arrives; a device uses one or two
        lay = _layout_from_lf(np.array(lf, dtype=np.intp), LF * len(range(first, n, w)))
        _DEVICE_LAYOUTS[(n, first)] = lay
    # every LF where the layout has one, the last byte one and no other LF anywhere
    if (buf[end - 1] != 0x0A or buf.count(LF, start, end) != lay.n_lines
            or buf[start + first:end:DATA_LINE_CHARS + 2] != lay.lf_stride):
        return None
    return lay


class _ScanLayout(NamedTuple):
    """Where everything lies in the data block of a scan message as a device sends it:
    the timestamp line (4 characters + sum), then lines of DATA_LINE_CHARS + sum + LF, the
    last one shorter; the block runs from the timestamp to the LF ending the last line."""

    #: (2 * n_lines,) intp: the ``np.add.reduceat`` boundaries of :class:`_Layout`
    bounds: np.ndarray
    #: (n_values, n_chars + 1) intp: positions of each value's characters in the block,
    #: then of the timestamp line's LF (for the offset, see _LF_WEIGHTS)
    data: np.ndarray
    #: what ``block[5::DATA_LINE_CHARS + 2]`` is (the LFs on the line grid)
    lf_stride: bytes
    #: what ``block.translate(None, _DATA_CHARS)`` is: one LF per line, nothing else
    lfs: bytes
    n_values: int


#: (block length, n_chars) -> the device's scan layout, or None if no device sends that
_SCAN_LAYOUTS: dict[tuple[int, int], _ScanLayout | None] = {}


def _scan_layout(size: int, n_chars: int) -> _ScanLayout | None:
    """The (cached) :class:`_ScanLayout` of a ``size``-byte block of ``n_chars`` values."""
    key = (size, n_chars)
    if key in _SCAN_LAYOUTS:
        return _SCAN_LAYOUTS[key]
    lay = None
    w = DATA_LINE_CHARS + 2
    lf = list(range(5, size, w))  # the timestamp line's LF, then every full line's
    if lf and lf[-1] != size - 1 and size - 1 - lf[-1] >= 3:
        lf.append(size - 1)  # a shorter last line, at least one character + sum
    if lf and lf[-1] == size - 1 and len(lf) >= 2:
        base = _layout_from_lf(np.array(lf, dtype=np.intp))
        n_values, rest = divmod(base.content.size - 4, n_chars)
        if not rest:
            data = np.full((n_values, n_chars + 1), 5, dtype=np.intp)  # 5: an LF
            data[:, :n_chars] = base.content[4:].reshape(n_values, n_chars)
            lay = _ScanLayout(base.bounds, data, LF * len(range(5, size, w)), LF * len(lf),
                              n_values)
    if len(_SCAN_LAYOUTS) >= _DEVICE_LAYOUTS_MAX:
        _SCAN_LAYOUTS.clear()  # bounded whatever arrives; a device uses one or two
    _SCAN_LAYOUTS[key] = lay
    return lay


def _any_layout(a: np.ndarray) -> _Layout:
    """The layout of any block (uint8 array), or the ProtocolError that frames it badly."""
    lf = np.flatnonzero(a == 0x0A)
    if lf.size == 0 or lf[-1] != a.size - 1:
        raise ProtocolError("scip data block does not end with LF; allowed: lines + sum + LF")
    starts = np.empty(lf.size, dtype=np.intp)
    starts[0] = 0
    starts[1:] = lf[:-1] + 1
    if (lf - starts).min() < 2:
        raise ProtocolError("scip data line is empty; allowed: content followed by a sum")
    return _layout_from_lf(lf)


#: content sum (mod 256) -> the sum character plus LF (0x0A) that must follow it
_SUM_LF_TABLE = bytes(((np.arange(256) & 0x3F) + _CHAR0 + 0x0A).astype(np.uint8))


def _verify_block(buf: bytes, start: int = 0, end: int | None = None) -> np.ndarray:
    """Strictly verify LF-terminated ``<content><sum>`` lines at once (vectorised).

    The block is ``buf[start:end]`` (read in place, not copied). Returns the joined content
    (sums and LFs removed) as a uint8 array. The device's layout is recognised with a few
    bytes operations and its index arrays are cached, so a scan costs three numpy calls:
    a view, one ``reduceat`` for every line's sums (compared as bytes, through a
    translation table), one gather of the content.
    """
    end = len(buf) if end is None else end
    a = np.frombuffer(buf, dtype=np.uint8)[start:end]
    if a.size == 0:
        return a
    lay = _device_layout(buf, start, end) or _any_layout(a)
    # each line's content sum and its sum char + LF; mod 256 suffices (the sum is mod 64);
    # the comparison is on bytes: a translate() by the table is the wanted sum + LF
    r = np.add.reduceat(a, lay.bounds, dtype=np.uint8).tobytes()
    if r[0::2].translate(_SUM_LF_TABLE) != r[1::2]:
        _raise_checksum(a, lay)
    return a.take(lay.content)


def _raise_checksum(a: np.ndarray, lay: _Layout) -> None:
    """Raise the ProtocolError naming the first line whose sum does not verify."""
    content = np.add.reduceat(a, lay.bounds, dtype=np.int64)[0::2]
    sums = a[lay.bounds[1::2]].astype(np.int64)
    want = (content & 0x3F) + _CHAR0
    i = int(np.flatnonzero(want != sums)[0])
    raise ProtocolError(
        f"scip checksum of data line {i} = {chr(sums[i])!r} is invalid; "
        f"allowed: {chr(want[i])!r}"
    )


def _verify_lines(lines: Sequence[bytes]) -> np.ndarray:
    """Strictly verify ``<content><sum>`` lines (no LF); return the joined content."""
    if not lines:
        return np.zeros(0, dtype=np.uint8)
    return _verify_block(LF.join(lines) + LF)


def decode_data_block(lines: Sequence[bytes], n_chars: int) -> np.ndarray:
    """Verify data lines (each ``<content><sum>``, no LF), join and decode them.

    Returns
    -------
    numpy.ndarray, shape (n,), int32
    """
    return decode_values(_verify_lines(lines).tobytes(), n_chars)


# ---------------------------------------------------------------------------------------
# messages sensor -> host
# ---------------------------------------------------------------------------------------
def _b(s: bytes | str) -> bytes:
    return s if isinstance(s, bytes) else s.encode("ascii")


def encode_message(
    echo: bytes | str, status: str, body: Iterable[bytes] = (), *, scip1: bool = False
) -> bytes:
    """Assemble one reply: echo, status (+sum), body lines, terminating empty line.

    Parameters
    ----------
    echo : bytes or str
        The command line as the host sent it (without line ending).
    status : str
        Two-character status (``"00"``); with ``scip1=True`` a 1-char SCIP 1.1 status that
        is sent without a sum.
    body : iterable of bytes
        Complete lines (content + sum) without LF, e.g. from :func:`info_line`; or raw
        already-terminated blocks when they end with LF (e.g. :func:`encode_data_block`).
    """
    out = [_b(echo), LF, _b(status) if scip1 else with_checksum(status), LF]
    for line in body:
        out.append(line)
        if not line.endswith(LF):
            out.append(LF)
    out.append(LF)
    return b"".join(out)


def encode_scan_reply(
    echo: bytes | str,
    status: str,
    timestamp_ms: int,
    ranges_mm: np.ndarray,
    n_chars: int,
) -> bytes:
    """Encode a GD/GS/MD/MS data message.

    Parameters
    ----------
    echo : bytes or str
        Echo line (for MD/MS the command with the remaining count in its last 2 digits).
    status : str
        ``"00"`` for GD/GS, ``"99"`` for MD/MS scan messages.
    timestamp_ms : int
        Device timer [ms]; reduced modulo 2**24.
    ranges_mm : numpy.ndarray, shape (n,), int
        Ranges [mm] or error codes (< DMIN).
    n_chars : int
        3 (GD/MD) or 2 (GS/MS).
    """
    ts = with_checksum(encode_value(int(timestamp_ms) % TIMESTAMP_MODULUS_MS, 4))
    data = encode_data_block(encode_values(ranges_mm, n_chars))
    return encode_message(echo, status, [ts, data])


def info_line(key: str, value: str) -> bytes:
    """``KEY:VALUE;<sum>`` with the sum over ``KEY:VALUE`` (``;`` excluded, WIKI)."""
    content = f"{key}:{value}".encode("ascii")
    return content + b";" + checksum(content)


def encode_info_reply(echo: bytes | str, items: Iterable[tuple[str, str]]) -> bytes:
    """Encode a VV/PP/II reply from ``(key, value)`` pairs (status ``00``)."""
    return encode_message(echo, "00", [info_line(k, v) for k, v in items])


# ---------------------------------------------------------------------------------------
# commands host -> sensor
# ---------------------------------------------------------------------------------------
def _check_tag(tag: str | None, *, as_request: bool = False) -> None:
    if tag is None:
        return
    if len(tag) > _TAG_MAX:
        if as_request:
            raise ScipRequestError("0G", "scip.tag", tag, "at most 16 characters")
        raise ParameterError("scip.tag", tag, "at most 16 characters")
    if not _TAG_RE.fullmatch(tag):
        if as_request:
            raise ScipRequestError("0H", "scip.tag", tag, "letters, digits, space and . _ + @")
        raise ParameterError("scip.tag", tag, "letters, digits, space and . _ + @")


def command(code: str, params: str = "", tag: str | None = None) -> bytes:
    """Build a command line ``<code><params>[;tag]LF``.

    Parameters
    ----------
    code : str
        ``"BM"``, ``"TM"``, ``"SCIP2.0"`` ...
    params : str
        Parameter characters (e.g. ``"1"`` for ``TM1``).
    tag : str, optional
        The "string characters" echoed back (<= 16 of letters, digits, `` ._+@``).
    """
    _check_tag(tag)
    line = f"{code}{params}" + (f";{tag}" if tag is not None else "")
    return line.encode("ascii") + LF


def split_command(line: bytes | str) -> tuple[str, str, str | None]:
    """Split a command line into ``(code, params, tag)``.

    Line endings (LF, CR, CRLF) are stripped; ``code`` is the first 2 characters (3 for
    ``%XX``), or ``"SCIP2.0"``.
    """
    s = line.decode("ascii", "replace") if isinstance(line, (bytes, bytearray)) else line
    s = s.rstrip("\r\n")
    tag = None
    if ";" in s:
        s, tag = s.split(";", 1)
    if s.startswith("SCIP"):
        return s[:7], s[7:], tag
    n = 3 if s.startswith("%") else 2
    return s[:n], s[n:], tag


_N_CHARS = {"GD": 3, "MD": 3, "GS": 2, "MS": 2}


@dataclass(frozen=True)
class DistanceRequest:
    """A GD/GS/MD/MS request (SPEC §8.1-8.2).

    Attributes
    ----------
    command : str
        ``"GD"``, ``"GS"``, ``"MD"`` or ``"MS"``.
    start, end : int
        First and last step (inclusive), 4 digits each.
    cluster : int
        Steps merged into one value (0..99; 0 means 1), 2 digits.
    interval : int or None
        MD/MS only: scans skipped between transmissions (0..9).
    count : int or None
        MD/MS only: number of scans (0 = until ``QT``, 1..99). In an echo of a scan
        message this is the *remaining* count.
    tag : str or None
        The echoed string characters.
    """

    command: str
    start: int
    end: int
    cluster: int = 1
    interval: int | None = None
    count: int | None = None
    tag: str | None = None

    def __post_init__(self) -> None:
        if self.command not in _N_CHARS:
            raise ParameterError("scip.command", self.command, "GD, GS, MD or MS")
        for name, v, hi in (("start", self.start, 9999), ("end", self.end, 9999),
                            ("cluster", self.cluster, 99)):
            if not (isinstance(v, (int, np.integer)) and 0 <= v <= hi):
                raise ParameterError(f"scip.{name}", v, f"an integer 0..{hi}")
        if self.end < self.start:
            raise ParameterError("scip.end", self.end, f">= start ({self.start})")
        if self.is_multi:
            interval = 0 if self.interval is None else self.interval
            count = 0 if self.count is None else self.count
            if not 0 <= interval <= 9:
                raise ParameterError("scip.interval", self.interval, "an integer 0..9")
            if not 0 <= count <= 99:
                raise ParameterError("scip.count", self.count, "0 (until QT) or 1..99")
            object.__setattr__(self, "interval", int(interval))
            object.__setattr__(self, "count", int(count))
        elif self.interval is not None or self.count is not None:
            raise ParameterError(
                "scip.interval/count", (self.interval, self.count), "None for GD/GS"
            )
        _check_tag(self.tag)

    @property
    def is_multi(self) -> bool:
        """True for MD/MS (continuous) requests."""
        return self.command in ("MD", "MS")

    @property
    def n_chars(self) -> int:
        """Characters per value: 3 (GD/MD) or 2 (GS/MS)."""
        return _N_CHARS[self.command]

    @property
    def cluster_size(self) -> int:
        """Steps per value (cluster 0 counts as 1)."""
        return max(1, self.cluster)

    @property
    def n_values(self) -> int:
        """Number of values in each scan message."""
        return -(-(self.end - self.start + 1) // self.cluster_size)

    @property
    def steps(self) -> np.ndarray:
        """First step of each value, shape ``(n_values,)`` int."""
        return self.start + self.cluster_size * np.arange(self.n_values)

    def line(self, count: int | None = None) -> str:
        """The command line without LF; ``count`` overrides the count field (echoes)."""
        s = f"{self.command}{self.start:04d}{self.end:04d}{self.cluster:02d}"
        if self.is_multi:
            c = self.count if count is None else count
            s += f"{self.interval:01d}{c:02d}"
        if self.tag is not None:
            s += ";" + self.tag
        return s

    def encode(self) -> bytes:
        """The command as bytes to send, LF terminated."""
        return self.line().encode("ascii") + LF

    def echo(self, remaining: int | None = None) -> str:
        """The echo line of a reply (MD/MS scan messages carry the remaining count)."""
        return self.line(remaining)

    @classmethod
    def parse(cls, line: bytes | str) -> DistanceRequest:
        """Parse a request or echo line, checking fields like the device does.

        Raises
        ------
        ScipRequestError
            With the status a device answers: ``0C`` too short, ``0D`` too long,
            ``01``..``07`` non-numeric fields, ``05`` end < start, ``0G``/``0H`` bad tag.
        """
        code, params, tag = split_command(line)
        if code not in _N_CHARS:
            raise ScipRequestError("0E", "scip.command", code, "GD, GS, MD or MS")
        multi = code in ("MD", "MS")
        want = 13 if multi else 10
        if len(params) < want:
            raise ScipRequestError("0C", f"{code}.parameters", params, f"{want} digits")
        if len(params) > want:
            raise ScipRequestError("0D", f"{code}.parameters", params, f"{want} digits")
        _check_tag(tag, as_request=True)
        fields = [("01", "start", params[0:4]), ("02", "end", params[4:8]),
                  ("03", "cluster", params[8:10])]
        if multi:
            fields += [("06", "interval", params[10:11]), ("07", "count", params[11:13])]
        vals = {}
        for status, name, txt in fields:
            if not (txt.isascii() and txt.isdigit()):
                raise ScipRequestError(status, f"{code}.{name}", txt, "decimal digits")
            vals[name] = int(txt)
        if vals["end"] < vals["start"]:
            raise ScipRequestError("05", f"{code}.end", vals["end"], f">= start {vals['start']}")
        return cls(command=code, tag=tag, **vals)


def gd_command(start: int, end: int, cluster: int = 1, tag: str | None = None) -> bytes:
    """``GD`` (single scan, 3-char ranges) command line."""
    return DistanceRequest("GD", start, end, cluster, tag=tag).encode()


def gs_command(start: int, end: int, cluster: int = 1, tag: str | None = None) -> bytes:
    """``GS`` (single scan, 2-char ranges, max 4095 mm) command line."""
    return DistanceRequest("GS", start, end, cluster, tag=tag).encode()


def md_command(start: int, end: int, cluster: int = 1, interval: int = 0, count: int = 0,
               tag: str | None = None) -> bytes:
    """``MD`` (continuous scans, 3-char ranges) command line; ``count`` 0 = until QT."""
    return DistanceRequest("MD", start, end, cluster, interval, count, tag).encode()


def ms_command(start: int, end: int, cluster: int = 1, interval: int = 0, count: int = 0,
               tag: str | None = None) -> bytes:
    """``MS`` (continuous scans, 2-char ranges) command line; ``count`` 0 = until QT."""
    return DistanceRequest("MS", start, end, cluster, interval, count, tag).encode()


# ---------------------------------------------------------------------------------------
# status codes (SPEC §8, §9)
# ---------------------------------------------------------------------------------------
_GENERAL_STATUS = {
    "00": "command received without error",
    "99": "scan data",
    "0A": "unable to create transmission data or reply command internally",
    "0B": "buffer shortage or command repeated that is already processed",
    "0C": "command with insufficient parameters 1",
    "0D": "undefined command 1 (newer firmware: command too long)",
    "0E": "undefined command 2 (newer firmware: command not defined)",
    "0F": "command with insufficient parameters 2 (newer firmware: not supported)",
    "0G": "string character in command exceeds 16 letters",
    "0H": "string character has invalid letters",
    "0I": "sensor is in firmware update mode",
    "0L": "sensor is in an abnormal state",
    "0M": "sensor is unstable",
}
_DIST_STATUS = {
    "01": "starting step has non-numeric value",
    "02": "end step has non-numeric value",
    "03": "cluster count has non-numeric value",
    "04": "end step is out of range",
    "05": "end step is smaller than starting step",
}
_COMMAND_STATUS: dict[str, dict[str, str]] = {
    "GD": {**_DIST_STATUS, "10": "laser is off"},
    "MD": {**_DIST_STATUS, "06": "scan interval has non-numeric value",
           "07": "number of scans has non-numeric value",
           "98": "resumption of process after confirming normal laser operation"},
    "BM": {"01": "unable to control due to laser malfunction", "02": "laser is already on"},
    "TM": {"01": "invalid control code", "02": "adjust mode on command received when "
           "sensor's adjust mode is already on", "03": "adjust mode off command received "
           "when sensor's adjust mode is already off", "04": "adjust mode is off when "
           "requested for time"},
    "SS": {"01": "bit rate has non-numeric value", "02": "invalid bit rate",
           "03": "sensor is already running at that bit rate",
           "04": "not compatible with the sensor model"},
    "CR": {"01": "invalid speed", "02": "speed out of range",
           "03": "motor is already running at that speed",
           "04": "not compatible with the sensor model"},
    "HS": {"01": "invalid parameter", "02": "already running in the requested mode",
           "03": "incompatible with current sensor model"},
    "SCIP2.0": {"0": "switched to SCIP 2.0", "E": "command not understood (SCIP 1.1)"},
}
_COMMAND_STATUS["GS"] = _COMMAND_STATUS["GD"]
_COMMAND_STATUS["MS"] = _COMMAND_STATUS["MD"]


def status_meaning(command_code: str, status: str) -> str:
    """The spec's meaning of ``status`` in reply to ``command_code`` (best effort)."""
    table = _COMMAND_STATUS.get(command_code, {})
    if status in table:
        return table[status]
    if status in _GENERAL_STATUS:
        return _GENERAL_STATUS[status]
    if len(status) == 1:
        return "SCIP 1.1 status " + ("ok" if status == "0" else "error")
    if status.isdigit():
        n = int(status)
        if command_code in ("MD", "MS") and 21 <= n <= 49:
            return "processing stopped to verify the error"
        if 50 <= n <= 98:
            return "hardware trouble (laser, motor malfunction etc.)"
    return "undocumented status"


def parse_status_line(line: bytes) -> tuple[str, bool]:
    """Parse a status line; return ``(status, scip1)``.

    A 3-byte line is a SCIP 2.0 status + sum (verified strictly); a 1-byte line is a
    SCIP 1.1 status (no sum).

    Raises
    ------
    ProtocolError
        Wrong length or checksum.
    """
    if len(line) == 3:
        if ((line[0] + line[1]) & 0x3F) + _CHAR0 == line[2] and _STATUS_RE.fullmatch(line, 0, 2):
            return line[:2].decode("ascii"), False  # the usual case, without copies
        status = verify_line(line)
        # a byte changed by +-0x40 or 0x80 keeps the sum: statuses are [0-9A-Z] (SPEC §9)
        if _STATUS_RE.fullmatch(status) is None:
            raise ProtocolError(f"scip status = {status!r} is invalid; allowed: 2 characters "
                                "of 0-9, A-Z")
        return status.decode("ascii"), False
    if len(line) == 1 and 0x20 < line[0] < 0x7F:
        return line.decode("ascii"), True
    raise ProtocolError(
        f"scip status line = {bytes(line)[:20]!r} is invalid; allowed: 2 chars + sum "
        "(or 1 char in SCIP 1.1)"
    )


# ---------------------------------------------------------------------------------------
# reply parsing
# ---------------------------------------------------------------------------------------
_STRICT_CODES = ("GD", "GS", "MD", "MS", "TM", "ME", "GE", "HD", "ND")


@dataclass(frozen=True)
class ScipReply:
    """One sensor->host message, structurally checked.

    Attributes
    ----------
    echo : str
        The echoed command line.
    status : str
        Status code (2 chars; 1 char when ``scip1``).
    body : tuple of bytes
        The lines after the status line, each ``<content><sum>`` without LF.
    scip1 : bool
        The status line was in SCIP 1.1 form (no sum).
    raw : bytes
        The message as received, including the final ``LF LF``.
    payload : numpy.ndarray of uint8 or None
        For verified GD/GS/MD/MS/TM replies: the body content joined, sums removed.
    """

    echo: str
    status: str
    body: tuple[bytes, ...]
    scip1: bool = False
    raw: bytes = b""
    payload: np.ndarray | None = field(default=None, repr=False, compare=False)

    @property
    def code(self) -> str:
        """Command code of the echo (``"GD"``, ``"SCIP2.0"`` ...)."""
        return split_command(self.echo)[0]

    @property
    def ok(self) -> bool:
        """True for the success statuses ``00`` / ``99`` (``0`` in SCIP 1.1)."""
        return self.status in ("00", "99") or (self.scip1 and self.status == "0")


_PRINTABLE_RE = re.compile(rb"[\x20-\x7e]{2,}")
#: echo -> command code (a device echoes the same few lines again and again)
_command_code = functools.lru_cache(maxsize=256)(lambda echo: split_command(echo)[0])


def _echo_ok(line: bytes) -> bool:
    return _PRINTABLE_RE.fullmatch(line) is not None


def _parse_parts(message: bytes) -> tuple[bytes, bytes, int, int, str, str, str, bool,
                                           np.ndarray | None]:
    """:func:`parse_reply` without building the body tuple (nor copying the message).

    Returns ``(msg, buf, n, body_at, echo, code, status, scip1, payload)``: the message
    without its final ``LF LF`` is ``buf[:n]``, its body lines start at ``buf[body_at:n]``
    (``body_at`` is -1 if there are none), ``code`` is the echo's command code.
    """
    msg = bytes(message)
    in_place = msg.endswith(b"\n\n")  # then buf[n] is the first LF of the final LF LF
    if in_place:
        buf, n = msg, len(msg) - 2
    else:
        buf = msg.rstrip(b"\n")
        n = len(buf)
    i = buf.find(LF, 0, n)
    if i < 0:
        raise ProtocolError(
            f"scip message = {msg[:40]!r} is invalid; allowed: echo, status line, LF LF"
        )
    if not _PRINTABLE_RE.fullmatch(buf, 0, i):
        raise ProtocolError(f"scip echo = {buf[:i][:40]!r} is invalid; allowed: printable ASCII")
    j = buf.find(LF, i + 1, n)
    status, scip1 = parse_status_line(buf[i + 1:j] if j >= 0 else buf[i + 1:n])
    echo = buf[:i].decode("ascii")
    code = _command_code(echo)
    payload = None
    if not scip1 and code in _STRICT_CODES:
        if j < 0:
            payload = np.zeros(0, dtype=np.uint8)
        elif in_place:  # the block is read where it is, LF-terminated
            payload = _verify_block(msg, j + 1, n + 1)
        else:
            payload = _verify_block(buf[j + 1:n] + LF)
    return msg, buf, n, (j + 1 if j >= 0 else -1), echo, code, status, scip1, payload


def parse_reply(message: bytes) -> ScipReply:
    """Split one message into echo, status and body lines, verifying it.

    The status line is always checked strictly; so are the body lines of distance and
    time replies (GD/GS/MD/MS/TM). Text lines of VV/PP/II are left for :func:`parse_info`.

    Parameters
    ----------
    message : bytes
        One message, with or without its terminating ``LF LF``.

    Raises
    ------
    ProtocolError
        Anything malformed.
    """
    msg, buf, n, body_at, echo, _, status, scip1, payload = _parse_parts(message)
    body = tuple(buf[body_at:n].split(LF)) if body_at >= 0 else ()
    if payload is None and any(len(x) == 0 for x in body):
        raise ProtocolError("scip message has an empty body line; allowed: LF LF only at end")
    return ScipReply(echo=echo, status=status, body=body, scip1=scip1, raw=msg, payload=payload)


def check_status(reply: ScipReply, allowed: Sequence[str] = ("00", "99")) -> ScipReply:
    """Return ``reply`` if its status is in ``allowed``, else raise :class:`ScipStatusError`."""
    if reply.status not in allowed:
        raise ScipStatusError(reply.code, reply.status, allowed=allowed)
    return reply


_ECHO_RE = re.compile(rb"(SCIP2\.0|%?[A-Z]{2}[0-9A-Za-z]*)(;[A-Za-z0-9 ._+@]{0,16})?")
_KNOWN_CODES = frozenset(
    b"GD GS MD MS ME GE HD ND BM QT RS RT RB TM SS CR HS DB VV PP II SC %S".split()
)


class ScipFramer:
    """Incremental splitter of a sensor's byte stream into complete, verified messages.

    ``feed(data)`` returns every message completed by ``data`` (each ending ``LF LF``).
    A candidate is returned only if its echo looks like a command line and it passes
    :func:`parse_reply` (strict checksums on status, timestamp and data lines). Otherwise
    the framer looks for a valid message starting later in the candidate (garbage before an
    echo, or a lost LF that glued two messages together) and else discards it, counting it
    in :attr:`rejected` and its bytes in :attr:`discarded_bytes`.

    Whatever the bytes, the framer raises nothing, its buffer stays below ``max_buffer``
    and the work per byte is bounded: the search for a later message start is one pass
    over the candidate's lines (an echo is at most :data:`_MAX_ECHO` characters, so only
    the tail of each line can start one), never a parse per position.

    Parameters
    ----------
    max_buffer : int
        Bytes kept while waiting for a terminator; beyond that the oldest are dropped.
        The default (64 KiB) is 20 times the longest SCIP 2.0 message (a 1081-step
        ``MD`` scan, about 3.4 kB).
    """

    def __init__(self, max_buffer: int = 1 << 16):
        require(isinstance(max_buffer, int) and max_buffer >= 64, "scip.framer.max_buffer",
                max_buffer, "an integer >= 64 bytes")
        self._buf = bytearray()
        self._searched = 0  # the buffer before this index holds no LF LF
        self.max_buffer = int(max_buffer)
        self.rejected = 0
        self.discarded_bytes = 0
        self.messages = 0

    def reset(self) -> None:
        """Forget any partial message."""
        self.discarded_bytes += len(self._buf)
        self._buf.clear()
        self._searched = 0

    @property
    def pending(self) -> int:
        """Bytes buffered towards an incomplete message."""
        return len(self._buf)

    def feed(self, data: bytes) -> list[bytes]:
        """Add received bytes; return the complete valid messages, oldest first."""
        return [r.raw for r in self.feed_replies(data)]

    def feed_replies(self, data: bytes) -> list[ScipReply]:
        """Like :meth:`feed`, returning the parsed (verified) :class:`ScipReply` objects."""
        buf = self._buf
        buf += data
        out: list[ScipReply] = []
        start = 0
        searched = False
        try:
            while True:
                i = buf.find(b"\n\n", max(start, self._searched))
                if i < 0:
                    searched = True
                    break
                cand = bytes(buf[start:i + 2])
                start = i + 2
                self._searched = 0
                if cand.strip(b"\n") == b"":
                    self.discarded_bytes += len(cand)
                    continue
                msg = self._salvage(cand)
                if msg is not None:
                    out.append(msg)
        finally:  # whatever happened, the consumed bytes go (a bad frame must not stick)
            del buf[:start]
            # the rest holds no LF LF: the next search starts at its last byte
            self._searched = max(0, len(buf) - 1) if searched else 0
            if len(buf) > self.max_buffer:
                drop = len(buf) - self.max_buffer
                del buf[:drop]
                self.discarded_bytes += drop
                self._searched = max(0, len(buf) - 1)
            self.messages += len(out)
        return out

    @staticmethod
    def _valid(msg: bytes) -> ScipReply | None:
        j = msg.find(LF)
        if j < 0 or j > _MAX_ECHO or not _ECHO_RE.fullmatch(msg[:j]):
            return None
        try:
            return parse_reply(msg)
        except (ProtocolError, ValueError):  # ValueError: defence in depth, never expected
            return None

    def _salvage(self, cand: bytes) -> ScipReply | None:
        stripped = cand.lstrip(b"\n")  # leading LFs are never part of a message
        lead = len(cand) - len(stripped)
        reply = self._valid(stripped)
        if reply is not None:
            self.discarded_bytes += lead
            return reply
        self.rejected += 1
        reply, at = _find_message(stripped)
        if reply is not None:
            self.discarded_bytes += lead + at
            return reply
        self.discarded_bytes += len(cand)
        return None


#: Longest echo line accepted: ``MD`` + 13 digits + ``;`` + a 16-character tag is 32.
_MAX_ECHO = 64


def _status_line_ok(line: bytes) -> bool:
    """Would :func:`parse_status_line` accept ``line``? (cheap pre-check)"""
    if len(line) == 3:
        return (_STATUS_RE.fullmatch(line, 0, 2) is not None
                and ((line[0] + line[1]) & 0x3F) + _CHAR0 == line[2])
    return len(line) == 1 and 0x20 < line[0] < 0x7F


def _find_message(text: bytes) -> tuple[ScipReply | None, int]:
    """The first valid message starting after the beginning of ``text`` (a candidate
    ending ``LF LF``, leading LFs removed), and its offset; ``(None, -1)`` if none.

    Linear in ``len(text)``: possible starts are the tails (at most :data:`_MAX_ECHO`
    characters) of lines followed by a status line; only if there are any, the per-line
    checksums are computed once (vectorised) and a suffix "every line from here on
    verifies" flag tells in O(1) whether a strict (distance/time) message can start
    there. :func:`parse_reply` runs only for starts that pass these checks, at most twice
    per line (strict / lenient codes).
    """
    body = text[:-2] if text.endswith(b"\n\n") else text.rstrip(b"\n")
    lines = body.split(LF)
    n = len(lines)
    cands: list[tuple[int, int, bool]] = []  # (line, offset in text, strict)
    pos = 0
    for i in range(n - 1):
        line, status = lines[i], lines[i + 1]
        e = len(line)
        if _status_line_ok(status):
            for j in range(max(0, e - _MAX_ECHO), e - 1):
                if (i or j) and line[j:j + 2] in _KNOWN_CODES and _ECHO_RE.fullmatch(line, j):
                    strict = len(status) == 3 and split_command(line[j:])[0] in _STRICT_CODES
                    cands.append((i, pos + j, strict))
        pos += e + 1
    if not cands:
        return None, -1
    a = np.frombuffer(body + LF, dtype=np.uint8)
    ends = np.flatnonzero(a == 0x0A)  # one per line
    starts = np.empty(n, dtype=np.intp)
    starts[0] = 0
    starts[1:] = ends[:-1] + 1
    lengths = ends - starts
    totals = np.add.reduceat(a, starts, dtype=np.int64) - 0x0A  # content + sum (+ LF out)
    last = a[np.maximum(ends - 1, 0)].astype(np.int64)
    line_ok = (lengths >= 2) & ((((totals - last) & 0x3F) + _CHAR0) == last)
    # strict_from[i]: lines i..n-1 all verify (strict_from[n] = True: no body at all)
    strict_from = np.ones(n + 1, dtype=bool)
    strict_from[:n] = np.logical_and.accumulate(line_ok[::-1])[::-1]
    nonempty_from = np.ones(n + 1, dtype=bool)
    nonempty_from[:n] = np.logical_and.accumulate((lengths > 0)[::-1])[::-1]
    tried: set[tuple[int, bool]] = set()
    for i, at, strict in cands:
        if (i, strict) in tried or not (strict_from if strict else nonempty_from)[i + 2]:
            continue
        tried.add((i, strict))
        reply = ScipFramer._valid(text[at:])
        if reply is not None:
            return reply, at
    return None, -1


# ---------------------------------------------------------------------------------------
# distance replies
# ---------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class ScanFrame:
    """One decoded GD/GS/MD/MS scan message.

    Attributes
    ----------
    request : DistanceRequest
        The request as echoed (for MD/MS, ``count`` is the *remaining* count).
    status : str
        ``"00"`` (GD/GS) or ``"99"`` (MD/MS).
    timestamp_ms : int
        Device timer at step 0 of the scan [ms], 24-bit (wraps every 4.66 h).
    ranges_mm : numpy.ndarray, shape (n_values,), int32, read-only
        Ranges [mm]; values below DMIN are error codes (see :func:`range_error_mask`).
    """

    request: DistanceRequest
    status: str
    timestamp_ms: int
    ranges_mm: np.ndarray

    @property
    def command(self) -> str:
        """``"GD"``, ``"GS"``, ``"MD"`` or ``"MS"``."""
        return self.request.command

    @property
    def echo(self) -> str:
        """The echo line."""
        return self.request.line()

    @property
    def start(self) -> int:
        return self.request.start

    @property
    def end(self) -> int:
        return self.request.end

    @property
    def cluster(self) -> int:
        return self.request.cluster

    @property
    def remaining(self) -> int | None:
        """MD/MS: scans still to come after this one (0 also for an infinite request)."""
        return self.request.count

    @property
    def tag(self) -> str | None:
        return self.request.tag

    @property
    def steps(self) -> np.ndarray:
        """First step of each value, shape ``(n_values,)`` int."""
        return self.request.steps


_parse_request_cached = functools.lru_cache(maxsize=256)(lambda echo: DistanceRequest.parse(echo))


def decode_scan(reply: ScipReply | bytes) -> ScanFrame:
    """Decode a distance message into a :class:`ScanFrame`.

    Raises
    ------
    ScipStatusError
        The status is not ``00``/``99`` (e.g. ``10`` laser off).
    ProtocolError
        Bad checksum, no timestamp (e.g. an MD acknowledgement), or the number of values
        does not match the echoed start/end/cluster.
    """
    if not isinstance(reply, ScipReply):
        frame = _device_scan(reply)
        if frame is not None:
            return frame
        # any other shape, or an error: no body tuple, no ScipReply, the checks in order
        _, buf, n, at, echo, _, status, _, payload = _parse_parts(reply)
        if payload is not None:
            end = buf.find(LF, at, n) if at >= 0 else -1
            ts_line = b"" if at < 0 else buf[at:end] if end >= 0 else buf[at:n]
            return _scan_frame(echo, status, at >= 0, ts_line, payload, (), ts_line[:4])
        reply = parse_reply(reply)
    body = reply.body
    return _scan_frame(reply.echo, reply.status, bool(body), body[0] if body else b"",
                       reply.payload, body, None)


#: the status lines (with their LF) a scan message can have: ``00`` (GD/GS) and ``99``
#: (MD/MS), with sums
_SCAN_STATUS_LINES = {b"00P\n": "00", b"99b\n": "99"}
_LINE = DATA_LINE_CHARS + 2


#: (echo + status lines, block length) -> what _scan_head found (cached: a device sends the
#: same few heads again and again; an MD/MS series counts down through at most 100 echoes)
_SCAN_HEADS: dict[tuple[bytes, int], tuple[DistanceRequest, str, int, _ScanLayout] | None] = {}
_SCAN_HEADS_MAX = 256


def _scan_head(head: bytes, size: int) -> tuple[DistanceRequest, str, int, _ScanLayout] | None:
    """``(request, status, n_chars, layout)`` if ``head`` (the echo line, the status line,
    each with its LF) starts a scan message as a device sends it and a ``size``-byte data
    block (timestamp line to the last LF) is the device's layout for it, else None."""
    i = head.find(LF)
    status = _SCAN_STATUS_LINES.get(head[i + 1:]) if i >= 2 else None
    if status is None or not _PRINTABLE_RE.fullmatch(head, 0, i):
        return None
    try:
        req = _parse_request_cached(head[:i].decode("ascii"))
    except (ScipRequestError, ParameterError):
        return None
    lay = _scan_layout(size, req.n_chars)
    if lay is None or lay.n_values != req.n_values:
        return None
    return req, status, req.n_chars, lay


def _device_scan(message: bytes) -> ScanFrame | None:
    """:func:`decode_scan` of a valid scan message as a device sends it (64-character data
    lines, ``LF LF`` at the end), or None for anything else - then the general path of
    :func:`decode_scan` decodes it or raises its error, so errors are found in one order.

    Every checksum is verified (status by the table of the two valid lines, timestamp and
    data lines by one ``np.add.reduceat``), every LF checked to be where the layout has
    one and every other byte of the block to be a data character (one ``bytes.translate``
    deleting those must leave exactly the LFs). Then one gather of the values' characters,
    one matrix product, and the timestamp by a 4-character expression.
    """
    msg = message if type(message) is bytes else bytes(message)
    n = len(msg) - 1  # the block ends with the first LF of the final LF LF, at msg[n - 1]
    start = msg.find(LF, 0, n) + 5  # the timestamp's first character (echo, LF, 3, LF)
    key = (msg[:start], n - start)
    head = _SCAN_HEADS.get(key)
    if head is None and key not in _SCAN_HEADS:
        head = _scan_head(*key) if start >= 7 else None
        if len(_SCAN_HEADS) >= _SCAN_HEADS_MAX:
            _SCAN_HEADS.clear()  # bounded whatever arrives
        _SCAN_HEADS[key] = head
    if head is None:
        return None
    req, status, n_chars, lay = head
    if (msg[n - 1:] != b"\n\n" or msg[start + 5:n:_LINE] != lay.lf_stride
            or msg[start:n].translate(None, _DATA_CHARS) != lay.lfs):
        return None
    a = np.frombuffer(msg, np.uint8, n - start, start)
    # each line's content sum and its sum char + LF, mod 256 (the sum is mod 64), compared
    # as bytes through the table of the wanted sum + LF (as _verify_block)
    r = np.add.reduceat(a, lay.bounds, dtype=np.uint8).tobytes()
    if r[0::2].translate(_SUM_LF_TABLE) != r[1::2]:
        return None
    # 4 characters, checked above: a plain expression, not the array path
    ts = ((msg[start] - _CHAR0) << 18 | (msg[start + 1] - _CHAR0) << 12
          | (msg[start + 2] - _CHAR0) << 6 | (msg[start + 3] - _CHAR0))
    ranges = a.take(lay.data).dot(_LF_WEIGHTS[n_chars]).astype(np.int32)
    ranges.setflags(write=False)
    return ScanFrame(req, status, ts, ranges)


def _scan_frame(echo: str, status: str, has_body: bool, ts_line: bytes,
                payload: np.ndarray | None, body: Sequence[bytes],
                ts_chars: bytes | None) -> ScanFrame:
    """The checks and decoding of :func:`decode_scan` once the message is split
    (``ts_chars``: the timestamp characters if ``payload`` was verified from ``ts_line``)."""
    try:
        req = _parse_request_cached(echo)
    except (ScipRequestError, ParameterError) as e:
        raise ProtocolError(f"scip scan echo = {echo!r} is invalid; {e}") from None
    if status not in ("00", "99"):
        raise ScipStatusError(_command_code(echo), status, allowed=("00", "99"))
    if not has_body:
        raise ProtocolError(
            f"scip {req.command} reply has no timestamp line; allowed: timestamp + data "
            "(an MD/MS acknowledgement carries no scan)"
        )
    if len(ts_line) != 5:
        raise ProtocolError(f"scip timestamp line = {ts_line!r} is invalid; allowed: 4 chars + sum")
    if payload is None:
        payload = _verify_lines(body)
    # 4 characters: plain Python, not the array path
    ts = _decode_int(payload[:4].tobytes() if ts_chars is None else ts_chars)
    data = payload[4:]
    if data.size % req.n_chars:
        decode_values(data, req.n_chars)  # raises the length error
    ranges = _decode_digits(data, req.n_chars)
    if ranges.size != req.n_values:
        raise ProtocolError(
            f"scip {req.command} value count = {ranges.size} is invalid; "
            f"allowed: {req.n_values} for {req.line()}"
        )
    ranges.setflags(write=False)
    return ScanFrame(request=req, status=status, timestamp_ms=ts, ranges_mm=ranges)


# ---------------------------------------------------------------------------------------
# range error codes (SPEC p.12, Tables 3/4)
# ---------------------------------------------------------------------------------------
RANGE_ERROR_CODES_URG04LX: Mapping[int, str] = {
    0: "no return: object possibly at 22 m",
    1: "reflected intensity too low",
    2: "reflected intensity too low",
    3: "other error",
    4: "other error",
    5: "other error",
    6: "other error",
    7: "distance data on the preceding and succeeding steps have errors",
    8: "intensity difference of two waves",
    9: "the same step had an error in the last two scans",
    **{k: "other error" for k in range(10, 18)},
    18: "error reading due to strong reflective object",
    19: "non-measurable step",
}
RANGE_ERROR_CODES_UTM30LX: Mapping[int, str] = {
    1: "no object in the range",
    2: "object too near",
    3: "measurement error (interference)",
    4: "object out of range (near end)",
    5: "other error",
}


def range_error_mask(ranges_mm: np.ndarray, dmin_mm: int = 20) -> np.ndarray:
    """Boolean mask of error codes (values below DMIN), same shape as ``ranges_mm``."""
    return np.asarray(ranges_mm) < dmin_mm


def range_error_meaning(code: int, model: str = "URG-04LX") -> str:
    """Meaning of one range error code for ``model`` (``"URG-04LX"`` or ``"UTM-30LX"``)."""
    table = RANGE_ERROR_CODES_UTM30LX if model.upper().startswith("UTM") \
        else RANGE_ERROR_CODES_URG04LX
    return table.get(int(code), "undocumented error code")


@dataclass(frozen=True)
class RangePlausibility:
    """Optional second check behind the 6-bit checksums: flags decoded ranges the sensor
    cannot plausibly have measured.

    Why it is needed: a line's sum is the sum of its characters modulo 64, so two
    characters of one line changed by +d and -d (mod 64) keep it - about 3 in 10^5 double
    corruptions pass the checksum (e.g. 529 -> 1233 mm: the middle character of one value
    up by 11, another character of the line down by 11). Such a value is off by a
    multiple of 64 mm (middle character) or 4096 mm (high character).

    A valid value ``v`` (>= DMIN) is flagged if

    * ``v > DMAX``: the device sends an error code there, never a range; or
    * it is an isolated spike - both neighbouring steps valid and ``v`` outside their span
      by ``excess > tol = abs_tol_mm + rel_tol * v`` - that the previous scan does not
      confirm. The previous value ``prev`` at that step confirms it if it is valid, nearer
      to ``v`` than the neighbours' span is (``|v - prev| < excess``; a corrupted value's
      previous one sits with its neighbours) and within the motion allowance
      ``|v - prev| <= tol + max_speed_m_s * period_s``. A thin object or a moving edge
      seen in two scans in a row is kept.

    Not seen: changes below ``tol`` (low-character corruptions of at most 63 mm, within
    the URG-04LX's +-30 mm accuracy at range), a corrupted value next to an error code or
    at the ends of the scan, and values corrupted into error codes (a lost point, not a
    wrong one). Error codes are never flagged.

    Measured (tests/test_scip_codec.py): false positives - on the two real URG-04LX
    captures, which have no previous scan, 1 of 892 checked values (a real 154 mm dip at
    step 63 of capture a); on 99 clean simulated nodding scans of the room (noise on, with
    the previous scan) 19 of 67 517 (2.8e-4; budget 5e-4). Detection - of checksum-passing
    +d/-d character pairs in the real captures that changed a valid value by 64 mm or
    more, 97 % (capture a) and 91 % (capture b) are flagged; the rest sit next to error
    codes or scan edges.

    Parameters
    ----------
    abs_tol_mm : float
        Absolute tolerance [mm] (noise; URG-04LX: +-10 mm to 1 m, 1 % beyond).
    rel_tol : float
        Tolerance as a fraction of the range (noise growing with range, surface slope).
    max_speed_m_s : float
        Fastest plausible change of the range at one step between consecutive scans [m/s]
        (a walking person; the nod moves the scan plane too).
    """

    abs_tol_mm: float = 30.0
    rel_tol: float = 0.03
    max_speed_m_s: float = 2.0

    def __post_init__(self) -> None:
        for name, hi in (("abs_tol_mm", 1e4), ("rel_tol", 1.0), ("max_speed_m_s", 1e3)):
            v = getattr(self, name)
            require(isinstance(v, (int, float)) and not isinstance(v, bool) and 0 <= v <= hi,
                    f"scip.plausibility.{name}", v, f"a number in [0, {hi:g}]")

    def flag(self, ranges_mm: np.ndarray, *, dmin_mm: int, dmax_mm: int,
             previous_mm: np.ndarray | None = None, period_s: float = 0.1) -> np.ndarray:
        """Mask of implausible values.

        Parameters
        ----------
        ranges_mm : numpy.ndarray, shape (n,), int
            Decoded values of one scan [mm or error codes], consecutive steps/clusters.
        dmin_mm, dmax_mm : int
            The device's PP range limits [mm].
        previous_mm : numpy.ndarray, shape (n,), optional
            The previous scan of the same request (same steps), or None.
        period_s : float
            Time between ``previous_mm`` and ``ranges_mm`` [s].

        Returns
        -------
        numpy.ndarray, shape (n,), bool
        """
        r = np.asarray(ranges_mm, dtype=np.float64)
        valid = r >= dmin_mm
        out = valid & (r > dmax_mm)
        if r.size < 3:
            return out
        tol = self.abs_tol_mm + self.rel_tol * r
        left, right = r[:-2], r[2:]
        mid = r[1:-1]
        inner = valid[:-2] & valid[1:-1] & valid[2:]
        # how far the value lies outside its neighbours' span [mm]
        excess = np.maximum(mid - np.maximum(left, right), np.minimum(left, right) - mid)
        spike = inner & (excess > tol[1:-1])
        if previous_mm is not None:
            p = np.asarray(previous_mm, dtype=np.float64)
            if p.shape != r.shape:
                raise ParameterError("scip.plausibility.previous_mm", p.shape,
                                     f"the shape of ranges_mm {r.shape}")
            pm = p[1:-1]
            reach = tol[1:-1] + 1000.0 * self.max_speed_m_s * float(period_s)
            change = np.abs(mid - pm)
            # the previous scan saw the spike too: nearer to it than to the neighbours (a
            # corrupted value's previous one sits with the neighbours), within the motion
            confirmed = (pm >= dmin_mm) & (change <= reach) & (change < excess)
            spike &= ~confirmed
        out[1:-1] |= spike
        return out


def ranges_mm_to_m(ranges_mm: np.ndarray, dmin_mm: int = 20) -> np.ndarray:
    """Ranges [mm] -> [m] float64, NaN where the value is an error code (< DMIN)."""
    r = np.asarray(ranges_mm)
    out = r.astype(np.float64) / 1000.0
    out[r < dmin_mm] = np.nan
    return out


# ---------------------------------------------------------------------------------------
# VV / PP / II
# ---------------------------------------------------------------------------------------
def info_line_verifies(line: bytes) -> bool:
    """Does a VV/PP/II ``KEY:VALUE;S`` line verify under any checksum rule seen on real
    firmware (``;`` excluded as documented; urg_library's n-1/n-2 byte fallbacks; the
    UTM-30LX's excluded ``<-`` comment)?"""
    return _info_line_ok(line)


def _info_line_ok(line: bytes) -> bool:
    """Does a ``KEY:VALUE;S`` line verify under any rule seen on real firmware?"""
    if len(line) < 2:
        return False
    s = line[-1]
    cands = [line[:-1]]  # urg_library fallback: n-1 bytes (with ';')
    if line[-2:-1] == b";":
        content = line[:-2]
        cands.insert(0, content)  # the documented rule: ';' excluded
        j = content.find(b"<-")
        if j >= 0:
            cands.append(content[:j])  # UTM-30LX II: comment excluded
    else:
        cands.append(line[:-2])  # urg_library fallback: n-2 bytes
    return any((sum(c) & 0x3F) + _CHAR0 == s for c in cands)


def parse_info(reply: ScipReply | bytes) -> dict[str, str]:
    """Parse VV/PP/II ``KEY:VALUE;<sum>`` lines into a dict (leniently).

    The status must be ``00``. A line whose sum matches none of the known rules (``;``
    excluded as documented; urg_library's n-1/n-2 byte fallbacks; UTM-30LX's excluded
    ``<-`` comment) is kept but raises a :class:`ScipChecksumWarning`; lines without a
    ``:`` (e.g. a stray ``I`` some firmware sends) are skipped with a warning.
    """
    if not isinstance(reply, ScipReply):
        reply = parse_reply(reply)
    check_status(reply, ("00",))
    out: dict[str, str] = {}
    for line in reply.body:
        if not _info_line_ok(line):
            warnings.warn(
                f"scip {reply.code} line {line!r}: checksum does not verify", ScipChecksumWarning,
                stacklevel=2,
            )
        text = line[:-2] if line[-2:-1] == b";" else line[:-1]
        s = text.decode("ascii", "replace")
        if ":" not in s:
            warnings.warn(f"scip {reply.code} line {line!r} has no KEY:VALUE; skipped",
                          ScipChecksumWarning, stacklevel=2)
            continue
        k, v = s.split(":", 1)
        out[k] = v
    return out


@dataclass(frozen=True)
class VersionInfo:
    """``VV`` reply: vendor, product, firmware, protocol, serial number (+ other keys)."""

    vendor: str
    product: str
    firmware: str
    protocol: str
    serial: str
    extra: Mapping[str, str] = field(default_factory=dict)

    def items(self) -> list[tuple[str, str]]:
        """``(key, value)`` pairs in reply order (for encoding)."""
        return [("VEND", self.vendor), ("PROD", self.product), ("FIRM", self.firmware),
                ("PROT", self.protocol), ("SERI", self.serial), *self.extra.items()]


@dataclass(frozen=True)
class SensorParams:
    """``PP`` reply: model name and the step/range/speed parameters.

    Attributes
    ----------
    model : str
        ``MODL`` text, e.g. ``"URG-04LX(Hokuyo Automatic Co.,Ltd.)"``.
    dmin_mm, dmax_mm : int
        Minimum and maximum measurable range [mm].
    ares : int
        Steps per revolution.
    amin, amax, afrt : int
        First, last and front step.
    scan_rpm : int
        Motor speed [rev/min].
    """

    model: str
    dmin_mm: int
    dmax_mm: int
    ares: int
    amin: int
    amax: int
    afrt: int
    scan_rpm: int
    extra: Mapping[str, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        # Every scan is decoded and timed with these numbers: a device (or a garbled digit
        # that kept its line's sum) reporting SCAN 0 or DMIN >= DMAX would give
        # ZeroDivisionError or all-NaN scans much later. Fields are named as in the reply.
        def need(cond: bool, key: str, value: object, allowed: str) -> None:
            if not cond:
                raise ParameterError(f"scip.PP.{key}", value, allowed)

        for key, v in (("DMIN", self.dmin_mm), ("DMAX", self.dmax_mm), ("ARES", self.ares),
                       ("AMIN", self.amin), ("AMAX", self.amax), ("AFRT", self.afrt),
                       ("SCAN", self.scan_rpm)):
            need(isinstance(v, (int, np.integer)) and not isinstance(v, bool), key, v,
                 "an integer")
        need(self.dmin_mm >= 1, "DMIN", self.dmin_mm, ">= 1 mm")
        need(self.dmin_mm < self.dmax_mm, "DMIN", self.dmin_mm, f"< DMAX ({self.dmax_mm} mm)")
        need(self.dmax_mm <= 64 ** 3 - 1, "DMAX", self.dmax_mm,
             "<= 262143 mm (the 3-character encoding)")
        need(1 <= self.ares <= 9999, "ARES", self.ares, "1..9999 steps per revolution")
        need(0 <= self.amin < self.ares, "AMIN", self.amin, f"0..{self.ares - 1} (ARES - 1)")
        need(self.amin <= self.amax < self.ares, "AMAX", self.amax,
             f"{self.amin}..{self.ares - 1} (AMIN..ARES - 1)")
        need(self.amin <= self.afrt <= self.amax, "AFRT", self.afrt,
             f"{self.amin}..{self.amax} (AMIN..AMAX)")
        need(1 <= self.scan_rpm <= 60_000, "SCAN", self.scan_rpm, "1..60000 rpm")

    @classmethod
    def from_lidar_model(cls, model: LidarModel, modl: str | None = None) -> SensorParams:
        """The PP values a device of ``model`` reports."""
        return cls(
            model=modl or f"{model.name}(Hokuyo Automatic Co.,Ltd.)",
            dmin_mm=round(model.range_min_m * 1000), dmax_mm=round(model.range_max_m * 1000),
            ares=model.steps_per_rev, amin=model.step_min, amax=model.step_max,
            afrt=model.step_front, scan_rpm=round(model.rpm),
        )

    def items(self) -> list[tuple[str, str]]:
        """``(key, value)`` pairs in reply order (for encoding)."""
        return [("MODL", self.model), ("DMIN", str(self.dmin_mm)), ("DMAX", str(self.dmax_mm)),
                ("ARES", str(self.ares)), ("AMIN", str(self.amin)), ("AMAX", str(self.amax)),
                ("AFRT", str(self.afrt)), ("SCAN", str(self.scan_rpm)), *self.extra.items()]

    def to_lidar_model(self, template: LidarModel | None = None) -> LidarModel:
        """A :class:`~nodlidar.lidar.LidarModel` with these parameters (SI units).

        Housing and noise come from ``template``, or from the known model whose name
        starts ``MODL`` (e.g. ``URG-04LX``), else from the URG-04LX.
        """
        if template is None:
            name = self.model.split("(")[0].strip().upper()
            matches = [m for k, m in LIDAR_MODELS.items() if name.startswith(k.upper())]
            template = max(matches, key=lambda m: len(m.name)) if matches \
                else LIDAR_MODELS["URG-04LX"]
        return dataclasses.replace(
            template,
            name=self.model.split("(")[0].strip() or template.name,
            steps_per_rev=self.ares, step_min=self.amin, step_max=self.amax,
            step_front=self.afrt, rpm=float(self.scan_rpm),
            range_min_m=self.dmin_mm / 1000.0, range_max_m=self.dmax_mm / 1000.0,
        )


@dataclass(frozen=True)
class SensorState:
    """``II`` reply: laser, motor speed, measurement mode, bit rate, time, status text."""

    model: str
    laser: str
    motor_speed: str
    measure_mode: str
    bitrate: str
    time: str
    status: str
    extra: Mapping[str, str] = field(default_factory=dict)

    @property
    def laser_on(self) -> bool:
        """True if ``LASR`` reads ON."""
        return self.laser.strip().upper().startswith("ON")

    def items(self) -> list[tuple[str, str]]:
        """``(key, value)`` pairs in reply order (for encoding)."""
        return [("MODL", self.model), ("LASR", self.laser), ("SCSP", self.motor_speed),
                ("MESM", self.measure_mode), ("SBPS", self.bitrate), ("TIME", self.time),
                ("STAT", self.status), *self.extra.items()]


def _take(d: dict[str, str], keys: Sequence[str], what: str) -> tuple[list[str], dict[str, str]]:
    rest = dict(d)
    vals = []
    for k in keys:
        if k not in rest:
            raise ProtocolError(f"scip {what} reply is missing {k}; allowed: all of {list(keys)}")
        vals.append(rest.pop(k))
    return vals, rest


def parse_version(reply: ScipReply | bytes) -> VersionInfo:
    """Parse a ``VV`` reply."""
    vals, rest = _take(parse_info(reply), ("VEND", "PROD", "FIRM", "PROT", "SERI"), "VV")
    vend, prod, firm, prot, seri = vals
    return VersionInfo(vend, prod, firm, prot, seri, extra=rest)


def parse_params(reply: ScipReply | bytes) -> SensorParams:
    """Parse a ``PP`` reply (numbers must be decimal)."""
    keys = ("MODL", "DMIN", "DMAX", "ARES", "AMIN", "AMAX", "AFRT", "SCAN")
    vals, rest = _take(parse_info(reply), keys, "PP")
    nums = []
    for k, v in zip(keys[1:], vals[1:], strict=True):
        try:
            nums.append(int(v.strip()))
        except ValueError:
            raise ProtocolError(f"scip PP {k} = {v!r} is invalid; allowed: an integer") from None
    dmin, dmax, ares, amin, amax, afrt, rpm = nums
    try:
        return SensorParams(vals[0], dmin, dmax, ares, amin, amax, afrt, rpm, extra=rest)
    except ParameterError as e:  # the device's reply, not a caller's argument
        raise ProtocolError(f"{e} (in the device's PP reply)") from None


def parse_state(reply: ScipReply | bytes) -> SensorState:
    """Parse an ``II`` reply (missing keys become ``""``)."""
    d = parse_info(reply)
    keys = ("MODL", "LASR", "SCSP", "MESM", "SBPS", "TIME", "STAT")
    modl, lasr, scsp, mesm, sbps, tim, stat = (d.pop(k, "") for k in keys)
    return SensorState(modl, lasr, scsp, mesm, sbps, tim, stat, extra=d)
