"""Exceptions raised by the codec; each names what is wrong with the input."""

from __future__ import annotations


class ProtocolError(ValueError):
    """Base class: a frame or message violates PROTOCOL.md."""


class CobsError(ProtocolError):
    """The frame body is not valid COBS (or contains a stray 0x00)."""


class CrcError(ProtocolError):
    """The CRC-32 trailer does not match header + payload."""


class LengthError(ProtocolError):
    """A frame or payload is shorter or longer than its layout or the limits allow."""


class VersionError(ProtocolError):
    """The header carries a protocol major version this codec does not speak."""


class IncompatibleFlagsError(ProtocolError):
    """The header sets an incompatible-flag bit this codec does not know: drop the frame."""


class UnknownMessageTypeError(ProtocolError):
    """The header names a message type this codec does not know."""


class FieldError(ProtocolError):
    """A field value is out of range or inconsistent with other fields (e.g. N, M)."""
