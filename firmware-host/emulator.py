"""The emulator runtime: the pure :class:`~skinmap.emulator.device.Device` behind a transport,
driven by a select loop that writes each scan when its time comes.

    emu = Emulator(ScannerSpec(n=5, m=5), make_shape("cylinder", radius=40),
                   PtyTransport("/tmp/skinmap-emulator/ttySKIN0"))
    emu.start()                       # background thread; or emu.run(duration) in the foreground
    ...  serial.Serial("/tmp/skinmap-emulator/ttySKIN0") ...
    emu.ground_truth(sample_index)    # true geometry of a scan that was sent
    emu.stop()

The scanner is powered by its host link: it boots when the pseudo-terminal appears (or when a
TCP client connects) and is off while the link is gone (disconnect), so a reconnect brings a
fresh HELLO.  Ground truth never goes over the wire: it is available from Python and, with
``truth_path``, as JSON lines (one per scan sent).
"""
from __future__ import annotations

import json
import math
import select
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, TextIO

import numpy as np

from skinmap.emulator.device import Device, ScannerSpec, ScanRecord
from skinmap.emulator.linkfaults import FaultyLink, LinkFaults
from skinmap.emulator.physics import GroundTruth, Shape
from skinmap.emulator.transport import TcpTransport, Transport

__all__ = ["FaultSchedule", "Emulator"]


@dataclass(frozen=True)
class FaultSchedule:
    """Periodic faults (0 = never).  First occurrence one period after start."""

    stall_every_s: float = 0.0
    stall_for_s: float = 0.0
    disconnect_every_s: float = 0.0
    disconnect_for_s: float = 0.0
    reboot_every_s: float = 0.0

    def __post_init__(self):
        for name, v in vars(self).items():
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"FaultSchedule.{name} must be a finite number >= 0 s, got {v!r}")
        if self.stall_every_s and not self.stall_for_s:
            raise ValueError("stall_every_s needs stall_for_s > 0")
        if self.disconnect_every_s and not self.disconnect_for_s:
            raise ValueError("disconnect_every_s needs disconnect_for_s > 0")


