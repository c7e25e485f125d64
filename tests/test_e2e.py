"""E2E protection: CRC-8 SAE J1850 against the AUTOSAR check values and a bitwise
reference, single-byte error detection, rolling-counter supervision."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from rig.wire.e2e import (
    CRC8_CHECK_VALUE,
    CRC8_TABLE,
    CRC8_TABLE2,
    CounterMonitor,
    CounterStatus,
    crc8_sae_j1850,
    frame_crc,
    protect,
)
from tests.support.crc import crc8_bitwise

# AUTOSAR SWS CRC Library, "8-bit SAE J1850 CRC Calculation" check table
AUTOSAR_CHECKS = [
    ("00000000", 0x59),
    ("F20183", 0x37),
    ("0FAA0055", 0x79),
    ("00FF5511", 0xB8),
    ("332255AABBCCDDEEFF", 0xCB),
    ("926B55", 0x8C),
    ("FFFFFFFF", 0x74),
]


def test_check_value_123456789() -> None:
    assert CRC8_CHECK_VALUE == 0x4B
    assert crc8_sae_j1850(b"123456789") == 0x4B
    assert crc8_bitwise(b"123456789") == 0x4B


@pytest.mark.parametrize(("hexdata", "expected"), AUTOSAR_CHECKS)
def test_autosar_check_table(hexdata: str, expected: int) -> None:
    data = bytes.fromhex(hexdata)
    assert crc8_sae_j1850(data) == expected
    assert crc8_bitwise(data) == expected


def test_tables_consistent_with_bitwise() -> None:
    for i in range(256):
        # one byte from state i with no init/xor: the table entry
        assert CRC8_TABLE[i] == crc8_bitwise(bytes([i]), init=0, xorout=0)
    for x in range(0, 65536, 257):
        s = CRC8_TABLE[CRC8_TABLE[x >> 8] ^ (x & 0xFF)]
        assert CRC8_TABLE2[x] == s


@given(st.binary(max_size=80))
def test_table_crc_matches_bitwise(data: bytes) -> None:
    assert crc8_sae_j1850(data) == crc8_bitwise(data)


@given(st.integers(0, 0x7FF), st.binary(min_size=8, max_size=8))
def test_frame_crc_is_crc_over_data_id_and_bytes_1_to_7(frame_id: int, data: bytes) -> None:
    expected = crc8_bitwise(bytes([frame_id & 0xFF, frame_id >> 8]) + data[1:])
    assert frame_crc(frame_id, data) == expected
    buf = bytearray(data)
    assert protect(frame_id, buf) == expected
    assert buf[0] == expected and buf[1:] == data[1:]


@given(st.integers(0, 0x7FF), st.binary(min_size=8, max_size=8), st.integers(0, 7),
       st.integers(1, 255))
def test_every_single_byte_error_detected(frame_id: int, data: bytes, pos: int,
                                          flip: int) -> None:
    buf = bytearray(data)
    protect(frame_id, buf)
    buf[pos] ^= flip
    assert buf[0] != frame_crc(frame_id, buf)


def test_data_id_masquerade_detected() -> None:
    ids = [0x080, 0x081, 0x100, 0x200, 0x300]
    payload = bytearray(b"\x00\x15\x22\x33\x44\x55\x66\x77")
    for a in ids:
        protect(a, payload)
        for b in ids:
            if b != a:
                assert frame_crc(b, payload) != payload[0]


def test_counter_sequence_with_wraparound() -> None:
    mon = CounterMonitor()
    assert mon.check(14) is CounterStatus.INITIAL
    assert mon.check(15) is CounterStatus.OK
    assert mon.check(0) is CounterStatus.OK  # wrap 15 -> 0
    assert mon.check(1) is CounterStatus.OK
    assert mon.lost == 0 and mon.lost_total == 0


def test_counter_stuck_and_jump() -> None:
    mon = CounterMonitor()
    mon.check(3)
    assert mon.check(3) is CounterStatus.REPEATED
    assert mon.check(3) is CounterStatus.REPEATED
    assert mon.repeated_total == 2
    assert mon.check(6) is CounterStatus.JUMPED
    assert mon.lost == 2
    assert mon.check(7) is CounterStatus.OK and mon.lost == 0
    assert mon.check(1) is CounterStatus.JUMPED  # across the wrap: 8..15, 0 lost
    assert mon.lost == 9
    assert mon.lost_total == 11 and mon.jumps_total == 2
    mon.reset()
    assert mon.check(9) is CounterStatus.INITIAL
    assert mon.lost_total == 11


@given(st.integers(0, 15), st.integers(0, 15))
def test_counter_lost_is_modular_gap(first: int, second: int) -> None:
    mon = CounterMonitor()
    mon.check(first)
    status = mon.check(second)
    gap = (second - first) % 16
    if gap == 0:
        assert status is CounterStatus.REPEATED
    elif gap == 1:
        assert status is CounterStatus.OK
    else:
        assert status is CounterStatus.JUMPED and mon.lost == gap - 1


@given(st.lists(st.booleans(), max_size=200), st.integers(0, 15))
def test_counter_lost_total_counts_dropped_frames(drops: list[bool], start: int) -> None:
    """A sender counting every frame; the receiver sees only the kept ones (runs of up
    to 14 drops, then a kept frame -- longer runs alias modulo 16)."""
    mon = CounterMonitor()
    mon.check(start)
    counter = start
    dropped = run = 0
    for drop in [*drops, False]:
        counter = (counter + 1) % 16
        if drop and run < 14:
            dropped += 1
            run += 1
            continue
        run = 0
        mon.check(counter)
    assert mon.lost_total == dropped
    assert mon.repeated_total == 0
