"""Field specifications and what is derived from them: struct formats, offsets and sizes.

The layout tables (the header here, the messages in ``messages.LAYOUTS``) are the one source
of truth of the byte layouts: the codec packs with structs built from them, PROTOCOL.md's
tables and the schema hash are generated from them.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Literal

FieldType = Literal["u8", "char", "u16", "i16", "u32", "u64"]

TYPE_SIZE: dict[str, int] = {"u8": 1, "char": 1, "u16": 2, "i16": 2, "u32": 4, "u64": 8}
_STRUCT_CODE: dict[str, str] = {"u8": "B", "char": "s", "u16": "H", "i16": "h", "u32": "I", "u64": "Q"}
NUMPY_DTYPE: dict[str, str] = {"u8": "u1", "u16": "<u2", "i16": "<i2", "u32": "<u4", "u64": "<u8"}


@dataclass(frozen=True)
class FieldSpec:
    """One field. count: "" a scalar, "16" a fixed array, "k*N*M" an array of k·N·M elements,
    "ceil(k*N*M/8)" a bitmap in bytes, "*" the rest of the payload."""

    type: FieldType
    name: str
    count: str = ""
    units: str = ""

    @property
    def is_fixed(self) -> bool:
        """True when the field's size does not depend on N, M or the payload length."""
        return self.count == "" or self.count.isdigit()

    def size(self, n: int, m: int) -> int:
        """Bytes of this field for an N × M array (a "*" field counts 0: it has no fixed size)."""
        unit = TYPE_SIZE[self.type]
        if self.count == "":
            return unit
        if self.count.isdigit():
            return unit * int(self.count)
        if self.count == "*":
            return 0
        if self.count.startswith("ceil("):
            k = int(self.count[len("ceil("):].split("*")[0])
            return (k * n * m + 7) // 8
        return unit * int(self.count.split("*")[0]) * n * m


HEADER_LAYOUT: tuple[FieldSpec, ...] = (
    FieldSpec("u8", "version", "", "protocol major version, 1"),
    FieldSpec("u8", "incompat_flags", "", "incompatible flags"),
    FieldSpec("u8", "compat_flags", "", "compatible flags"),
    FieldSpec("u8", "msg_type", "", "message type"),
    FieldSpec("u16", "seq", "", "sequence number of the sender's direction"),
    FieldSpec("u16", "payload_len", "", "payload bytes that follow the header"),
)


def fixed_prefix(fields: tuple[FieldSpec, ...]) -> tuple[FieldSpec, ...]:
    """The leading fields whose sizes are fixed (packed with one struct)."""
    out = []
    for f in fields:
        if not f.is_fixed:
            break
        out.append(f)
    return tuple(out)


def fixed_struct(fields: tuple[FieldSpec, ...]) -> struct.Struct:
    """Little-endian struct of the fixed leading fields of a layout."""
    codes = []
    for f in fixed_prefix(fields):
        code = _STRUCT_CODE[f.type]
        if f.count and f.type == "char":
            codes.append(f"{f.count}{code}")  # one bytes value
        elif f.count:
            codes.append(code * int(f.count))
        else:
            codes.append(code)
    return struct.Struct("<" + "".join(codes))


def field_offset(fields: tuple[FieldSpec, ...], name: str, n: int = 0, m: int = 0) -> int:
    """Byte offset of field `name` for an N × M array."""
    offset = 0
    for f in fields:
        if f.name == name:
            return offset
        offset += f.size(n, m)
    raise KeyError(f"no field {name!r} in layout")


def layout_size(fields: tuple[FieldSpec, ...], n: int, m: int) -> int:
    """Bytes of a layout for an N × M array ("*" fields count 0)."""
    return sum(f.size(n, m) for f in fields)


def schema_line(fields: tuple[FieldSpec, ...]) -> str:
    """Fields as the canonical text hashed into the schema hash: "u8 a; u32[4*N*M] b"."""
    return "; ".join(f"{f.type}[{f.count}] {f.name}" if f.count else f"{f.type} {f.name}" for f in fields)
