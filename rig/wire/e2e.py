"""End-to-end protection of the rig's CAN frames (AUTOSAR E2E profile 1 style).

Every frame of ``rig/wire/rig.dbc`` carries, in byte 0, a CRC-8 SAE J1850 (polynomial 0x1D,
initial value 0xFF, final XOR 0xFF; check value 0x4B for ``b"123456789"``) computed over
the frame's data ID -- the CAN identifier as two bytes, low byte first -- followed by
payload bytes 1..7.  The low nibble of byte 1 is a rolling counter 0..15.

The CRC is table driven: a 256-entry table for single bytes and a 65536-entry table that
consumes two bytes per lookup, so checking a frame costs one ``struct`` unpack and four
lookups.  :class:`CounterMonitor` classifies a received counter as new, repeated (stuck
sender or duplicated frame) or jumped (frames lost, with how many).
"""

from __future__ import annotations

import struct
from collections.abc import Iterable
from enum import IntEnum
from typing import Final

from rig.wire.dbc_constants import (
    E2E_COUNTER_MAX,
    E2E_CRC_INIT,
    E2E_CRC_POLYNOMIAL,
    E2E_CRC_XOROUT,
)

__all__ = [
    "COUNTER_MODULO",
    "CRC8_CHECK_VALUE",
    "CounterMonitor",
    "CounterStatus",
    "crc8_sae_j1850",
    "frame_crc",
    "frame_crc_start",
    "protect",
]

#: the DBC's E2E attributes (E2ECrcPolynomial, E2ECrcInit, E2ECrcXorOut, E2ECounterMax)
CRC8_POLY: Final = E2E_CRC_POLYNOMIAL
CRC8_INIT: Final = E2E_CRC_INIT
CRC8_XOROUT: Final = E2E_CRC_XOROUT
#: CRC of b"123456789" (AUTOSAR SWS CRC Library, 8-bit SAE J1850 "check" value)
CRC8_CHECK_VALUE: Final = 0x4B
COUNTER_MODULO: Final = E2E_COUNTER_MAX + 1


def _make_table() -> bytes:
    table = bytearray(256)
    for i in range(256):
        c = i
        for _ in range(8):
            c = ((c << 1) ^ CRC8_POLY) & 0xFF if c & 0x80 else (c << 1) & 0xFF
        table[i] = c
    return bytes(table)


#: state' = TABLE[state ^ byte]  (state kept without the final XOR)
CRC8_TABLE: Final[bytes] = _make_table()
#: two bytes per lookup: TABLE2[(state << 8) ^ (b0 << 8 | b1)] == TABLE[TABLE[state^b0]^b1]
CRC8_TABLE2: Final[bytes] = bytes(
    CRC8_TABLE[CRC8_TABLE[x >> 8] ^ (x & 0xFF)] for x in range(65536)
)

_PAYLOAD_WORDS: Final = struct.Struct(">xHHHB")  # bytes 1-2, 3-4, 5-6 as words, byte 7


def crc8_sae_j1850(data: Iterable[int], init: int = CRC8_INIT, xorout: int = CRC8_XOROUT) -> int:
    """CRC-8 SAE J1850 of ``data`` (any iterable of byte values)."""
    t = CRC8_TABLE
    s = init
    for b in data:
        s = t[s ^ b]
    return s ^ xorout


def frame_crc_start(frame_id: int) -> int:
    """CRC state (before the final XOR) after the two data-ID bytes of ``frame_id``."""
    t = CRC8_TABLE
    return t[t[CRC8_INIT ^ (frame_id & 0xFF)] ^ ((frame_id >> 8) & 0xFF)]


def frame_crc(frame_id: int, data: bytes | bytearray | memoryview) -> int:
    """The E2E CRC of an 8-byte frame: data ID, then bytes 1..7 (byte 0 is ignored)."""
    return _crc_from_start(frame_crc_start(frame_id), data)


def _crc_from_start(start: int, data: bytes | bytearray | memoryview) -> int:
    w1, w2, w3, b7 = _PAYLOAD_WORDS.unpack_from(data)
    t2 = CRC8_TABLE2
    s = t2[(start << 8) ^ w1]
    s = t2[(s << 8) ^ w2]
    s = t2[(s << 8) ^ w3]
    return CRC8_TABLE[s ^ b7] ^ CRC8_XOROUT


def protect(frame_id: int, buf: bytearray | memoryview) -> int:
    """Write the E2E CRC of ``buf`` (8 bytes, counter already in byte 1) into ``buf[0]``."""
    crc = frame_crc(frame_id, buf)
    buf[0] = crc
    return crc


class CounterStatus(IntEnum):
    """Outcome of one rolling-counter check (cf. E2E profile 1 check status)."""

    OK = 0  #: exactly the next counter value
    INITIAL = 1  #: first frame seen (or first after :meth:`CounterMonitor.reset`)
    REPEATED = 2  #: same counter as the previous frame: stuck sender or duplicate
    JUMPED = 3  #: counter skipped values: ``lost`` frames are missing


class CounterMonitor:
    """Rolling-counter supervision for one frame stream (counter modulo 16).

    ``check(counter)`` returns a :class:`CounterStatus`; after it, ``lost`` is the number
    of frames missing in front of this one (0 unless JUMPED; a jump of 16 or more frames
    cannot be told from a smaller one -- the stale-frame timeout covers that).  Totals are
    kept in ``repeated_total``, ``jumps_total`` and ``lost_total``.
    """

    __slots__ = ("jumps_total", "last", "lost", "lost_total", "modulo", "repeated_total")

    def __init__(self, modulo: int = COUNTER_MODULO) -> None:
        if modulo < 2:
            raise ValueError(f"counter modulo must be >= 2, got {modulo}")
        self.modulo = modulo
        self.last = -1
        self.lost = 0
        self.repeated_total = 0
        self.jumps_total = 0
        self.lost_total = 0

    def reset(self) -> None:
        """Forget the last counter (the next frame is INITIAL); totals are kept."""
        self.last = -1
        self.lost = 0

    def check(self, counter: int) -> CounterStatus:
        counter %= self.modulo
        last = self.last
        self.last = counter
        self.lost = 0
        if last < 0:
            return CounterStatus.INITIAL
        delta = (counter - last) % self.modulo
        if delta == 1:
            return CounterStatus.OK
        if delta == 0:
            self.repeated_total += 1
            return CounterStatus.REPEATED
        self.lost = delta - 1
        self.jumps_total += 1
        self.lost_total += delta - 1
        return CounterStatus.JUMPED
