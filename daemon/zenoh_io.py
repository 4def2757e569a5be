"""Zenoh edge of skinmapd: the publisher side.

Key space and layouts: ``skinmap.wire`` (docs/zenoh.md). Session configuration:
``skinmap.wire.session``; its names are imported here for the daemon's callers.

Late joiners: the latest payload of every key is kept and served by one queryable on
``<prefix>/<device>/*``, so ``get("<prefix>/<device>/elements")`` answers with the newest
elements message at once, and ``get("<prefix>/<device>/*")`` with everything cached.
"""

from __future__ import annotations

import logging
import threading
from typing import Any, Mapping

import zenoh

from skinmap.daemon.publisher import Publisher
from skinmap.wire import messages
from skinmap.wire.keys import ALL_KINDS, DATA_KINDS, ENCODINGS, check_key_segment, key_for
from skinmap.wire.session import (ZenohOpenError, check_loopback_endpoint, foreign_write_guard,
                                  make_session_config, open_session)

__all__ = ["SkinmapPublisher", "ZenohPublishers", "ALL_KINDS", "DATA_KINDS", "ENCODINGS", "check_key_segment",
           "key_for", "ZenohOpenError", "check_loopback_endpoint", "foreign_write_guard",
           "make_session_config", "open_session"]

log = logging.getLogger(__name__)

_PRIORITIES = {
    "elements": zenoh.Priority.DATA_HIGH,
    "surface": zenoh.Priority.DATA,
    "strains": zenoh.Priority.DATA,
    "status": zenoh.Priority.DATA_LOW,
    "contact": zenoh.Priority.DATA,
}

# Replies to one client can block (a reply takes the query's congestion control, BLOCK by
# default, and a client that stops reading fills its link until Zenoh closes it). Each query is
# answered by a thread of its own, so queries from other clients do not wait behind the stalled
# ones; at most this many at once. Beyond, the serving thread answers itself (in order, as if
# there were no threads) until a thread is free again.
REPLY_THREADS_MAX = 256


class SkinmapPublisher(Publisher):
    """Publishes one device's messages over Zenoh and serves the latest of each to late joiners.

    The session is owned by the caller. Publish methods are thread-safe and never block on a
    slow subscriber (congestion control DROP; data keys are express).
    """

    def __init__(self, session: zenoh.Session, prefix: str, device: str) -> None:
        self._keys = {kind: key_for(prefix, device, kind) for kind in ALL_KINDS}
        self._lock = threading.Lock()
        self._latest: dict[str, bytes] = {}
        self._closed = False
        self._publishers = {
            kind: session.declare_publisher(
                self._keys[kind], encoding=zenoh.Encoding(ENCODINGS[kind]),
                congestion_control=zenoh.CongestionControl.DROP,
                priority=_PRIORITIES[kind], express=kind in DATA_KINDS)
            for kind in (*DATA_KINDS, "status", "contact")}
        # Queries arrive on a channel and are answered by our own thread, so no Zenoh call
        # runs inside a Zenoh callback.
        self._queryable = session.declare_queryable(f"{prefix}/{device}/*",
                                                    zenoh.handlers.FifoChannel(64))
        self._queries = self._queryable.handler
        self._reply_slots = threading.BoundedSemaphore(REPLY_THREADS_MAX)
        self._token = session.liveliness().declare_token(key_for(prefix, device, "alive"))
        self._server = threading.Thread(target=self._serve_queries, daemon=True,
                                        name=f"skinmap-latest-{device}")
        self._server.start()

    @property
    def keys(self) -> dict[str, str]:
        return dict(self._keys)

    def send(self, kind: str, payload: bytes) -> None:
        if not isinstance(payload, (bytes, bytearray, memoryview)):
            raise TypeError(f"{kind} payload must be bytes, got {type(payload).__name__}")
        payload = bytes(payload)
        with self._lock:
            if self._closed:
                raise RuntimeError("SkinmapPublisher is closed")
            self._latest[kind] = payload
            self._publishers[kind].put(payload)

    def set_info(self, info: Mapping[str, Any]) -> None:
        """Replace the device description served on the ``info`` queryable (never put)."""
        payload = messages.encode_info(info)
        with self._lock:
            if self._closed:
                raise RuntimeError("SkinmapPublisher is closed")
            self._latest["info"] = payload

    def _serve_queries(self) -> None:
        while True:
            try:
                query = self._queries.recv()
            except Exception:  # channel closed by undeclare/session close
                return
            if not self._reply_slots.acquire(blocking=False):
                self._answer_and_release(query, slot=False)
                continue
            try:
                threading.Thread(target=self._answer_and_release, args=(query,), daemon=True,
                                 name="skinmap-reply").start()
            except RuntimeError as exc:  # no thread to be had: answer here, late rather than never
                log.warning("answering a query inline: %s", exc)
                self._answer_and_release(query)

    def _answer_and_release(self, query: zenoh.Query, slot: bool = True) -> None:
        try:
            self._answer(query)
        except Exception as exc:  # a bad query must not stop serving
            log.warning("latest-value query %s failed: %s", query.selector, exc)
        finally:
            try:
                query.drop()
            finally:
                if slot:
                    self._reply_slots.release()

    def _answer(self, query: zenoh.Query) -> None:
        with self._lock:
            latest = dict(self._latest)
        for kind, payload in latest.items():
            key = self._keys[kind]
            if query.key_expr.intersects(key):
                query.reply(key, payload, encoding=zenoh.Encoding(ENCODINGS[kind]))

    def close(self) -> None:
        """Undeclare publishers, queryable and liveliness token (idempotent)."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
        self._token.undeclare()
        self._queryable.undeclare()
        for pub in self._publishers.values():
            pub.undeclare()
        self._server.join(timeout=2.0)



class ZenohPublishers:
    """The gateway's PublisherFactory over one Zenoh session (owned by the caller)."""

    def __init__(self, session: zenoh.Session, prefix: str) -> None:
        self.session = session
        self.prefix = prefix

    def __call__(self, device: str) -> SkinmapPublisher:
        return SkinmapPublisher(self.session, self.prefix, device)
