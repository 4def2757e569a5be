"""skinmap.client: the light client of skinmapd's Zenoh data; subscribe and query only, numpy
arrays out. Needs only numpy and eclipse-zenoh (``pip install 'skinmap[client]'``): it imports
nothing of the gateway.

    from skinmap.client import SkinmapClient

    with SkinmapClient(["tcp/127.0.0.1:7447"], prefix="skinmap", device="demo") as client:
        print(client.info()["rows"])
        first = client.latest("elements")          # newest cached scan, at once
        for msg in client.iter_elements(timeout=2.0):
            use(msg.positions, msg.normals)        # (K, 3) metres, unit normals

Every message is checked against its layout's rules before it is handed out (`check_message`):
one that breaks them (a NaN in an element flagged VALID, counts that disagree with the header,
unknown flag bits, non-zero reserved bytes...) is dropped, counted in `rejected(kind)` and named
in `rejections(kind)`, so a forged or damaged put never reaches the caller as data.
"""

from __future__ import annotations

import collections
import queue
import struct
import threading
import time
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator

import numpy as np
import zenoh

from skinmap.wire import messages
from skinmap.wire.keys import ALL_KINDS, DATA_KINDS, check_key_segment, key_for
from skinmap.wire.session import make_session_config

DECODERS: dict[str, Callable[[bytes], Any]] = {
    "elements": messages.decode_elements,
    "surface": messages.decode_surface,
    "strains": messages.decode_strains,
    "status": messages.decode_status,
    "info": messages.decode_info,
}

_STREAM_KINDS = (*DATA_KINDS, "status")
_REJECTIONS_KEPT = 16
_UNIT_TOLERANCE = 1e-6
# every bit the wire format defines (its enums are the one list: a flag added there is known
# here; AMBIGUOUS, missing from a hand-kept copy, made every ambiguous frame a rejected one)
_KNOWN_ELEMENT_FLAGS = sum(int(flag) for flag in messages.ElementFlag)
_KNOWN_GAUGE_FLAGS = sum(int(flag) for flag in messages.GaugeFlag)


class RejectedMessage(messages.MessageError):
    """A message that decodes but breaks its layout's rules (docs/zenoh.md)."""


def _first_bad(mask: np.ndarray) -> int:
    return int(np.flatnonzero(mask)[0])


def _check_elements(m: messages.ElementsMessage, raw: bytes) -> None:
    if struct.unpack_from("<I", raw, messages.HEADER_SIZE + 4)[0] != 0:
        raise RejectedMessage("elements: reserved field after K is not 0")
    unknown = (m.flags & (0xFF ^ _KNOWN_ELEMENT_FLAGS)) != 0
    if unknown.any():
        i = _first_bad(unknown)
        raise RejectedMessage(f"elements: element {i} has unknown flag bits 0x{int(m.flags[i]):02x}")
    valid = m.valid
    scatter = m.uncertainty if m.scatter is None else m.scatter
    bad = valid & ~(np.isfinite(m.positions).all(axis=1) & np.isfinite(m.normals).all(axis=1)
                    & np.isfinite(m.uncertainty) & np.isfinite(scatter))
    if bad.any():
        raise RejectedMessage(f"elements: element {_first_bad(bad)} is flagged VALID but its position, "
                              "normal, uncertainty or scatter is not finite")
    with np.errstate(invalid="ignore"):
        norm_off = np.abs(np.linalg.norm(m.normals, axis=1) - 1.0) > _UNIT_TOLERANCE
        negative = (m.uncertainty < 0) | (scatter < 0)
    if (valid & norm_off).any():
        raise RejectedMessage(f"elements: element {_first_bad(valid & norm_off)} is flagged VALID but "
                              "its normal is not a unit vector")
    if negative.any():
        raise RejectedMessage(f"elements: element {_first_bad(negative)} has a negative uncertainty or scatter")


def _check_surface(m: messages.SurfaceMessage, raw: bytes) -> None:
    if raw[messages.HEADER_SIZE + 13:messages.HEADER_SIZE + 16] != b"\0\0\0":
        raise RejectedMessage("surface: padding after the counts is not 0")
    # skinmapd never publishes a non-finite node (it holds the last good frame instead)
    scatter = m.uncertainty if m.scatter is None else m.scatter
    for name, arr in (("node", m.nodes), ("normal", m.normals), ("uncertainty", m.uncertainty),
                      ("scatter", scatter), ("cloud point", m.cloud)):
        if not np.isfinite(arr).all():
            raise RejectedMessage(f"surface: a {name} is not finite")
    if (m.uncertainty < 0).any() or (scatter < 0).any():
        raise RejectedMessage("surface: a node has a negative uncertainty or scatter")


