"""Zenoh edge of skinmapd: loopback-safe session configuration and the publisher side.

Key space (docs/zenoh.md) under ``<prefix>/<device>/``:

- ``elements``, ``surface``, ``strains`` -- binary messages (skinmap.daemon.messages), put per scan
- ``status`` -- JSON, put about once a second
- ``contact`` -- JSON, put per processed scan when tactile mapping is on (docs/tactile.md)
- ``info``   -- JSON, queryable only (never put)
- ``alive``  -- liveliness token, present while the publisher is declared

Late joiners: the latest payload of every key is kept and served by one queryable on
``<prefix>/<device>/*``, so ``get("<prefix>/<device>/elements")`` answers with the newest
elements message at once, and ``get("<prefix>/<device>/*")`` with everything cached.
"""

from __future__ import annotations

import ipaddress
import json
import logging
import re
import threading
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterable, Iterator, Mapping

import zenoh

from skinmap.daemon import messages

log = logging.getLogger(__name__)

DATA_KINDS = ("elements", "surface", "strains")
ALL_KINDS = (*DATA_KINDS, "status", "contact", "info")

_ENCODINGS = {
    "elements": "application/octet-stream;skinmap.elements/1",
    "surface": "application/octet-stream;skinmap.surface/1",
    "strains": "application/octet-stream;skinmap.strains/1",
    "status": "application/json;" + messages.STATUS_SCHEMA,
    "contact": "application/json;skinmap.contact/1",
    "info": "application/json;" + messages.INFO_SCHEMA,
}

_PRIORITIES = {
    "elements": zenoh.Priority.DATA_HIGH,
    "surface": zenoh.Priority.DATA,
    "strains": zenoh.Priority.DATA,
    "status": zenoh.Priority.DATA_LOW,
    "contact": zenoh.Priority.DATA,
}

_MODES = ("peer", "client", "router")
# Replies to one client can block (a reply takes the query's congestion control, BLOCK by
# default, and a client that stops reading fills its link until Zenoh closes it). Each query is
# answered by a thread of its own, so queries from other clients do not wait behind the stalled
# ones; at most this many at once. Beyond, the serving thread answers itself (in order, as if
# there were no threads) until a thread is free again.
REPLY_THREADS_MAX = 256
_KEY_SEGMENT = re.compile(r"^[A-Za-z0-9_.\-]+$")
_ENDPOINT = re.compile(r"^(?P<proto>[a-z0-9]+)/(?P<host>\[[^\]]*\]|[^:/\[\]]+):(?P<port>[^#?]*)"
                       r"(?P<rest>[#?].*)?$")
# Explicit `multicast: { ... enabled: true ... }` in a JSON5 file (quoted or bare keys).
_MULTICAST_ON = re.compile(r"""["']?multicast["']?\s*:\s*\{[^{}]*?["']?enabled["']?\s*:\s*true""")


def check_loopback_endpoint(endpoint: str, *, listen: bool = False) -> str:
    """Return ``endpoint`` if it is tcp on 127.0.0.1, [::1] or localhost with a valid port,
    else raise ValueError naming it."""
    if not isinstance(endpoint, str):
        raise TypeError(f"endpoint must be a string, got {type(endpoint).__name__}")
    match = _ENDPOINT.match(endpoint)
    if match is None:
        raise ValueError(f"endpoint {endpoint!r} is not of the form tcp/HOST:PORT")
    if match["proto"] != "tcp":
        raise ValueError(f"endpoint {endpoint!r}: only tcp is allowed on the loopback default")
    host = match["host"].strip("[]")
    if host != "localhost":
        try:
            loopback = ipaddress.ip_address(host) in (ipaddress.ip_address("127.0.0.1"),
                                                      ipaddress.ip_address("::1"))
        except ValueError:
            loopback = False
        if not loopback:
            raise ValueError(f"endpoint {endpoint!r} is not loopback (127.0.0.1, [::1] or "
                             f"localhost); pass allow_non_loopback=True to use it")
    port = match["port"]
    lowest = 0 if listen else 1
    if not port.isdigit() or not lowest <= int(port) <= 65535:
        raise ValueError(f"endpoint {endpoint!r} has an invalid port {port!r}")
    return endpoint


def _endpoint_list(name: str, endpoints: Iterable[str] | str) -> list[str]:
    if isinstance(endpoints, str):
        raise TypeError(f"{name} must be a list of endpoints, got the string {endpoints!r}")
    return list(endpoints)


def _file_endpoints(config: zenoh.Config, key: str, mode: str) -> list[str]:
    raw = json.loads(config.get_json(key))
    if isinstance(raw, dict):  # per-mode form: {"peer": [...], "router": [...]}
        raw = raw.get(mode)
    return list(raw or [])


