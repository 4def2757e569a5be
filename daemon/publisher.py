"""What the gateway sends to its clients: the `Publisher` interface (one device's messages),
a null publisher and an in-memory one for tests. The Zenoh publisher is
`skinmap.daemon.zenoh_io.SkinmapPublisher`.

Payloads are the wire messages of `skinmap.wire.messages`; status and info are validated and
encoded here (`encode_status`, `encode_info`), contacts as compact JSON (`encode_contact`), so
every publisher sends the same bytes.
"""
from __future__ import annotations

import json
import threading
from abc import ABC, abstractmethod
from typing import Any, Callable, Mapping

from skinmap.wire import messages

__all__ = ["Publisher", "PublisherFactory", "NullPublisher", "MemoryPublisher", "MemoryPublishers",
           "encode_contact", "as_payload"]


def encode_contact(contact: Mapping[str, Any]) -> bytes:
    """A `contact` message (skinmap.daemon.tactile.ContactTracker.update) as compact JSON."""
    return json.dumps(dict(contact), separators=(",", ":")).encode()


def as_payload(kind: str, payload: object) -> bytes:
    if not isinstance(payload, (bytes, bytearray, memoryview)):
        raise TypeError(f"{kind} payload must be bytes, got {type(payload).__name__}")
    return bytes(payload)


class Publisher(ABC):
    """One device's outgoing messages. Thread-safe; no call blocks on a slow subscriber."""

    @abstractmethod
    def send(self, kind: str, payload: bytes) -> None:
        """Send an encoded message of `kind` (elements, surface, strains, status, contact)."""

    @abstractmethod
    def set_info(self, info: Mapping[str, Any]) -> None:
        """Replace the device description served to clients that ask (never put)."""

    @abstractmethod
    def close(self) -> None:
        """Release what the publisher holds (idempotent)."""

    def publish_elements(self, payload: bytes) -> None:
        """An encoded elements message (messages.encode_elements)."""
        self.send("elements", as_payload("elements", payload))

    def publish_surface(self, payload: bytes) -> None:
        self.send("surface", as_payload("surface", payload))

    def publish_strains(self, payload: bytes) -> None:
        self.send("strains", as_payload("strains", payload))

    def publish_status(self, status: Mapping[str, Any]) -> None:
        """Validate, encode and send a status report (messages.STATUS_FIELDS)."""
        self.send("status", messages.encode_status(status))

    def publish_contact(self, contact: Mapping[str, Any]) -> None:
        self.send("contact", encode_contact(contact))

    def __enter__(self) -> Publisher:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()


PublisherFactory = Callable[[str], Publisher]
"""Opens the publisher of one device, given its name."""


class NullPublisher(Publisher):
    """Sends nothing (Zenoh disabled); messages are still encoded and checked."""

    def send(self, kind: str, payload: bytes) -> None:
        pass

    def set_info(self, info: Mapping[str, Any]) -> None:
        messages.encode_info(info)

    def close(self) -> None:
        pass


class MemoryPublisher(Publisher):
    """Keeps every message sent, for tests: `sent` holds (kind, payload) in order, `info` the
    latest device description. Closed, it refuses messages like the Zenoh publisher."""

    def __init__(self, device: str = "") -> None:
        self.device = device
        self.sent: list[tuple[str, bytes]] = []
        self.info: messages.DeviceInfo | None = None
        self.closed = False
        self._lock = threading.Lock()

    def send(self, kind: str, payload: bytes) -> None:
        with self._lock:
            if self.closed:
                raise RuntimeError("the publisher is closed")
            self.sent.append((kind, payload))

    def set_info(self, info: Mapping[str, Any]) -> None:
        decoded = messages.decode_info(messages.encode_info(info))
        with self._lock:
            if self.closed:
                raise RuntimeError("the publisher is closed")
            self.info = decoded

    def close(self) -> None:
        with self._lock:
            self.closed = True

    def payloads(self, kind: str) -> list[bytes]:
        with self._lock:
            return [p for k, p in self.sent if k == kind]


class MemoryPublishers:
    """A PublisherFactory of MemoryPublishers; `opened` lists them in the order opened."""

    def __init__(self) -> None:
        self.opened: list[MemoryPublisher] = []

    def __call__(self, device: str) -> MemoryPublisher:
        pub = MemoryPublisher(device)
        self.opened.append(pub)
        return pub

    @property
    def latest(self) -> MemoryPublisher:
        if not self.opened:
            raise LookupError("no publisher opened yet (no scanner handshake)")
        return self.opened[-1]