def _check_strains(m: messages.StrainsMessage, raw: bytes) -> None:
    unknown = (m.gauge_flags & (0xFF ^ _KNOWN_GAUGE_FLAGS)) != 0
    if unknown.any():
        raise RejectedMessage("strains: a gauge has unknown flag bits")
    for layer, eps, valid in (("upper", m.eps_upper, m.valid_upper), ("lower", m.eps_lower, m.valid_lower)):
        if (valid & ~np.isfinite(eps)).any():
            k, i, j = np.argwhere(valid & ~np.isfinite(eps))[0]
            raise RejectedMessage(f"strains: {layer} gauge [{k}, {i}, {j}] is flagged valid but not finite")


_CHECKS: dict[str, Callable[[Any, bytes], None]] = {
    "elements": _check_elements, "surface": _check_surface, "strains": _check_strains,
}


def check_message(kind: str, payload: bytes) -> Any:
    """Decode a ``kind`` payload and check it against the layout's rules; the decoded message,
    or MessageError (RejectedMessage for a rule broken by a well-formed buffer) naming why."""
    _check_kind(kind, ALL_KINDS)
    decoded = DECODERS[kind](payload)
    if kind in _CHECKS:
        header = bytes(payload[:messages.HEADER_SIZE])
        if header[6:8] != b"\0\0":
            raise RejectedMessage(f"{kind}: reserved header bytes are not 0")
        _CHECKS[kind](decoded, bytes(payload))
    return decoded


def _check_kind(kind: str, allowed: tuple[str, ...]) -> None:
    if kind not in allowed:
        raise ValueError(f"unknown message kind {kind!r}; expected one of {allowed}")


class _DropOldestQueue:
    """Bounded queue fed from a Zenoh callback: never blocks; drops the oldest when full."""

    def __init__(self, maxsize: int) -> None:
        self.queue: queue.Queue[bytes | None] = queue.Queue(maxsize)
        self.dropped = 0

    def push(self, item: bytes | None) -> None:
        while True:
            try:
                self.queue.put_nowait(item)
                return
            except queue.Full:
                try:
                    self.queue.get_nowait()
                    self.dropped += 1
                except queue.Empty:
                    pass


class Subscription:
    """A callback subscription: the user callback runs on a dedicated thread (it may block or
    use the client); stop it with ``close()``."""

    def __init__(self, session: zenoh.Session, key: str, decode: Callable[[bytes], Any],
                 callback: Callable[[Any], None], queue_size: int,
                 on_error: Callable[[Exception], None] | None,
                 on_reject: Callable[[messages.MessageError], None] | None = None) -> None:
        self._buffer = _DropOldestQueue(queue_size)
        self._decode = decode
        self._callback = callback
        self._on_error = on_error
        self._on_reject = on_reject
        self._subscriber = session.declare_subscriber(
            key, lambda sample: self._buffer.push(sample.payload.to_bytes()))
        self._thread = threading.Thread(target=self._run, daemon=True,
                                        name=f"skinmap-client-{key}")
        self._thread.start()

    @property
    def dropped(self) -> int:
        """Messages discarded because the callback fell behind."""
        return self._buffer.dropped

    def _run(self) -> None:
        while True:
            payload = self._buffer.queue.get()
            if payload is None:
                return
            try:
                try:
                    decoded = self._decode(payload)
                except messages.MessageError as exc:
                    if self._on_reject is not None:
                        self._on_reject(exc)
                    raise
                self._callback(decoded)
            except Exception as exc:  # keep delivering; report through on_error if given
                if self._on_error is not None:
                    self._on_error(exc)

    def close(self) -> None:
        self._subscriber.undeclare()
        self._buffer.push(None)
        if threading.current_thread() is not self._thread:
            self._thread.join(timeout=2.0)