class Emulator:
    def __init__(
        self,
        config: ScannerSpec,
        shape: Shape,
        transport: Transport,
        link_faults: LinkFaults = LinkFaults(),
        schedule: FaultSchedule = FaultSchedule(),
        truth_path: str | Path | None = None,
        element_uv: np.ndarray | None = None,
        clock: Callable[[], float] = time.monotonic,
    ):
        self.config = config
        self.shape = shape
        self.transport = transport
        self.schedule = schedule
        self.clock = clock
        self.link = FaultyLink(link_faults, np.random.default_rng([config.seed, 2]))
        self.element_uv = None if element_uv is None else np.asarray(element_uv, float).reshape(-1, 2)
        self.truth_path = Path(truth_path) if truth_path is not None else None
        self._truth_file: TextIO | None = None
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._reconnect_at: float | None = None
        self.device: Device | None = None
        self.started_at: float | None = None
        self.disconnects = 0
        self.reboots = 0
        self.stalls = 0
        self.on_scan: Callable[[ScanRecord], None] | None = None
        self.error: BaseException | None = None

    # ------------------------------------------------------------------ lifecycle

    @property
    def _device(self) -> Device:
        """The device, once :meth:`open` (or :meth:`start`, :meth:`run`) has created it."""
        if self.device is None:
            raise RuntimeError("the emulator is not open: call open(), start() or run() first")
        return self.device

    def open(self) -> None:
        """Create the device and open the transport (the scanner powers up with its link)."""
        with self._lock:
            now = self.clock()
            self.started_at = now
            self.device = Device(self.config, self.shape, now_s=now)
            self.device.on_scan = self._record_truth
            sched = self.schedule
            self._next_stall = now + sched.stall_every_s if sched.stall_every_s else math.inf
            self._next_disconnect = now + sched.disconnect_every_s if sched.disconnect_every_s else math.inf
            self._next_reboot = now + sched.reboot_every_s if sched.reboot_every_s else math.inf
            if self.truth_path is not None:
                self.truth_path.parent.mkdir(parents=True, exist_ok=True)
                self._truth_file = self.truth_path.open("w", encoding="utf-8")
            self.transport.open()

    def close(self) -> None:
        with self._lock:
            self.transport.close()
            if self._truth_file is not None:
                self._truth_file.close()
                self._truth_file = None

    def start(self) -> "Emulator":
        """Open and run the loop in a background thread until :meth:`stop`."""
        if self.device is None:
            self.open()
        self._stop.clear()
        self._thread = threading.Thread(target=self._loop, name="skinmap-emulator", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop the background loop and close; re-raises an error that ended the loop."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        self.close()
        if self.error is not None:
            raise RuntimeError("the emulator loop failed") from self.error

    def run(self, duration_s: float | None = None, on_tick: Callable[["Emulator"], None] | None = None,
            tick_s: float = 1.0) -> None:
        """Run in the calling thread for ``duration_s`` (None: until :meth:`request_stop`)."""
        if self.device is None:
            self.open()
        end = math.inf if duration_s is None else self.clock() + duration_s
        next_tick = self.clock() + tick_s
        try:
            while not self._stop.is_set():
                now = self.clock()
                if now >= end:
                    break
                self.step(min(0.05, end - now, max(0.0, next_tick - now)))
                if on_tick is not None and self.clock() >= next_tick:
                    on_tick(self)
                    next_tick += tick_s
        finally:
            self.close()

    def request_stop(self) -> None:
        self._stop.set()

    def _loop(self) -> None:
        try:
            while not self._stop.is_set():
                self.step(0.05)
        except BaseException as exc:  # surfaced by stop(); a silent dead thread would hide it
            self.error = exc
            raise

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    # ------------------------------------------------------------------ one loop iteration

    def step(self, max_wait_s: float = 0.05) -> None:
        """Wait for host bytes or the next due event (at most ``max_wait_s``), then serve."""
        t = self.transport
        with self._lock:
            now = self.clock()
            wake = self._next_wake(now)
            rfds, wfd = t.read_fds(), t.write_fd()
        timeout = min(max_wait_s, max(0.0, wake - now))
        if rfds or wfd is not None:
            try:
                readable, _, _ = select.select(rfds, [wfd] if wfd is not None else [], [], timeout)
            except (OSError, ValueError):
                readable = []  # an fd closed under us (disconnect from another thread)
        else:
            time.sleep(timeout)
            readable = []
        with self._lock:
            now = self.clock()
            self._run_schedule(now)
            dev = self._device
            out = []
            for fd in readable:
                if isinstance(t, TcpTransport) and t.server is not None and fd == t.server.fileno():
                    if t.accept() and not getattr(t, "shared", False):
                        dev.reboot(now, watchdog=False)  # powered by the new connection
                    continue
                data = t.on_readable(fd)
                if data and t.connected:
                    out.append(dev.on_bytes(data, now))
            if t.connected:
                out.append(dev.poll(now, tx_ready=t.tx_ready))
                data = b"".join(out)
                if data:
                    t.send(self.link.apply(data, now))
                t.flush()
            if self._truth_file is not None:
                self._truth_file.flush()

    def _next_wake(self, now: float) -> float:
        wake = min(self._next_stall, self._next_disconnect, self._next_reboot)
        if self._reconnect_at is not None:
            wake = min(wake, self._reconnect_at)
        elif self.transport.connected:
            wake = min(wake, self._device.next_event_s())
        return wake

    def _run_schedule(self, now: float) -> None:
        s = self.schedule
        if self._reconnect_at is not None and now >= self._reconnect_at:
            self._reconnect(now)
        if now >= self._next_stall:
            self._next_stall += s.stall_every_s
            self.stall(s.stall_for_s)
        if now >= self._next_disconnect:
            self._next_disconnect += s.disconnect_every_s
            self.disconnect(s.disconnect_for_s)
        if now >= self._next_reboot:
            self._next_reboot += s.reboot_every_s
            self.reboot()

    # ------------------------------------------------------------------ faults (thread safe)

    def stall(self, duration_s: float) -> None:
        """The firmware hangs: nothing sent or answered for ``duration_s``."""
        with self._lock:
            self._device.stall(self.clock(), duration_s)
            self.stalls += 1

    def reboot(self) -> None:
        """Watchdog reboot: sequence numbers and sample index restart, HELLO again, IDLE."""
        with self._lock:
            self._device.reboot(self.clock(), watchdog=True)
            self.reboots += 1

    def disconnect(self, reconnect_after_s: float | None) -> None:
        """The port vanishes (pty and symlink removed / TCP server closed); after
        ``reconnect_after_s`` (None: never) a NEW port appears behind the same name and the
        scanner boots afresh."""
        with self._lock:
            self.transport.close()
            self.disconnects += 1
            self._reconnect_at = None if reconnect_after_s is None else self.clock() + reconnect_after_s

    def _reconnect(self, now: float) -> None:
        self._reconnect_at = None
        self.transport.open()
        self._device.reboot(now, watchdog=False)

    def set_shape(self, shape: Shape) -> None:
        """Put the emulated sheet into another shape (e.g. a calibration pose)."""
        with self._lock:
            self.shape = shape
            if self.device is not None:
                self.device.set_shape(shape)

    def hidden_truth(self) -> dict[str, np.ndarray]:
        """The device's hidden truths (true gauge factors and layer offsets); see Device."""
        with self._lock:
            return self._device.hidden_truth()

    def set_open(self, mask: np.ndarray) -> None:
        with self._lock:
            self._device.set_open(mask)

    def set_saturated(self, mask: np.ndarray) -> None:
        with self._lock:
            self._device.set_saturated(mask)

    # ------------------------------------------------------------------ truth and status

    def ground_truth(self, sample_index: int, boot: int | None = None) -> GroundTruth:
        """True geometry of a scan that was sent (at the shape time of its TDM step 0)."""
        with self._lock:
            return self._device.ground_truth(sample_index, boot, self.element_uv)

    def _record_truth(self, record: ScanRecord) -> None:
        if self.on_scan is not None:
            self.on_scan(record)
        if self._truth_file is None:
            return
        gt = self._device.ground_truth(record.sample_index, record.boot, self.element_uv)
        line = {
            "boot": record.boot,
            "sample_index": record.sample_index,
            "timestamp_us": record.timestamp_us,
            "step_period_ns": record.step_period_ns,
            "shape_time_s": round(record.shape_time_s, 9),
            "nodes": np.round(gt.nodes, 6).tolist(),
            "normals": np.round(gt.normals, 9).tolist(),
        }
        if gt.element_uv is not None and gt.element_positions is not None and gt.element_normals is not None:
            line["element_uv"] = gt.element_uv.tolist()
            line["element_positions"] = np.round(gt.element_positions, 6).tolist()
            line["element_normals"] = np.round(gt.element_normals, 9).tolist()
        self._truth_file.write(json.dumps(line, separators=(",", ":")) + "\n")

    def status_line(self) -> str:
        with self._lock:
            d = self._device
            now = self.clock()
            up = now - (self.started_at or now)
            link = self.transport.describe() if self.transport.connected else "disconnected"
            return (
                f"t={up:7.1f}s state={d.state.name.lower()} boot={d.boot_count} "
                f"scans={d.scans_sent} dropped={d.scans_dropped} rate={d.scan_rate_mhz / 1000:g}/s "
                f"rx={self.transport.bytes_in}B tx={self.transport.bytes_out}B link={link}"
            )
