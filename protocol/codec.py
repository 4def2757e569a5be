"""Whole-frame encode/decode: message dataclass <-> on-wire bytes."""

from __future__ import annotations

from dataclasses import dataclass

from .errors import FieldError, UnknownMessageTypeError
from .framing import COMPAT_EXTENDED_PAYLOAD, HEADER_SIZE, decode_body, encode_body
from .payloads import MESSAGE_CLASSES, Message, MsgType


@dataclass(eq=False)
class Frame:
    """One decoded frame. `raw` is the frame as received, trailing 0x00 included."""

    seq: int
    msg: Message
    compat_flags: int = 0
    incompat_flags: int = 0
    raw: bytes = b""

    @property
    def msg_type(self) -> MsgType:
        return self.msg.TYPE


def encode_frame(msg: Message, seq: int, *, compat_flags: int = 0, incompat_flags: int = 0) -> bytes:
    """The full on-wire frame of `msg` with sequence number `seq`, trailing 0x00 included."""
    pack = getattr(msg, "pack_payload", None)
    if pack is None or type(msg) not in MESSAGE_CLASSES.values():
        raise FieldError(f"cannot encode {type(msg).__name__}: not a protocol message")
    return encode_body(msg.TYPE, seq, pack(), compat_flags=compat_flags, incompat_flags=incompat_flags)


def decode_frame(body: bytes) -> Frame:
    """Decode one frame body (the bytes before a 0x00; one trailing 0x00 is allowed).

    Raises a ProtocolError subclass naming what is wrong: CobsError, LengthError, CrcError,
    VersionError, IncompatibleFlagsError, UnknownMessageTypeError or FieldError.
    """
    header, raw = decode_body(body)
    try:
        mtype = MsgType(header.msg_type)
    except ValueError:
        raise UnknownMessageTypeError(f"unknown message type 0x{header.msg_type:02X}") from None
    payload = memoryview(raw)[HEADER_SIZE : HEADER_SIZE + header.payload_len]
    extended = bool(header.compat_flags & COMPAT_EXTENDED_PAYLOAD)
    msg = MESSAGE_CLASSES[mtype].unpack_payload(payload, extended)
    wire = bytes(body) if body[-1:] == b"\x00" else bytes(body) + b"\x00"
    return Frame(header.seq, msg, header.compat_flags, header.incompat_flags, wire)
