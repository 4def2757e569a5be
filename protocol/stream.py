"""Incremental stream decoder: bytes in, frames out, every fault counted, never raises."""

from __future__ import annotations

from .codec import Frame, decode_frame
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
    CRC_SIZE,
    decode_body,
    HEADER_SIZE,
    KNOWN_INCOMPAT_FLAGS,
    MAX_ENCODED_BODY,
    MIN_ENCODED_BODY,
    PROTOCOL_MAJOR,
)
from .payloads import MsgType

_COUNTER_OF = {
    CobsError: "cobs_errors",
    CrcError: "crc_errors",
    LengthError: "length_errors",
    VersionError: "version_errors",
    IncompatibleFlagsError: "incompat_flag_drops",
    UnknownMessageTypeError: "unknown_type",
    FieldError: "field_errors",
}

COUNTERS = (
    "frames_ok", "bytes_in", "garbage_bytes", "cobs_errors", "crc_errors", "length_errors",
    "version_errors", "incompat_flag_drops", "unknown_type", "field_errors", "oversize_frames",
    "salvaged_frames", "seq_gaps", "seq_lost",
)


class StreamDecoder:
    """Split a byte stream at 0x00 delimiters and decode each frame.

    Survives garbage, truncation and bit flips: a bad body is counted and skipped. If a bad
    body ends with an intact frame (garbage without a delimiter in front of it), that frame
    is recovered (`salvaged_frames`). A body growing beyond the largest legal frame is dropped
    at once and the rest of it, up to the next 0x00, is skipped unbuffered.
    """

    # the counters (COUNTERS, PROTOCOL.md section 3), set to 0 in __init__
    frames_ok: int
    bytes_in: int
    garbage_bytes: int
    cobs_errors: int
    crc_errors: int
    length_errors: int
    version_errors: int
    incompat_flag_drops: int
    unknown_type: int
    field_errors: int
    oversize_frames: int
    salvaged_frames: int
    seq_gaps: int
    seq_lost: int

    def __init__(self) -> None:
        self._buf = bytearray()
        self._skipping = False
        self._last_seq: int | None = None
        self.last_error: str | None = None
        for name in COUNTERS:
            setattr(self, name, 0)

    def counters(self) -> dict[str, int]:
        return {name: getattr(self, name) for name in COUNTERS}

    @property
    def buffered_bytes(self) -> int:
        """Bytes held while waiting for a delimiter (never more than one legal frame + a read)."""
        return len(self._buf)

    def reset(self) -> None:
        """Forget buffered bytes and sequence state (e.g. after reopening the port)."""
        self._buf.clear()
        self._skipping = False
        self._last_seq = None

    def feed(self, data: bytes | bytearray | memoryview) -> list[Frame]:
        self.bytes_in += len(data)
        frames: list[Frame] = []
        if self._skipping:
            end = bytes(data).find(0) if not isinstance(data, (bytes, bytearray)) else data.find(0)
            if end < 0:
                self.garbage_bytes += len(data)
                return frames
            self.garbage_bytes += end
            data = data[end + 1 :]
            self._skipping = False
        buf = self._buf
        search_from = len(buf)
        buf += data
        start = 0
        while True:
            end = buf.find(0, search_from)
            if end < 0:
                break
            if end > start:
                self._body(bytes(buf[start : end + 1]), frames)
            start = search_from = end + 1
        if start:
            del buf[:start]
        if len(buf) > MAX_ENCODED_BODY:
            self.oversize_frames += 1
            self.garbage_bytes += len(buf)
            self.last_error = f"frame body exceeds {MAX_ENCODED_BODY} bytes without a delimiter"
            buf.clear()
            self._skipping = True
        return frames

    def _body(self, wire: bytes, frames: list[Frame]) -> None:
        """Decode one body (with its trailing 0x00) and append the frame or count the fault."""
        if len(wire) - 1 > MAX_ENCODED_BODY:
            self.oversize_frames += 1
            self.garbage_bytes += len(wire) - 1
            self.last_error = f"frame body of {len(wire) - 1} bytes exceeds {MAX_ENCODED_BODY}"
            return
        try:
            frame = decode_frame(wire)
        except UnknownMessageTypeError as exc:
            # An intact frame (CRC good) of a type this host does not know (vendor, newer minor
            # version): counted apart, not damage, and its seq is the sender's, so no loss.
            self.unknown_type += 1
            self.last_error = str(exc)
            self._note_seq(decode_body(wire)[0].seq, restarted=False)
            return
        except ProtocolError as exc:
            setattr(self, _COUNTER_OF.get(type(exc), "length_errors"),
                    getattr(self, _COUNTER_OF.get(type(exc), "length_errors")) + 1)
            self.last_error = str(exc)
            if isinstance(exc, (CobsError, CrcError, LengthError)):
                salvaged = self._salvage(wire)
                if salvaged is not None:
                    skipped, frame = salvaged
                    self.garbage_bytes += skipped
                    self.salvaged_frames += 1
                    self._accept(frame, frames)
                    return
            self.garbage_bytes += len(wire) - 1
            return
        self._accept(frame, frames)

    def _accept(self, frame: Frame, frames: list[Frame]) -> None:
        # A HELLO with sequence 0 is a sender that (re)booted: its counter restarts, nothing was lost.
        self._note_seq(frame.seq, restarted=frame.seq == 0 and frame.msg_type == MsgType.HELLO)
        self.frames_ok += 1
        frames.append(frame)

    def _note_seq(self, seq: int, restarted: bool) -> None:
        if self._last_seq is not None and not restarted:
            lost = (seq - self._last_seq - 1) & 0xFFFF
            if lost:
                self.seq_gaps += 1
                self.seq_lost += lost
        self._last_seq = seq

    @staticmethod
    def _salvage(wire: bytes) -> tuple[int, Frame] | None:
        """Find an intact frame that is a proper suffix of a bad body.

        A frame starts with a COBS code byte >= 2 followed by the version byte (the header's
        first byte is never 0), so only those positions are tried; each candidate's header is
        un-stuffed and checked (known type, no unknown incompatible flag, payload_len fitting
        the rest of the body) before the full decode, and CRC decides.
        """
        end = len(wire) - 1  # the delimiter
        last = end - MIN_ENCODED_BODY  # last start leaving room for a minimal frame
        pos = wire.find(PROTOCOL_MAJOR, 2)
        while 0 <= pos and pos - 1 <= last:
            start = pos - 1
            if wire[start] >= 2 and _plausible_header(wire, start, end):
                try:
                    return start, decode_frame(wire[start:])
                except ProtocolError:
                    pass
            pos = wire.find(PROTOCOL_MAJOR, pos + 1)
        return None


_KNOWN_TYPES = frozenset(int(t) for t in MsgType)


def _plausible_header(wire: bytes, start: int, end: int) -> bool:
    """Un-stuff the 8 header bytes of a COBS body starting at `start` and sanity-check them."""
    head = bytearray()
    i = start
    while len(head) < HEADER_SIZE:
        code = wire[i] if i < end else 0
        if code == 0 or i + code > end:
            return False
        head += wire[i + 1 : i + code]
        i += code
        if code < 0xFF:
            head.append(0)
    if head[1] & ~KNOWN_INCOMPAT_FLAGS or head[3] not in _KNOWN_TYPES:
        return False
    raw_len = HEADER_SIZE + CRC_SIZE + head[6] + (head[7] << 8)
    return raw_len + 1 <= end - start <= raw_len + raw_len // 254 + 1
