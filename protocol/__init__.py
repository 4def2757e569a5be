"""skinmap.protocol: the scanner wire protocol (PROTOCOL.md) as a pure codec, no I/O.

    frame = encode_frame(Scan(...), seq)         # on-wire bytes, trailing 0x00 included
    decoder = StreamDecoder()
    for f in decoder.feed(chunk): f.seq, f.msg, f.raw
"""

from .codec import Frame, decode_frame, encode_frame
from .errors import (
    CobsError,
    CrcError,
    FieldError,
    IncompatibleFlagsError,
    LengthError,
    ProtocolError,
    UnknownMessageTypeError,
    VersionError,
)
from .framing import (
    COMPAT_EXTENDED_PAYLOAD,
    HEADER_SIZE,
    MAX_ENCODED_BODY,
    MAX_PAYLOAD,
    PROTOCOL_MAJOR,
    PROTOCOL_MINOR,
    crc32,
)
from .payloads import (
    COMMANDS,
    MAX_DIM,
    MAX_PING_ECHO,
    MIN_DIM,
    RES_MAX_VALID,
    RES_OPEN,
    RES_SATURATED,
    SCHEMA_HASH,
    Ack,
    Compatibility,
    DeviceState,
    ErrorCode,
    FaultFlag,
    Hello,
    Message,
    MsgType,
    Nak,
    Ping,
    QueryInfo,
    Reset,
    Scan,
    ScanFlag,
    SetScanRate,
    Start,
    Status,
    Stop,
    hello_compatibility,
    schema_text,
)
from .stream import StreamDecoder
from .tdm import default_channel_map, step_period_ns, tdm_steps, unit_sample_times_us

__all__ = [
    "Ack", "COMMANDS", "Compatibility", "COMPAT_EXTENDED_PAYLOAD", "CobsError", "CrcError", "DeviceState",
    "ErrorCode", "FaultFlag", "FieldError", "Frame", "HEADER_SIZE", "Hello",
    "IncompatibleFlagsError", "LengthError", "MAX_DIM", "MAX_ENCODED_BODY", "MAX_PAYLOAD",
    "MAX_PING_ECHO", "MIN_DIM", "Message", "MsgType", "Nak", "PROTOCOL_MAJOR", "PROTOCOL_MINOR",
    "Ping", "ProtocolError", "QueryInfo", "RES_MAX_VALID", "RES_OPEN", "RES_SATURATED", "Reset",
    "SCHEMA_HASH", "Scan", "ScanFlag", "SetScanRate", "Start", "Status", "Stop", "StreamDecoder",
    "UnknownMessageTypeError", "VersionError", "crc32", "decode_frame", "default_channel_map",
    "encode_frame", "hello_compatibility", "schema_text", "step_period_ns", "tdm_steps", "unit_sample_times_us",
]