def make_session_config(listen: Iterable[str] = (), connect: Iterable[str] = (), *,
                        allow_non_loopback: bool = False, mode: str = "peer",
                        config_file: str | Path | None = None,
                        deny_remote_writes: str | None = None) -> zenoh.Config:
    """Build a Zenoh config that talks only to the given endpoints.

    Multicast scouting and gossip are always switched off, except that a ``config_file``
    (production: TLS, access control) may explicitly enable multicast scouting. Every
    endpoint -- given here or found in the file -- must be tcp on loopback unless
    ``allow_non_loopback`` is True. ``listen``/``connect`` given here replace the file's.
    With ``deny_remote_writes`` (a key expression), other sessions' writes there are dropped
    by access control (``foreign_write_guard``), unless the file enables its own.
    """
    if mode not in _MODES:
        raise ValueError(f"mode must be one of {_MODES}, got {mode!r}")
    listen = _endpoint_list("listen", listen)
    connect = _endpoint_list("connect", connect)
    if not allow_non_loopback:
        for e in listen:
            check_loopback_endpoint(e, listen=True)
        for e in connect:
            check_loopback_endpoint(e)

    multicast_in_file = False
    if config_file is not None:
        path = Path(config_file)
        try:
            text = path.read_text(encoding="utf-8")
        except OSError as exc:
            raise ValueError(f"cannot read Zenoh config file {str(path)!r}: {exc}") from None
        try:
            config = zenoh.Config.from_file(str(path))
        except Exception as exc:  # zenoh raises ZError with the parser's message
            raise ValueError(f"invalid Zenoh config file {str(path)!r}: {exc}") from None
        multicast_in_file = (json.loads(config.get_json("scouting/multicast/enabled")) is True
                             and _MULTICAST_ON.search(text) is not None)
    else:
        config = zenoh.Config()

    config.insert_json5("mode", json.dumps(mode))
    # Always set listen explicitly: zenoh's default peer listener is tcp/[::]:0 (all interfaces).
    if listen or config_file is None:
        config.insert_json5("listen/endpoints", json.dumps(listen))
    if connect or config_file is None:
        config.insert_json5("connect/endpoints", json.dumps(connect))
    if not allow_non_loopback:
        for e in _file_endpoints(config, "listen/endpoints", mode):
            check_loopback_endpoint(e, listen=True)
        for e in _file_endpoints(config, "connect/endpoints", mode):
            check_loopback_endpoint(e)
    if not multicast_in_file:
        config.insert_json5("scouting/multicast/enabled", "false")
        config.insert_json5("scouting/gossip/enabled", "false")
    if deny_remote_writes is not None and \
            json.loads(config.get_json("access_control/enabled")) is not True:
        config.insert_json5("access_control", json.dumps(foreign_write_guard(deny_remote_writes)))
    return config


def foreign_write_guard(key_expr: str) -> dict[str, Any]:
    """A Zenoh ``access_control`` block for a publishing session: what other sessions send
    into ``key_expr`` that would write there (put, delete, a queryable, a liveliness token, a
    reply) is dropped on arrival; subscribing, querying and everything else stay allowed.

    The subject has no attributes, so it matches every remote session on every link."""
    return {
        "enabled": True,
        "default_permission": "allow",
        "rules": [{"id": "no-foreign-writes", "permission": "deny", "flows": ["ingress"],
                   "messages": ["put", "delete", "declare_queryable", "liveliness_token", "reply"],
                   "key_exprs": [key_expr]}],
        "subjects": [{"id": "every-remote-session"}],
        "policies": [{"rules": ["no-foreign-writes"], "subjects": ["every-remote-session"]}],
    }


class ZenohOpenError(OSError):
    """The Zenoh session could not be opened (an endpoint in use, unreachable, refused)."""


def _zerror_text(exc: Exception) -> str:
    """Zenoh's error message on one line, without its Rust source locations."""
    text = " ".join(str(exc).split())
    text = re.sub(r" at \S+\.rs:\d+\.?", "", text)
    listener = re.search(r"bound to (\S+?): \[[^\]]*?: ([^\[\]]+?)(?: \(os error \d+\))?\.?\]", text)
    if listener:
        return f"cannot listen on {listener[1]}: {listener[2]}"
    return text


@contextmanager
def open_session(config: zenoh.Config) -> Iterator[zenoh.Session]:
    """Open a session and always close it on exit; ZenohOpenError (one line naming the
    endpoint and the reason, e.g. "cannot listen on tcp/127.0.0.1:7447: Address already in
    use") if it cannot be opened.

    Closing explicitly matters: a process holding callback subscribers or queryables can hang
    at interpreter exit otherwise (atexit runs too late).
    """
    try:
        session = zenoh.open(config)
    except zenoh.ZError as exc:
        raise ZenohOpenError(f"Zenoh: {_zerror_text(exc)}") from None
    try:
        yield session
    finally:
        session.close()


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


class SkinmapPublisher:
    """Publishes one device's messages and serves the latest of each to late joiners.

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
                self._keys[kind], encoding=zenoh.Encoding(_ENCODINGS[kind]),
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

    def _put(self, kind: str, payload: bytes) -> None:
        if not isinstance(payload, (bytes, bytearray, memoryview)):
            raise TypeError(f"{kind} payload must be bytes, got {type(payload).__name__}")
        payload = bytes(payload)
        with self._lock:
            if self._closed:
                raise RuntimeError("SkinmapPublisher is closed")
            self._latest[kind] = payload
            self._publishers[kind].put(payload)

    def publish_elements(self, payload: bytes) -> None:
        """Put an encoded elements message (messages.encode_elements)."""
        self._put("elements", payload)

    def publish_surface(self, payload: bytes) -> None:
        self._put("surface", payload)

    def publish_strains(self, payload: bytes) -> None:
        self._put("strains", payload)

    def publish_status(self, status: Mapping[str, Any]) -> None:
        """Validate, encode and put a status report (messages.STATUS_FIELDS)."""
        self._put("status", messages.encode_status(status))

    def publish_contact(self, contact: Mapping[str, Any]) -> None:
        """Put a `contact` message (skinmap.daemon.tactile.ContactTracker.update) as JSON."""
        self._put("contact", json.dumps(dict(contact), separators=(",", ":")).encode())

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
                query.reply(key, payload, encoding=zenoh.Encoding(_ENCODINGS[kind]))

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

    def __enter__(self) -> "SkinmapPublisher":
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()
