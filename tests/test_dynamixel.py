"""Protocol 2.0 codec: CRC, byte stuffing, frame parsing and resync, unit conversions."""

from __future__ import annotations

import math
import random

import numpy as np
import pytest

from nodlidar import dynamixel as dx
from nodlidar.errors import ParameterError, ProtocolError

# Examples from the ROBOTIS Protocol 2.0 e-manual.
PING_ID1 = bytes.fromhex("FF FF FD 00 01 03 00 01 19 4E")
READ_ID1_132_4 = bytes.fromhex("FF FF FD 00 01 07 00 02 84 00 04 00 1D 15")


def test_crc_of_manual_ping_example():
    assert dx.crc16(PING_ID1[:-2]) == 0x4E19
    assert dx.ping_packet(1).encode() == PING_ID1


def test_crc_of_manual_read_example():
    assert dx.read_packet(1, 132, 4).encode() == READ_ID1_132_4


def test_crc_is_incremental():
    data = bytes(range(200))
    assert dx.crc16(data[100:], dx.crc16(data[:100])) == dx.crc16(data)


def test_decode_round_trip_instruction_and_status():
    pkt = dx.decode_packet(READ_ID1_132_4)
    assert pkt == dx.InstructionPacket(1, dx.Instruction.READ, bytes([0x84, 0, 4, 0]))
    st = dx.StatusPacket(1, 0, dx.encode_value(-1234, 4, signed=True))
    back = dx.decode_packet(st.encode())
    assert isinstance(back, dx.StatusPacket)
    assert back == st
    assert dx.decode_value(back.params, signed=True) == -1234
    assert back.error_code is dx.ErrorCode.NONE and not back.alert


def test_status_error_bits():
    st = dx.decode_packet(dx.StatusPacket(3, 0x80 | dx.ErrorCode.DATA_LIMIT).encode())
    assert st.alert and st.error_code is dx.ErrorCode.DATA_LIMIT


@pytest.mark.parametrize(
    "body",
    [
        b"\xff\xff\xfd",
        b"\xff\xff\xfd\xfd",
        b"\xff\xff\xfd\xff\xff\xfd",
        b"\x00\xff\xff\xff\xfd\x01",
        b"\xff\xff\xfd\x00\xff\xff\xfd\xfd\xfd",
        b"",
        b"\x01\x02",
    ],
)
def test_stuffing_round_trip(body):
    stuffed = dx.stuff(body)
    assert dx.unstuff(stuffed) == body
    # a stuffed body never contains the header pattern FF FF FD followed by non-FD
    for i in range(len(stuffed) - 3):
        if stuffed[i : i + 3] == b"\xff\xff\xfd":
            assert stuffed[i + 3] == 0xFD


def test_stuffing_changes_length_field_and_survives_the_wire():
    data = b"\xff\xff\xfd\x11"
    frame = dx.write_packet(7, 116, data).encode()
    assert b"\xff\xff\xfd\xfd" in frame[7:]
    assert frame[5] | (frame[6] << 8) == len(frame) - 7
    pkt = dx.decode_packet(frame)
    assert pkt.params[2:] == data


def test_random_payload_round_trips():
    rng = random.Random(1)
    for _ in range(300):
        n = rng.randrange(0, 40)
        params = bytes(rng.choice([0xFF, 0xFD, 0x00, rng.randrange(256)]) for _ in range(n))
        frame = dx.encode_packet(5, dx.Instruction.WRITE, params)
        assert dx.decode_packet(frame).params == params


def test_unstuff_rejects_unstuffed_pattern():
    with pytest.raises(ProtocolError, match="packet.body"):
        dx.unstuff(b"\xff\xff\xfd\x01")


def test_parser_resyncs_on_garbage_and_split_input():
    frames = [dx.ping_packet(1).encode(), dx.read_packet(2, 132, 4).encode()]
    stream = b"\x00\xff\xff\x13garbage\xff\xff\xfd" + frames[0] + b"\xff\xff" + frames[1]
    parser = dx.PacketParser()
    got = []
    for i in range(0, len(stream), 3):  # arrive in small pieces
        parser.feed(stream[i : i + 3])
        got += list(parser.packets())
    assert [p.encode() for p in got] == frames
    assert parser.garbage_bytes > 0
    assert parser.pending == 0


def test_parser_rejects_bad_crc_then_continues():
    good = dx.ping_packet(2).encode()
    bad = bytearray(dx.ping_packet(1).encode())
    bad[-1] ^= 0x55
    parser = dx.PacketParser()
    parser.feed(bytes(bad) + good)
    with pytest.raises(dx.CrcError) as ei:
        parser.next_packet()
    assert ei.value.packet_id == 1
    assert isinstance(ei.value, ProtocolError)
    assert "packet.crc" in str(ei.value)
    assert parser.next_packet() == dx.ping_packet(2)
    assert parser.next_packet() is None
    assert parser.crc_errors == 1