class SkinmapClient:
    """Subscriber/query helper for one skinmapd device. Use as a context manager.

    Blocking reads (``elements``, ``surface``, ``strains``, iterators) start their subscription
    on first use and then return messages in arrival order from a bounded queue of
    ``queue_size`` (oldest dropped when the reader falls behind; see ``dropped``).
    Messages that break their layout's rules are skipped (``rejected``, ``rejections``).
    """

    def __init__(self, connect: Iterable[str] = ("tcp/127.0.0.1:7447",), prefix: str = "skinmap",
                 device: str = "demo", *, mode: str = "peer", allow_non_loopback: bool = False,
                 config_file: str | Path | None = None, queue_size: int = 16) -> None:
        if queue_size < 1:
            raise ValueError(f"queue_size must be >= 1, got {queue_size}")
        self._keys = {kind: key_for(prefix, device, kind) for kind in (*ALL_KINDS, "alive")}
        self._config = make_session_config([], list(connect), mode=mode,
                                           allow_non_loopback=allow_non_loopback,
                                           config_file=config_file)
        self._queue_size = queue_size
        self._session: zenoh.Session | None = None
        self._lock = threading.Lock()
        self._streams: dict[str, tuple[Any, _DropOldestQueue]] = {}
        self._subscriptions: list[Subscription] = []
        self._rejected: collections.Counter[str] = collections.Counter()
        self._rejections: dict[str, collections.deque[str]] = {}

    # -- lifecycle --------------------------------------------------------------------------

    def open(self) -> "SkinmapClient":
        if self._session is None:
            self._session = zenoh.open(self._config)
        return self

    def close(self) -> None:
        """Undeclare everything and close the session (idempotent)."""
        session, self._session = self._session, None
        if session is None:
            return
        for sub in self._subscriptions:
            sub.close()
        self._subscriptions.clear()
        for subscriber, buffer in self._streams.values():
            subscriber.undeclare()
            buffer.push(None)  # wake blocked readers
        self._streams.clear()
        session.close()

    def __enter__(self) -> "SkinmapClient":
        return self.open()

    def __exit__(self, *_exc: object) -> None:
        self.close()

    @property
    def session(self) -> zenoh.Session:
        if self._session is None:
            raise RuntimeError("SkinmapClient is not open (use it in a with-block or call open())")
        return self._session

    @property
    def keys(self) -> dict[str, str]:
        return dict(self._keys)

    def dropped(self, kind: str = "elements") -> int:
        """Messages of ``kind`` discarded because the reader fell behind."""
        stream = self._streams.get(kind)
        return stream[1].dropped if stream else 0

    def rejected(self, kind: str = "elements") -> int:
        """Messages of ``kind`` dropped because they break the layout's rules (forged or
        damaged: undecodable, NaN in a VALID element, counts disagreeing with the header...)."""
        with self._lock:
            return self._rejected[kind]

    def rejections(self, kind: str = "elements") -> list[str]:
        """Why the most recent rejected ``kind`` messages were dropped (up to 16, oldest first)."""
        with self._lock:
            return list(self._rejections.get(kind, ()))

    def _reject(self, kind: str, exc: Exception) -> None:
        with self._lock:
            self._rejected[kind] += 1
            self._rejections.setdefault(kind, collections.deque(maxlen=_REJECTIONS_KEPT)).append(str(exc))

    def _decode(self, kind: str, payload: bytes) -> Any:
        try:
            return check_message(kind, payload)
        except messages.MessageError as exc:
            self._reject(kind, exc)
            raise

    def pending(self, kind: str = "elements") -> int:
        """Messages of ``kind`` received and not yet read."""
        stream = self._streams.get(kind)
        return stream[1].queue.qsize() if stream else 0

    # -- streams ----------------------------------------------------------------------------

    def _stream(self, kind: str) -> _DropOldestQueue:
        session = self.session
        with self._lock:
            if kind not in self._streams:
                buffer = _DropOldestQueue(self._queue_size)
                # The callback only copies the bytes into the queue: no blocking, no Zenoh calls.
                subscriber = session.declare_subscriber(
                    self._keys[kind], lambda sample: buffer.push(sample.payload.to_bytes()))
                self._streams[kind] = (subscriber, buffer)
            return self._streams[kind][1]

    def subscribe(self, kind: str) -> None:
        """Start queueing ``kind`` now, so that the next read returns the first message after
        this call (reads otherwise subscribe on first use)."""
        _check_kind(kind, _STREAM_KINDS)
        self._stream(kind)

    def next(self, kind: str, timeout: float | None = 5.0) -> Any:
        """Block for the next well-formed ``kind`` message and return it decoded; TimeoutError
        if none arrives within ``timeout`` seconds (None waits for ever). Messages breaking the
        layout's rules are skipped and counted (``rejected``)."""
        _check_kind(kind, _STREAM_KINDS)
        buffer = self._stream(kind)
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            wait = None if deadline is None else max(0.0, deadline - time.monotonic())
            try:
                payload = buffer.queue.get(timeout=wait)
            except queue.Empty:
                raise TimeoutError(f"no {kind} message on {self._keys[kind]!r} within "
                                   f"{timeout} s") from None
            if payload is None:
                raise RuntimeError("SkinmapClient was closed while waiting")
            try:
                return self._decode(kind, payload)
            except messages.MessageError:
                continue

    def elements(self, timeout: float | None = 5.0) -> messages.ElementsMessage:
        """Next elements message (per-element positions/normals in metres)."""
        return self.next("elements", timeout)

    def surface(self, timeout: float | None = 5.0) -> messages.SurfaceMessage:
        """Next surface message (node grid, normals, uncertainty, point cloud)."""
        return self.next("surface", timeout)

    def strains(self, timeout: float | None = 5.0) -> messages.StrainsMessage:
        return self.next("strains", timeout)

    def iter_messages(self, kind: str, timeout: float | None = 5.0) -> Iterator[Any]:
        """Yield ``kind`` messages as they arrive; stops when the client closes or nothing
        arrives within ``timeout`` seconds."""
        while self._session is not None:
            try:
                yield self.next(kind, timeout)
            except (TimeoutError, RuntimeError):
                return

    def iter_elements(self, timeout: float | None = 5.0) -> Iterator[messages.ElementsMessage]:
        return self.iter_messages("elements", timeout)

    def on_message(self, kind: str, callback: Callable[[Any], None], *,
                   on_error: Callable[[Exception], None] | None = None) -> Subscription:
        """Call ``callback(decoded_message)`` for each ``kind`` message on a client thread."""
        _check_kind(kind, _STREAM_KINDS)
        sub = Subscription(self.session, self._keys[kind], lambda p: check_message(kind, p),
                           callback, self._queue_size, on_error,
                           on_reject=lambda exc: self._reject(kind, exc))
        self._subscriptions.append(sub)
        return sub

    def on_elements(self, callback: Callable[[messages.ElementsMessage], None], *,
                    on_error: Callable[[Exception], None] | None = None) -> Subscription:
        return self.on_message("elements", callback, on_error=on_error)

    # -- queries ----------------------------------------------------------------------------

    def latest(self, kind: str, timeout: float = 2.0) -> Any:
        """The daemon's latest cached ``kind`` message, decoded. LookupError if nothing
        answers within ``timeout`` (daemon absent or nothing published yet)."""
        _check_kind(kind, ALL_KINDS)
        key = self._keys[kind]
        errors = []
        for reply in self.session.get(key, timeout=timeout):
            if reply.ok is not None:
                try:
                    return self._decode(kind, reply.ok.payload.to_bytes())
                except messages.MessageError as exc:
                    errors.append(f"rejected reply: {exc}")
                    continue
            if reply.err is not None:
                errors.append(reply.err.payload.to_string())
        detail = f": {'; '.join(errors)}" if errors else ""
        raise LookupError(f"no {kind} available on {key!r} (is skinmapd running and has it "
                          f"published one yet?){detail}")

    def info(self, timeout: float = 2.0) -> dict[str, Any]:
        """Device description: array geometry, element layout, calibration, versions."""
        return self.latest("info", timeout)

    def status(self, timeout: float = 2.0) -> dict[str, Any]:
        """The latest status report (rates, drops, CRC errors, reconnects, solver time...)."""
        return self.latest("status", timeout)

    def alive(self, timeout: float = 1.0) -> bool:
        """True if the device's liveliness token is currently declared."""
        replies = self.session.liveliness().get(self._keys["alive"], timeout=timeout)
        return any(reply.ok is not None for reply in replies)


def discover(session: zenoh.Session, prefix: str, timeout: float = 2.0) -> list[str]:
    """Device names whose liveliness token `<prefix>/<device>/alive` is declared now."""
    check_key_segment("prefix", prefix)
    found = set()
    for reply in session.liveliness().get(f"{prefix}/*/alive", timeout=timeout):
        if reply.ok is not None:
            parts = str(reply.ok.key_expr).split("/")
            if len(parts) >= 2 and parts[-1] == "alive":
                found.add(parts[-2])
    return sorted(found)
