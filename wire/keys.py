"""Zenoh key space of skinmap (docs/zenoh.md): the kinds under ``<prefix>/<device>/``, their
encodings, and how a key is built. Pure; shared by the gateway, the client and the tools.

- ``elements``, ``surface``, ``strains`` -- binary messages (skinmap.wire.messages), put per scan
- ``status`` -- JSON, put about once a second
- ``contact`` -- JSON, put per processed scan when tactile mapping is on (docs/tactile.md)
- ``info``   -- JSON, queryable only (never put)
- ``alive``  -- liveliness token, present while the publisher is declared

One input: ``pose`` (JSON, skinmap.wire.messages.POSE_FIELDS), the probe's pose for the next
press, put by whatever moves the probe on ``pose_key`` -- ``<prefix>-in/<device>/pose``, outside
the space ``<prefix>/**`` the gateway keeps other sessions from writing into.
"""

from __future__ import annotations

import re

from skinmap.wire import messages

DATA_KINDS = ("elements", "surface", "strains")
ALL_KINDS = (*DATA_KINDS, "status", "contact", "info")

ENCODINGS = {
    "elements": f"application/octet-stream;skinmap.elements/{messages.LAYOUT_VERSION}",
    "surface": f"application/octet-stream;skinmap.surface/{messages.LAYOUT_VERSION}",
    "strains": f"application/octet-stream;skinmap.strains/{messages.LAYOUT_VERSION}",
    "status": "application/json;" + messages.STATUS_SCHEMA,
    "contact": "application/json;skinmap.contact/1",
    "info": "application/json;" + messages.INFO_SCHEMA,
}
POSE_ENCODING = "application/json;" + messages.POSE_SCHEMA


_KEY_SEGMENT = re.compile(r"^[A-Za-z0-9_.\-]+$")


def check_key_segment(name: str, value: str) -> str:
    """A prefix is one or more '/'-separated plain segments; a device is one plain segment."""
    if not isinstance(value, str) or not value:
        raise ValueError(f"{name} must be a non-empty string, got {value!r}")
    parts = value.split("/") if name == "prefix" else [value]
    for part in parts:
        if not _KEY_SEGMENT.match(part):
            raise ValueError(f"{name} {value!r} has an invalid key segment {part!r} "
                             f"(allowed: letters, digits, '_', '-', '.')")
    return value


def key_for(prefix: str, device: str, kind: str) -> str:
    """Key expression of one kind (``elements``, ..., ``alive``) of one device."""
    if kind not in ALL_KINDS and kind != "alive":
        raise ValueError(f"unknown key kind {kind!r}; expected one of {ALL_KINDS + ('alive',)}")
    return f"{check_key_segment('prefix', prefix)}/{check_key_segment('device', device)}/{kind}"


def pose_key(prefix: str, device: str) -> str:
    """Key expression the gateway of ``device`` takes probe poses from (docs/tactile.md)."""
    return f"{check_key_segment('prefix', prefix)}-in/{check_key_segment('device', device)}/pose"