def test_parser_skips_absurd_length():
    good = dx.ping_packet(3).encode()
    parser = dx.PacketParser()
    parser.feed(b"\xff\xff\xfd\x00\x01\xff\xff" + good)
    assert list(parser.packets()) == [dx.ping_packet(3)]


def test_parser_waits_for_partial_frame():
    frame = dx.read_packet(1, 0, 2).encode()
    parser = dx.PacketParser()
    parser.feed(frame[:-1])
    assert parser.next_packet() is None
    parser.feed(frame[-1:])
    assert parser.next_packet() == dx.read_packet(1, 0, 2)


def test_decode_packet_errors():
    with pytest.raises(ProtocolError, match="packet.frame"):
        dx.decode_packet(b"\x00\x01\x02")
    with pytest.raises(ProtocolError, match="packet.length"):
        dx.decode_packet(PING_ID1 + b"\x00")
    with pytest.raises(dx.CrcError):
        dx.decode_packet(PING_ID1[:-1] + b"\x00")


def test_sync_packets_layout():
    sr = dx.sync_read_packet(132, 4, [1, 2, 3])
    assert sr.id == dx.BROADCAST_ID and sr.params == bytes([132, 0, 4, 0, 1, 2, 3])
    sw = dx.sync_write_packet(116, 4, {1: b"\x00\x08\x00\x00", 2: b"\x01\x08\x00\x00"})
    assert sw.params == bytes([116, 0, 4, 0, 1, 0, 8, 0, 0, 2, 1, 8, 0, 0])
    with pytest.raises(ParameterError, match=r"sync_write.data\[1\]"):
        dx.sync_write_packet(116, 4, {1: b"\x00"})


def test_packet_validation():
    with pytest.raises(ParameterError, match="packet.id"):
        dx.InstructionPacket(253, dx.Instruction.PING)
    with pytest.raises(ParameterError, match="status.id"):
        dx.StatusPacket(dx.BROADCAST_ID)
    with pytest.raises(ParameterError, match="packet.instruction"):
        dx.InstructionPacket(1, 0x55)


def test_control_table_addresses():
    t = dx.CONTROL_TABLE
    expect = {
        "model_number": (0, 2),
        "firmware_version": (6, 1),
        "id": (7, 1),
        "baud_rate": (8, 1),
        "operating_mode": (11, 1),
        "velocity_limit": (44, 4),
        "max_position_limit": (48, 4),
        "min_position_limit": (52, 4),
        "torque_enable": (64, 1),
        "led": (65, 1),
        "profile_velocity": (112, 4),
        "goal_position": (116, 4),
        "realtime_tick": (120, 2),
        "moving": (122, 1),
        "present_velocity": (128, 4),
        "present_position": (132, 4),
    }
    for name, (addr, size) in expect.items():
        assert (t[name].address, t[name].size) == (addr, size)
    items = sorted(t.values(), key=lambda i: i.address)
    for a, b in zip(items, items[1:], strict=False):
        assert a.end <= b.address  # no overlaps
    assert items[-1].end <= dx.CONTROL_TABLE_SIZE
    assert t["id"].eeprom and not t["goal_position"].eeprom
    with pytest.raises(ParameterError, match="control.item"):
        dx.item("nope")


def test_encode_value_range():
    assert dx.encode_value(2048, 4) == b"\x00\x08\x00\x00"
    assert dx.decode_value(dx.encode_value(-5, 4, signed=True), signed=True) == -5
    with pytest.raises(ParameterError, match="control.value"):
        dx.encode_value(256, 1)


def test_unit_conversions():
    assert dx.ticks_to_rad(2048) == 0.0
    assert dx.ticks_to_rad(3072) == pytest.approx(math.pi / 2)
    assert dx.rad_to_ticks(-math.pi / 2) == 1024
    arr = dx.ticks_to_rad(np.array([0, 2048, 4096]))
    np.testing.assert_allclose(arr, [-math.pi, 0, math.pi])
    np.testing.assert_array_equal(dx.rad_to_ticks(arr), [0, 2048, 4096])
    assert dx.velocity_raw_to_rad_s(1) == pytest.approx(0.229 * 2 * math.pi / 60)
    assert dx.rad_s_to_velocity_raw(dx.velocity_raw_to_rad_s(123)) == 123
    assert isinstance(dx.rad_to_ticks(0.1), int)
