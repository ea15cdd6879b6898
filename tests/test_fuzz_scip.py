"""Fuzz tests of the SCIP 2.0 codec and framer (issue 15), with a fixed budget.

Properties:

* every malformed byte sequence gives a typed error - ``ProtocolError`` (the codec) or
  another :class:`~nodlidar.errors.NodlidarError` - never ``UnicodeDecodeError``,
  ``IndexError``, ``ValueError`` ...;
* the framer never raises, its buffer stays within ``max_buffer``, everything it yields
  verifies, and valid messages after any junk (closed by ``LF LF``) come through intact;
* the mutation corpus of the real URG-04LX captures (tests/data/urg04lx-captures, every
  single-byte substitution) is accepted only when the decoded data is unchanged.

Hypothesis runs derandomized (the same examples every run) with ``max_examples`` sized
for a few seconds in all: the "scip-fuzz" settings profile below.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from nodlidar import scip
from nodlidar.errors import NodlidarError, ProtocolError
from nodlidar.lidar import lidar_model
from nodlidar.sim.clock import ManualClock
from nodlidar.sim.scip_emulator import ScipDevice

settings.register_profile(
    "scip-fuzz", derandomize=True, max_examples=100, deadline=None, database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
FUZZ = settings.get_profile("scip-fuzz")

CAPTURES = Path(__file__).resolve().parent / "data" / "urg04lx-captures"
RAW = {name: (CAPTURES / f"capture-{name}-gd0044072501.bin").read_bytes() for name in "ab"}

# --- strategies ------------------------------------------------------------------------
#: pieces that make a parser take its less travelled paths
TOKENS = [b"\n", b"\n\n", b"\r", b"GD", b"MD", b"GS", b"MS", b"VV", b"PP", b"II", b"BM", b"QT",
          b"TM1", b"SCIP2.0", b"%ST", b"0044072501", b"0044072501000", b";", b";tag",
          b"00P", b"99b", b"9yb", b"p0P", b"\xb00P", b"0Ee", b"E", b"m2@0?", b"000", b"ooo",
          b"0" * 64, b"KEY:VALUE;", b":", b"\x00", b"\xff", b"\x80", b"o", b"p", b"/"]

token_soup = st.lists(st.one_of(st.sampled_from(TOKENS), st.binary(max_size=8)),
                      max_size=40).map(b"".join)
any_bytes = st.one_of(st.binary(max_size=300), token_soup)


@st.composite
def scan_messages(draw) -> bytes:
    """A valid GD/GS/MD/MS scan message (random request, values, timestamp, tag)."""
    cmd = draw(st.sampled_from(["GD", "GS", "MD", "MS"]))
    start = draw(st.integers(0, 1080))
    end = draw(st.integers(start, min(start + 700, 1080)))
    cluster = draw(st.integers(0, 99))
    multi = cmd in ("MD", "MS")
    tag = draw(st.one_of(st.none(), st.text("abcXYZ019 ._+@", max_size=16)))
    req = scip.DistanceRequest(cmd, start, end, cluster, draw(st.integers(0, 9)) if multi
                               else None, draw(st.integers(0, 99)) if multi else None, tag)
    top = 4095 if req.n_chars == 2 else 262143
    seed = draw(st.integers(0, 2**32 - 1))
    values = np.random.default_rng(seed).integers(0, top + 1, req.n_values)
    ts = draw(st.integers(0, (1 << 24) - 1))
    remaining = draw(st.integers(0, 99)) if multi else None
    return scip.encode_scan_reply(req.echo(remaining), "99" if multi else "00", ts, values,
                                  req.n_chars)


@st.composite
def other_messages(draw) -> bytes:
    """A valid reply that is not a scan: simple statuses, TM1, VV/PP/II, SCIP 1.1."""
    kind = draw(st.sampled_from(["simple", "tm1", "info", "scip1"]))
    if kind == "simple":
        return scip.encode_message(draw(st.sampled_from(["BM", "QT", "RS", "XX", "SCIP2.0"])),
                                   draw(st.sampled_from(["00", "02", "0E", "10"])))
    if kind == "tm1":
        t = draw(st.integers(0, (1 << 24) - 1))
        return scip.encode_message("TM1", "00", [scip.with_checksum(scip.encode_value(t, 4))])
    if kind == "info":
        return scip.encode_info_reply("PP", scip.SensorParams.from_lidar_model(
            lidar_model(draw(st.sampled_from(["URG-04LX", "UTM-30LX"])))).items())
    return scip.encode_message("QT", "E", scip1=True)


valid_messages = st.one_of(scan_messages(), other_messages())


def _decoded(msg: bytes) -> tuple[int, list[int], list[int]]:
    f = scip.decode_scan(msg)
    return f.timestamp_ms, f.ranges_mm.tolist(), f.steps.tolist()


# --- the codec: only typed errors ------------------------------------------------------
@FUZZ
@given(any_bytes)
def test_parse_reply_raises_only_protocol_error(data):
    try:
        r = scip.parse_reply(data)
    except ProtocolError:
        return
    assert isinstance(r.echo, str) and isinstance(r.status, str)


@FUZZ
@given(st.one_of(any_bytes, scan_messages()))
def test_decode_scan_raises_only_typed_errors(data):
    try:
        f = scip.decode_scan(data)
    except NodlidarError:
        return
    assert f.ranges_mm.size == f.request.n_values


@FUZZ
@given(any_bytes)
def test_info_parsers_raise_only_typed_errors(data):
    for parse in (scip.parse_params, scip.parse_version, scip.parse_state):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", scip.ScipChecksumWarning)
            try:
                parse(b"PP\n00P\n" + data + b"\n\n")
                parse(data)
            except NodlidarError:
                pass


@FUZZ
@given(st.binary(max_size=64), st.integers(1, 4), st.lists(st.binary(max_size=70), max_size=4))
def test_value_decoders_raise_only_protocol_error(data, n_chars, lines):
    try:
        v = scip.decode_values(data, n_chars)
        assert v.size == len(data) // n_chars
    except ProtocolError:
        pass
    try:
        scip.decode_data_block(lines, 3)
    except ProtocolError:
        pass
    try:
        scip.parse_status_line(data)
    except ProtocolError:
        pass
    for chars in (data[:5], data[:4].decode("latin-1")):
        try:
            scip.decode_value(chars)
        except ProtocolError:
            pass


@FUZZ
@given(st.one_of(any_bytes, st.text(max_size=40)))
def test_request_parser_raises_only_typed_errors(line):
    scip.split_command(line)  # never raises
    try:
        req = scip.DistanceRequest.parse(line)
    except scip.ScipRequestError as e:
        assert isinstance(e, ProtocolError) and len(e.status) == 2
        return
    assert req.encode().rstrip(b"\n") in (line if isinstance(line, bytes)
                                          else line.encode()).replace(b"\r", b"\n")


@FUZZ
@given(any_bytes)
def test_emulator_command_parser_never_raises(line):
    """The emulated device answers any line (as its host would send it) with complete
    messages, and never raises."""
    dev = ScipDevice(lidar_model("URG-04LX"), ManualClock())
    for part in line.replace(b"\r", b"\n").split(b"\n"):
        for msg in dev.handle_line(part, 0.0):
            assert msg.endswith(b"\n\n")


# --- mutations of valid messages --------------------------------------------------------
@FUZZ
@given(scan_messages(), st.data())
def test_single_substitution_accepted_only_with_the_same_data(msg, data):
    """One byte replaced anywhere in a valid scan message: a typed error, or the same
    timestamp, ranges and steps (e.g. cluster 01 -> 00, a tag character)."""
    pos = data.draw(st.integers(0, len(msg) - 1))
    new = data.draw(st.integers(0, 255).filter(lambda v: v != msg[pos]))
    bad = msg[:pos] + bytes((new,)) + msg[pos + 1:]
    try:
        got = _decoded(bad)
    except NodlidarError:
        return
    assert got == _decoded(msg)


@FUZZ
@given(scan_messages(), st.lists(st.tuples(st.integers(0, 10_000), st.integers(0, 255),
                                           st.sampled_from(["sub", "ins", "del"])),
                                 min_size=1, max_size=6))
def test_mutated_messages_raise_only_typed_errors(msg, edits):
    b = bytearray(msg)
    for pos, value, op in edits:
        pos %= len(b) + (op == "ins")
        if op == "sub" and b:
            b[pos % len(b)] = value
        elif op == "ins":
            b.insert(pos, value)
        elif b:
            del b[pos % len(b)]
    try:
        scip.decode_scan(bytes(b))
    except NodlidarError:
        pass
    framer = scip.ScipFramer()
    for m in framer.feed(bytes(b)):
        scip.parse_reply(m)  # whatever the framer yields verifies
    assert framer.pending <= framer.max_buffer


def _general_outcome(msg: bytes) -> tuple:
    """decode_scan of the parsed reply: the general path (no device-layout shortcut)."""
    try:
        f = scip.decode_scan(scip.parse_reply(msg))
    except NodlidarError as e:
        return type(e).__name__, str(e)
    return f.request, f.status, f.timestamp_ms, f.ranges_mm.tolist(), f.ranges_mm.dtype


def _frame_outcome(f: scip.ScanFrame) -> tuple:
    return f.request, f.status, f.timestamp_ms, f.ranges_mm.tolist(), f.ranges_mm.dtype


@FUZZ
@given(scan_messages(), st.lists(st.tuples(st.integers(0, 10_000), st.integers(1, 255),
                                           st.booleans()), max_size=4))
def test_device_fast_path_agrees_with_the_general_path(msg, edits):
    """decode_scan(bytes) takes a shortcut for messages as a device sends them
    (scip._device_scan, issue 16): it must take it for every valid scan message, and on
    changed bytes - each by +d, some with the next byte by -d so that a line's sum holds -
    either decline (None) or return exactly what the general path returns; decode_scan of
    the bytes always returns or raises what the general path does."""
    fast = scip._device_scan(msg)
    assert fast is not None and _frame_outcome(fast) == _general_outcome(msg)
    b = bytearray(msg)
    for pos, d, paired in edits:
        pos %= len(b)
        b[pos] = (b[pos] + d) % 256
        if paired and pos + 1 < len(b):
            b[pos + 1] = (b[pos + 1] - d) % 256
    bad = bytes(b)
    want = _general_outcome(bad)
    fast = scip._device_scan(bad)
    if fast is not None:
        assert _frame_outcome(fast) == want
    try:
        got = _frame_outcome(scip.decode_scan(bad))
    except NodlidarError as e:
        got = type(e).__name__, str(e)
    assert got == want


# --- the framer ------------------------------------------------------------------------
@FUZZ
@given(st.lists(st.one_of(valid_messages, any_bytes), max_size=12), st.lists(valid_messages,
       min_size=1, max_size=4), st.lists(st.integers(1, 4000), max_size=20),
       st.sampled_from([256, 4096, 1 << 16]))
def test_framer_bounded_and_resyncs_after_any_junk(prefix, tail, cuts, max_buffer):
    """Any mix of messages and junk, fed in arbitrary pieces: the framer never raises,
    keeps at most ``max_buffer`` bytes, yields only messages that verify, and once the
    junk is closed by LF LF every following valid message comes through intact."""
    stream = b"".join(prefix) + b"\n\n" + b"".join(tail)
    framer = scip.ScipFramer(max_buffer=max_buffer)
    out: list[bytes] = []
    pos = 0
    for cut in [*cuts, len(stream)]:
        piece = stream[pos:pos + cut]
        pos += len(piece)
        out += framer.feed(piece)
        assert framer.pending <= max_buffer
    out += framer.feed(stream[pos:])
    for m in out:
        scip.parse_reply(m)
    if all(len(m) <= max_buffer for m in tail):
        assert out[len(out) - len(tail):] == tail
    assert framer.pending == 0  # the stream ends with a complete message


# --- the mutation corpus of the real captures -------------------------------------------
def _substitutions(raw: bytes, values_for) -> tuple[int, int, int]:
    """Decode every substitution ``raw[p] -> v`` for v in ``values_for(raw[p])``, and feed
    it to a fresh framer (and what it yields to the decoder); assert only typed errors,
    and acceptance only with the same data. Returns (mutants, accepted by the decoder,
    accepted by framer + decoder)."""
    ref = _decoded(raw)
    b = bytearray(raw)
    n = dec_ok = fr_ok = 0
    for p, old in enumerate(raw):
        for v in values_for(old):
            b[p] = v
            mutant = bytes(b)
            n += 1
            try:
                got = _decoded(mutant)
            except NodlidarError:
                got = None
            if got is not None:
                assert got == ref, (p, old, v)
                dec_ok += 1
            framed = scip.ScipFramer().feed(mutant)
            assert len(framed) <= 1
            if framed:  # framed (every sum verifies); the decoder may still refuse it
                try:
                    got = _decoded(framed[0])
                except NodlidarError:
                    continue
                assert got == ref, (p, old, v)
                fr_ok += 1
        b[p] = old
    return n, dec_ok, fr_ok


def _same_sum(old: int) -> list[int]:
    """Every other byte value with the same 6-bit contribution to a line's sum (old +-
    0x40, 0x80, 0xC0): the only single substitutions a line checksum cannot see."""
    return [(old + k * 0x40) % 256 for k in (1, 2, 3)]


@pytest.mark.parametrize("name", ["a", "b"])
def test_mutation_corpus_checksum_invisible_substitutions(name):
    """Each byte of each real capture replaced by the three values that keep its line's
    sum (6 402 mutants per capture): none is accepted (the echo has no sum, but a digit
    +-0x40 is no digit, and a status, data or timestamp byte +-0x40 leaves 0-9A-Z or
    '0'..'o')."""
    n, dec_ok, fr_ok = _substitutions(RAW[name], _same_sum)
    assert n == 3 * len(RAW[name])
    assert dec_ok == fr_ok == 0


@pytest.mark.slow
@pytest.mark.timeout(1800)
@pytest.mark.parametrize("name", ["a", "b"])
def test_mutation_corpus_every_single_byte_substitution(name):
    """Every single-byte substitution of each real capture (2134 x 255 = 544 170 mutants
    per capture), through the decoder and the framer: only typed errors; accepted only
    with unchanged data - exactly once, the cluster field '01' -> '00' (0 means 1)."""
    n, dec_ok, fr_ok = _substitutions(RAW[name], lambda old: [v for v in range(256)
                                                              if v != old])
    assert n == 255 * len(RAW[name])
    assert dec_ok == fr_ok == 1
