"""An independent CRC-8 SAE J1850 reference for the wire tests (rig.wire.e2e uses tables)."""

from __future__ import annotations


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
