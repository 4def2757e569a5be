"""Live view: subscribe to gateways over Zenoh and serve the Foxglove WebSocket protocol
(foxglove-sdk's server) on loopback, so the Foxglove app shows the live scene.

The bridge only subscribes (and queries each device's latest values once, for an at-once
picture). Every message is checked as the client checks it; its Foxglove views are the very
ones the MCAP log stores (``skinmap.daemon.mcapschema.wire_views``), under ``/<device>/...``:
``scene``, ``elements/poses``, ``elements/plot``, ``strains/plot``, ``surface`` (point cloud),
``tf`` and ``status``. The skinmap binary layouts themselves are not served (Foxglove cannot
decode them).
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from typing import Any, Iterable

import foxglove
import zenoh

from skinmap.daemon.mcapschema import LAYOUT_SCHEMA_ENCODING, TopicSpec, device_topic, wire_views
from skinmap.wire import messages
from skinmap.wire.keys import check_key_segment
from skinmap.wire.session import check_loopback_endpoint

log = logging.getLogger(__name__)

BRIDGED_KINDS = ("elements", "surface", "strains", "status")


class FoxgloveBridge:
    """Zenoh subscriber -> Foxglove WebSocket server on ``host:port`` (port 0: any free one,
    read it from ``port``). ``start()`` / ``stop()``, or use as a context manager."""

    def __init__(self, session: zenoh.Session, prefix: str, devices: Iterable[str] = ("*",), *,
                 host: str = "127.0.0.1", port: int = 8765, allow_non_loopback: bool = False,
                 queue_size: int = 1024, name: str = "skinmap") -> None:
        from skinmap.client import check_message

        check_key_segment("prefix", prefix)
        self.devices = [d if d == "*" else check_key_segment("device", d) for d in devices]
        if not allow_non_loopback:
            check_loopback_endpoint(f"tcp/{host}:{port}", listen=True)
        self.session, self.prefix = session, prefix
        self.host, self._port, self.name = host, port, name
        self._check = check_message
        self._context = foxglove.Context()
        self._channels: dict[str, foxglove.Channel] = {}
        self._q: queue.Queue[tuple[str, str, bytes] | None] = queue.Queue(queue_size)
        self._subscribers: list[Any] = []
        self._server: Any = None
        self._worker = threading.Thread(target=self._run, name="skinmap-foxglove", daemon=True)
        self.forwarded = 0
        self.rejected = 0
        self.dropped = 0

    @property
    def port(self) -> int:
        return self._server.port if self._server is not None else self._port

    def start(self) -> "FoxgloveBridge":
        self._server = foxglove.start_server(name=self.name, host=self.host, port=self._port,
                                             context=self._context)
        self._worker.start()
        for device in self.devices:
            for kind in BRIDGED_KINDS:
                self._subscribers.append(self.session.declare_subscriber(
                    f"{self.prefix}/{device}/{kind}", self._on_sample))
        # The latest of everything at once, from the gateways' latest-value queryable.
        threading.Thread(target=self._fetch_latest, daemon=True,
                         name="skinmap-foxglove-latest").start()
        return self

    def _fetch_latest(self) -> None:
        for device in self.devices:
            try:
                for reply in self.session.get(f"{self.prefix}/{device}/*", timeout=2.0):
                    if reply.ok is not None:
                        self._on_sample(reply.ok)
            except Exception as exc:  # noqa: BLE001 - the live stream goes on without it
                log.warning("latest values of %s: %s", device, exc)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        parts = str(sample.key_expr).split("/")
        if len(parts) < 2 or parts[-1] not in BRIDGED_KINDS:
            return
        try:
            self._q.put_nowait((parts[-2], parts[-1], sample.payload.to_bytes()))
        except queue.Full:
            self.dropped += 1

    def _channel(self, spec: TopicSpec) -> foxglove.Channel:
        channel = self._channels.get(spec.topic)
        if channel is None:
            schema = foxglove.Schema(name=spec.schema_name, encoding=spec.schema_encoding,
                                     data=spec.schema_data)
            channel = foxglove.Channel(spec.topic, schema=schema,
                                       message_encoding=spec.message_encoding,
                                       context=self._context)
            self._channels[spec.topic] = channel
        return channel

    def _forward(self, device: str, kind: str, payload: bytes) -> None:
        try:
            msg = self._check(kind, payload)
        except messages.MessageError as exc:
            self.rejected += 1
            log.warning("%s/%s rejected: %s", device, kind, exc)
            return
        if kind == "status":
            spec = device_topic("/status", device)
            views: list[tuple[TopicSpec, bytes, int | None, int]] = [
                (spec, messages.encode_status(msg), None, int(msg["host_time_ns"]))]
        else:
            latency = (time.time_ns() - msg.host_time_ns) / 1e6 if kind == "elements" else None
            views = wire_views(kind, payload, msg.host_time_ns, device, latency)
        for spec, data, _seq, t_ns in views:
            if spec.schema_encoding == LAYOUT_SCHEMA_ENCODING:
                continue  # skinmap binary layouts: for skinmap tools, not for Foxglove
            self._channel(spec).log(data, log_time=t_ns)
        self.forwarded += 1

    def _run(self) -> None:
        while True:
            item = self._q.get()
            if item is None:
                return
            try:
                self._forward(*item)
            except Exception as exc:  # noqa: BLE001 - one bad message must not stop the view
                log.warning("forwarding %s/%s failed: %s", item[0], item[1], exc)

    def stop(self) -> None:
        for sub in self._subscribers:
            sub.undeclare()
        self._subscribers.clear()
        if self._worker.is_alive():
            self._q.put(None)
            self._worker.join(timeout=10)
        if self._server is not None:
            self._server.stop()
            self._server = None

    def __enter__(self) -> "FoxgloveBridge":
        return self.start()

    def __exit__(self, *_exc: object) -> None:
        self.stop()


__all__ = ["FoxgloveBridge", "BRIDGED_KINDS"]
