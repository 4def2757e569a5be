"""Several gateways and many clients through one Zenoh router: the router, discovery by
liveliness (``skinmap.client.discover``, re-exported here), and a recorder that writes what it receives from one or many gateways to MCAP.

Topology (docs/zenoh.md, *Fleet*): gateways and clients connect to the router's endpoint; the
router routes; nothing scouts (multicast and gossip off), every endpoint is on loopback unless
non-loopback use is asked for explicitly.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable

import zenoh

from skinmap.client import discover
from skinmap.daemon.mcaplog import LogStorageError, McapLogger
from skinmap.wire import messages
from skinmap.wire.keys import check_key_segment
from skinmap.wire.session import make_session_config

log = logging.getLogger(__name__)

RECORDED_KINDS = ("elements", "surface", "strains", "status")


def router_config(listen: Iterable[str], *, allow_non_loopback: bool = False,
                  config_file: str | Path | None = None) -> zenoh.Config:
    """A Zenoh session config in router mode on `listen` (loopback-checked, no scouting)."""
    listen = list(listen)
    if not listen and config_file is None:
        raise ValueError("a router needs at least one listen endpoint, e.g. tcp/127.0.0.1:7447")
    return make_session_config(listen, [], mode="router", allow_non_loopback=allow_non_loopback,
                               config_file=config_file)


@dataclass
class DeviceCounts:
    """What the recorder saw of one device."""

    messages: dict[str, int] = field(default_factory=dict)  # per kind
    rejected: int = 0
    last_seq: dict[str, int] = field(default_factory=dict)
    seq_steps: dict[str, list[int]] = field(default_factory=dict)


class Recorder:
    """Subscribes to `<prefix>/<device>/<kind>` for the given devices (or every device, `*`),
    checks every message against its layout's rules (skinmap.client.check_message), and logs
    it under `/<device>/...` with its Foxglove views. The device's `info` is queried once per
    device and stored as a `/<device>/info` message.

    The Zenoh callbacks only queue the payload; one writer thread encodes and writes (the
    logger is not thread-safe). Synchronous start/stop; use as a context manager.
    """

    def __init__(self, session: zenoh.Session, prefix: str, devices: Iterable[str] = ("*",),
                 directory: str | Path = "recordings", *, basename: str = "skinmap-record",
                 queue_size: int = 4096, **logger_kw: Any) -> None:
        from skinmap.client import check_message

        check_key_segment("prefix", prefix)
        self.devices = [d if d == "*" else check_key_segment("device", d) for d in devices]
        if not self.devices:
            raise ValueError("give at least one device (or '*' for every device)")
        self._check = check_message
        self.session = session
        self.prefix = prefix
        self.logger = McapLogger(directory, basename=basename, create_directory=True,
                                 metadata={"recorder_prefix": prefix,
                                           "recorder_devices": ",".join(self.devices)},
                                 **logger_kw)
        self.counts: dict[str, DeviceCounts] = {}
        self.dropped = 0  # queue overflow (the writer fell behind)
        self.storage_errors = 0
        self._q: queue.Queue[tuple[str, str, bytes, int] | None] = queue.Queue(queue_size)
        self._info_done: set[str] = set()
        self._subscribers: list[Any] = []
        self._writer = threading.Thread(target=self._write_loop, name="skinmap-recorder",
                                        daemon=True)
        self._started = False

    def _on_sample(self, sample: zenoh.Sample) -> None:
        parts = str(sample.key_expr).split("/")
        device, kind = parts[-2], parts[-1]
        try:
            self._q.put_nowait((device, kind, sample.payload.to_bytes(), time.time_ns()))
        except queue.Full:
            self.dropped += 1

    def start(self) -> "Recorder":
        if self._started:
            return self
        self._started = True
        self._writer.start()
        for device in self.devices:
            for kind in RECORDED_KINDS:
                self._subscribers.append(self.session.declare_subscriber(
                    f"{self.prefix}/{device}/{kind}", self._on_sample))
        return self

    def _count(self, device: str) -> DeviceCounts:
        return self.counts.setdefault(device, DeviceCounts())

    def _record_info(self, device: str, t_ns: int) -> None:
        self._info_done.add(device)
        try:
            replies = list(self.session.get(f"{self.prefix}/{device}/info", timeout=2.0))
        except Exception as exc:  # noqa: BLE001 - a failed query must not stop the recording
            log.warning("info of %s: %s", device, exc)
            return
        for reply in replies:
            if reply.ok is None:
                continue
            try:
                info = messages.decode_info(reply.ok.payload.to_bytes())
            except messages.MessageError as exc:
                log.warning("info of %s rejected: %s", device, exc)
                continue
            self.logger.write(f"/{device}/info", t_ns, messages.encode_info(info),
                              schema_name="skinmap.Info", schema_encoding="jsonschema",
                              schema_data=b'{"title":"skinmap.Info","type":"object"}',
                              message_encoding="json")
            return

    def _write_one(self, device: str, kind: str, payload: bytes, t_rx: int) -> None:
        counts = self._count(device)
        try:
            msg = self._check(kind, payload)
        except messages.MessageError as exc:
            counts.rejected += 1
            log.warning("%s/%s rejected: %s", device, kind, exc)
            return
        if device not in self._info_done:
            self._record_info(device, t_rx)
        counts.messages[kind] = counts.messages.get(kind, 0) + 1
        if kind == "status":
            self.logger.log_status(int(msg.get("host_time_ns", t_rx)), msg, device=device)
            return
        prev = counts.last_seq.get(kind)
        if prev is not None:
            counts.seq_steps.setdefault(kind, []).append((msg.seq - prev) % 2**32)
        counts.last_seq[kind] = msg.seq
        if kind == "elements":
            self.logger.log_elements(msg.host_time_ns, payload, (t_rx - msg.host_time_ns) / 1e6,
                                     device=device)
        elif kind == "surface":
            self.logger.log_surface(msg.host_time_ns, payload, device=device)
        elif kind == "strains":
            self.logger.log_strains(msg.host_time_ns, payload, device=device)

    def _write_loop(self) -> None:
        last_tick = time.monotonic()
        while True:
            try:
                item = self._q.get(timeout=0.5)
            except queue.Empty:
                item = ()  # type: ignore[assignment]
            if item is None:
                return
            try:
                if item:
                    self._write_one(*item)
                if time.monotonic() - last_tick >= 1.0:
                    last_tick = time.monotonic()
                    self.logger.tick()
            except LogStorageError as exc:
                self.storage_errors += 1
                log.error("recording: %s", exc)
            except Exception as exc:  # noqa: BLE001 - one bad message must not end the recording
                log.warning("recording a message failed: %s", exc)

    def stop(self) -> None:
        """Undeclare, write what is queued, finish the file (idempotent)."""
        for sub in self._subscribers:
            sub.undeclare()
        self._subscribers.clear()
        if self._started and self._writer.is_alive():
            self._q.put(None)
            self._writer.join(timeout=30)
        self.logger.close()

    def __enter__(self) -> "Recorder":
        return self.start()

    def __exit__(self, *_exc: object) -> None:
        self.stop()
