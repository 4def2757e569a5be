"""Byte-level framing: header, CRC-32 trailer and COBS with a 0x00 delimiter.

Frame on the wire:  COBS(header | payload | crc32_le) 0x00   (PROTOCOL.md, "Framing").
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass

from cobs import cobs

from .errors import CobsError, CrcError, IncompatibleFlagsError, LengthError, VersionError
from .layout import HEADER_LAYOUT, fixed_struct

PROTOCOL_MAJOR = 1
PROTOCOL_MINOR = 0

DELIMITER = b"\x00"
HEADER = fixed_struct(HEADER_LAYOUT)  # version, incompat_flags, compat_flags, msg_type, seq, payload_len
HEADER_SIZE = HEADER.size  # 8
CRC_SIZE = 4
MAX_PAYLOAD = 40960
MAX_RAW_FRAME = HEADER_SIZE + MAX_PAYLOAD + CRC_SIZE
MIN_RAW_FRAME = HEADER_SIZE + CRC_SIZE
# COBS adds at most one byte per 254 bytes (and one for an empty input).
MAX_ENCODED_BODY = MAX_RAW_FRAME + MAX_RAW_FRAME // 254 + 1
MIN_ENCODED_BODY = MIN_RAW_FRAME + 1

# Compatible flags (a reader ignores bits it does not know).
COMPAT_EXTENDED_PAYLOAD = 0x01  # payload carries fields appended by a later minor version
KNOWN_COMPAT_FLAGS = COMPAT_EXTENDED_PAYLOAD
# Incompatible flags (a reader drops frames with bits it does not know). None defined in 1.x.
KNOWN_INCOMPAT_FLAGS = 0x00

_U32_LE = struct.Struct("<I")


def crc32(data: bytes | bytearray | memoryview) -> int:
    """CRC-32/IEEE 802.3 (reflected, poly 0x04C11DB7, init and xorout 0xFFFFFFFF)."""
    return zlib.crc32(data) & 0xFFFFFFFF


@dataclass(frozen=True, slots=True)
class Header:
    version: int
    incompat_flags: int
    compat_flags: int
    msg_type: int
    seq: int
    payload_len: int


def _check_u8(name: str, value: int) -> None:
    if not isinstance(value, int) or not 0 <= value <= 0xFF:
        raise ValueError(f"{name} must be an integer in 0..255, got {value!r}")


def encode_body(
    msg_type: int,
    seq: int,
    payload: bytes | bytearray | memoryview,
    *,
    compat_flags: int = 0,
    incompat_flags: int = 0,
    version: int = PROTOCOL_MAJOR,
) -> bytes:
    """Build the on-wire bytes of one frame, trailing 0x00 delimiter included."""
    _check_u8("msg_type", msg_type)
    _check_u8("compat_flags", compat_flags)
    _check_u8("incompat_flags", incompat_flags)
    _check_u8("version", version)
    if not isinstance(seq, int) or not 0 <= seq <= 0xFFFF:
        raise ValueError(f"seq must be an integer in 0..65535, got {seq!r}")
    if len(payload) > MAX_PAYLOAD:
        raise LengthError(f"payload of {len(payload)} bytes exceeds MAX_PAYLOAD={MAX_PAYLOAD}")
    head = HEADER.pack(version, incompat_flags, compat_flags, msg_type, seq, len(payload))
    crc = zlib.crc32(payload, zlib.crc32(head)) & 0xFFFFFFFF
    return cobs.encode(b"".join((head, payload, _U32_LE.pack(crc)))) + DELIMITER


def decode_body(body: bytes | bytearray | memoryview) -> tuple[Header, bytes]:
    """Undo COBS, check length, CRC, version and incompatible flags of one frame body.

    `body` is the bytes between two delimiters (one trailing 0x00 is tolerated).
    Returns the header and the decoded raw frame (header | payload | crc); the payload is
    raw[HEADER_SIZE:HEADER_SIZE + header.payload_len].
    """
    if not isinstance(body, bytes):
        body = bytes(body)  # the COBS C extension reads plain bytes only
    if body[-1:] == DELIMITER:
        body = body[:-1]
    if len(body) < MIN_ENCODED_BODY:
        raise LengthError(
            f"frame body of {len(body)} bytes is shorter than the minimum {MIN_ENCODED_BODY}"
        )
    if len(body) > MAX_ENCODED_BODY:
        raise LengthError(
            f"frame body of {len(body)} bytes exceeds the maximum {MAX_ENCODED_BODY}"
        )
    try:
        raw = cobs.decode(body)
    except cobs.DecodeError as exc:
        raise CobsError(f"invalid COBS frame body: {exc}") from None
    if len(raw) < MIN_RAW_FRAME:
        raise LengthError(f"decoded frame of {len(raw)} bytes is shorter than {MIN_RAW_FRAME}")
    header = Header(*HEADER.unpack_from(raw))
    expected = HEADER_SIZE + header.payload_len + CRC_SIZE
    if header.payload_len > MAX_PAYLOAD:
        raise LengthError(
            f"payload_len {header.payload_len} exceeds MAX_PAYLOAD={MAX_PAYLOAD}"
        )
    if len(raw) != expected:
        raise LengthError(
            f"decoded frame is {len(raw)} bytes but payload_len {header.payload_len} "
            f"implies {expected}"
        )
    (crc_rx,) = _U32_LE.unpack_from(raw, expected - CRC_SIZE)
    crc_calc = zlib.crc32(memoryview(raw)[: expected - CRC_SIZE]) & 0xFFFFFFFF
    if crc_rx != crc_calc:
        raise CrcError(f"CRC-32 mismatch: frame says 0x{crc_rx:08X}, computed 0x{crc_calc:08X}")
    if header.version != PROTOCOL_MAJOR:
        raise VersionError(
            f"protocol major version {header.version} is not supported (expected {PROTOCOL_MAJOR})"
        )
    unknown = header.incompat_flags & ~KNOWN_INCOMPAT_FLAGS
    if unknown:
        raise IncompatibleFlagsError(f"unknown incompatible flags 0x{unknown:02X}")
    return header, raw
