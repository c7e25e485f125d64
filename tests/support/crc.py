"""Independent references for the wire tests: a bitwise CRC-8 SAE J1850 (rig.wire.e2e uses
tables) and frames encoded by cantools (the reference DBC codec) with that CRC."""

from __future__ import annotations

from typing import Any


def crc8_bitwise(data: bytes, init: int = 0xFF, xorout: int = 0xFF) -> int:
    """Independent reference: MSB-first shift register, polynomial x^8+x^4+x^3+x^2+1."""
    reg = init
    for byte in data:
        for bit in range(7, -1, -1):
            top = ((reg >> 7) & 1) ^ ((byte >> bit) & 1)
            reg = (reg << 1) & 0xFF
            if top:
                reg ^= 0x1D
    return reg ^ xorout


def with_crc(frame_id: int, payload: bytes) -> bytes:
    """``payload`` with its byte 0 replaced by the E2E CRC over the frame ID (little endian,
    2 bytes) and bytes 1-7."""
    return bytes([crc8_bitwise(bytes([frame_id & 0xFF, frame_id >> 8]) + payload[1:])]) \
        + payload[1:]


def ref_encode(db: Any, frame_id: int, signals: dict[str, Any]) -> bytes:
    """The frame encoded by cantools from ``db`` (a loaded DBC) with the E2E CRC of the
    bitwise reference (the CRC is the frame's first signal)."""
    msg = db.get_message_by_frame_id(frame_id)
    crc_name = msg.signals[0].name
    body = bytes(msg.encode({**signals, crc_name: 0}, scaling=True, strict=True))
    return bytes(msg.encode({**signals, crc_name: with_crc(frame_id, body)[0]}, scaling=True,
                            strict=True))
