"""End-to-end protection of feedback frames: CRC-8 SAE J1850 and a 4-bit alive counter.

The default DBC (``dbc/canrls.dbc``) protects ``DriveCurrent`` and ``DriveSpeed``
the way AUTOSAR E2E profile 1 does: byte 0 holds a CRC-8 over the frame ID and the
rest of the payload, and a 4-bit counter increments by one (mod 16) per frame.

.. math::

    \\mathrm{crc} = \\mathrm{CRC8}_{0x1D}(\\mathrm{id}_{lo}, \\mathrm{id}_{hi},
                                   d_1, \\ldots, d_{n-1})

with initial value 0xFF and final XOR 0xFF (check value ``CRC8(b"123456789") == 0x4B``).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

__all__ = ["CRC8_TABLE", "crc8", "e2e_crc", "COUNTER_MODULO"]

COUNTER_MODULO = 16
_POLY = 0x1D


def _make_table() -> npt.NDArray[np.uint8]:
    table = np.zeros(256, dtype=np.uint8)
    for byte in range(256):
        c = byte
        for _ in range(8):
            c = ((c << 1) ^ _POLY) & 0xFF if c & 0x80 else (c << 1) & 0xFF
        table[byte] = c
    return table


#: Lookup table of CRC-8 SAE J1850 (polynomial 0x1D), one entry per byte value.
CRC8_TABLE: npt.NDArray[np.uint8] = _make_table()
_TABLE = [int(v) for v in CRC8_TABLE]


def crc8(data: bytes | bytearray | memoryview, init: int = 0xFF, xorout: int = 0xFF) -> int:
    """CRC-8 SAE J1850 of ``data`` (poly 0x1D, init 0xFF, xorout 0xFF)."""
    c = init
    for b in bytes(data):
        c = _TABLE[c ^ b]
    return c ^ xorout


def e2e_crc(frame_id: int, payload: bytes | bytearray) -> int:
    """The CRC byte of a protected frame.

    Computed over the frame ID (2 bytes, little endian), then payload bytes 1 and on.
    """
    head = bytes((frame_id & 0xFF, (frame_id >> 8) & 0xFF))
    return crc8(head + bytes(payload[1:]))
