"""The gateway: the scanner link, its Notifier and the listeners, wired together.

    link thread ──▶ Notifier ──▶ ScanMonitor (counts, clock check; on the link thread)
                             ├─▶ ProcessingListener (queue of 2, newest wins) ──▶ ResultOutput ──▶ Publisher
                             │                                                         └──▶ Notifier
                             └─▶ LogListener (bounded queue, drops counted) ──▶ LogSink (MCAP)
    main thread: status (Health), console line, tare reload, systemd notifications

The link thread never waits on reconstruction, the publisher or the disk. The systemd watchdog
is fed by the main thread only while the data path works (scans are processed and published,
or none arrive to be processed), so a wedged or failing pipeline gets the service restarted.
"""
from __future__ import annotations

import logging
import threading
import time
from typing import Any, Callable

import skinmap
from skinmap.daemon.config import DaemonConfig, config_to_toml
from skinmap.daemon.console import shape_summary
from skinmap.daemon.device_setup import ScannerState, calibration_doc, device_info, device_name
from skinmap.daemon.fanout import (ConfigRecord, Event, Notifier, PoseRecord, RawFrame, Record, ScanReceived,
                                   StatusRecord)
from skinmap.daemon.health import DeviceClockCheck, GatewayStats, Health, ScanMonitor
from skinmap.daemon.link import ScannerLink
from skinmap.daemon.logsink import LogListener, LogSink, NullLogSink
from skinmap.daemon.notify import SystemdNotifier
from skinmap.daemon.output import ResultOutput
from skinmap.daemon.pipeline import FramePipeline, FrameResult
from skinmap.ports import PortFactory
from skinmap.daemon.processing import ProcessingListener
from skinmap.daemon.publisher import PublisherFactory
from skinmap.protocol import Frame, Hello, Scan, encode_frame

__all__ = ["Gateway", "default_log_sink", "limit_blas_threads", "prepare_reconstruction_kernels"]

log = logging.getLogger("skinmapd")

WATCHDOG_CHECK_S = 0.5  # how often the main loop judges the data path
ConsoleFn = Callable[[dict[str, Any], dict[str, Any]], None]
#: Opens the probe-pose input of a device by name, handing records to the given callable;
#: returns something with ``undeclare()`` ([tactile]; skinmap.daemon.poses).
PoseInputFactory = Callable[[str, Callable[[Record], None]], Any]


class Gateway:
    """The running service. `run()` blocks until `stop()` (or a signal in `service.main`).

    `publishers` opens the Publisher of a device by name (None: publish nothing);
    `log_sink_factory` makes the log sink when [log] is enabled (default: MCAP files)."""

    def __init__(
        self,
        cfg: DaemonConfig,
        *,
        publishers: PublisherFactory | None = None,
        pose_inputs: PoseInputFactory | None = None,
        port_factory: PortFactory | None = None,
        log_sink_factory: Callable[[DaemonConfig], LogSink] | None = None,
        console: ConsoleFn | None = None,
        notifier: SystemdNotifier | None = None,
    ) -> None:
        self.cfg = cfg
        self._console = console
        self.notifier = notifier or SystemdNotifier()
        self._stop = threading.Event()
        self._shutdown_lock = threading.Lock()
        self._shutting_down = threading.Event()
        self.records = Notifier()
        self.scanner = ScannerState(cfg)
        self.monitor = ScanMonitor(self._on_event)
        self.sink: LogSink = (log_sink_factory or default_log_sink)(cfg) if cfg.log.enabled else NullLogSink()
        self.log: LogListener | None = LogListener(self.sink, cfg.log.queue_size) if cfg.log.enabled else None
        self._pose_inputs = pose_inputs
        self._pose_input: Any = None  # [tactile]: the probe-pose subscriber of the current device
        self.output = ResultOutput(cfg, self.records, publishers, logging_on=self.log is not None)
        self.processing = ProcessingListener(cfg.output.rate_hz, self.scanner, self.output, self.records,
                                             on_new_pipeline=self._on_new_pipeline,
                                             on_first_result=self._on_first_result,
                                             lead_scans=cfg.output.lead_scans, scan_rate_hz=cfg.device.scan_rate_hz)
        for listener in (self.monitor, self.processing, self.log):
            if listener is not None:
                self.records.add_listener(listener)
        self.link = ScannerLink(
            cfg.device,
            on_hello=self._on_hello,
            on_scan=self._on_scan,
            on_frame=self._on_frame,
            on_event=self._on_event,
            on_alive=self._on_link_alive,
            port_factory=port_factory,
        )
        self.health = Health(cfg, self.link, self.monitor, self.processing, self.output, self.scanner,
                             self.log, self.sink, self.notifier, self.records)

    # -- what tests and tools read -----------------------------------------------------------

    @property
    def stats(self) -> GatewayStats:
        return self.health.stats()

    @property
    def results(self) -> list[FrameResult]:
        """The latest few results (for tests and the console)."""
        return self.processing.results

    @property
    def clock(self) -> DeviceClockCheck:
        return self.monitor.clock

    @property
    def watchdog_fed(self) -> bool:
        return self.health.watchdog_fed

    def status(self) -> dict[str, Any]:
        return self.health.status()

    def data_path_problem(self, now: float | None = None) -> str:
        return self.health.data_path_problem(now)

    def info(self) -> dict[str, Any]:
        hello, pipeline = self.scanner.hello, self.scanner.pipeline
        assert hello is not None and pipeline is not None
        return device_info(self.output.device, hello, pipeline, self.cfg, source="live")

    # -- link callbacks (link thread: hand on only) ------------------------------------------

    def _on_frame(self, frame: Frame, t_rx_ns: int) -> None:
        self.records.notify(RawFrame(t_rx_ns, frame.raw))

    def _on_hello(self, hello: Hello) -> None:
        self.scanner.on_hello(hello)
        self.monitor.clock.reset()

    def _on_link_alive(self) -> None:
        self.health.link_alive_mono = time.monotonic()

    def _on_scan(self, scan: Scan, _frame: Frame, t_rx_ns: int) -> None:
        self.records.notify(ScanReceived(scan, t_rx_ns, time.monotonic_ns()))

    def _on_event(self, level: str, text: str) -> None:
        getattr(log, level if level in ("info", "warning", "error") else "info")(text)
        self.records.notify(Event(time.time_ns(), level, text))

    # -- processing thread callbacks ---------------------------------------------------------

    def _on_new_pipeline(self, pipeline: FramePipeline) -> None:
        hello = self.scanner.hello
        assert hello is not None
        self.output.use_device(device_name(hello, self.cfg), self.info)
        if self.cfg.tactile.enabled and self._pose_inputs is not None:
            self._close_pose_input()
            self._pose_input = self._pose_inputs(self.output.device, self._on_pose_input)
        self._log_config()

    def _on_pose_input(self, record: Record) -> None:
        """A record from the pose input: a valid pose is also the one contacts beginning from
        now on carry (ResultOutput.note_pose); everything goes on to the log."""
        if isinstance(record, PoseRecord):
            self.output.note_pose(record.pose)
        self.records.notify(record)

    def _on_first_result(self) -> None:
        self.notifier.ready(f"streaming from {self.cfg.device.port}")

    def _log_config(self) -> None:
        # The HELLO goes along so a log file that starts mid-stream (rotation) replays alone.
        hello, pipeline = self.scanner.hello, self.scanner.pipeline
        if self.log is not None and pipeline is not None and hello is not None:
            doc = calibration_doc(pipeline.calibration)
            doc["hello_frame_hex"] = encode_frame(hello, 0).hex()
            self.records.notify(ConfigRecord(time.time_ns(), config_to_toml(self.cfg), doc))

    # -- main thread -------------------------------------------------------------------------

    def _status_tick(self) -> None:
        st = self.status()
        if self.output.publisher is not None:
            try:
                self.output.publisher.publish_status(st)
            except Exception as exc:  # noqa: BLE001 - status is best effort; the data path goes on
                log.warning("status publish failed: %s", exc)
        self.records.notify(StatusRecord(st["host_time_ns"], st))
        self.notifier.status(f"{st['link_state']}, {st['publish_rate_hz']:.1f} Hz, seq {st['seq']}")
        if self._console is not None:
            r = self.results[-1] if self.results else None
            self._console(st, shape_summary(r.nodes_mm if r is not None else None,
                                            r.element_positions_mm if r is not None else None))
        if self.scanner.reload_if_changed():
            self._log_config()
            self.output.set_info(self.info())

    # -- lifecycle ---------------------------------------------------------------------------

    def start(self) -> None:
        limit_blas_threads()  # before the first solve: replay must see the same arithmetic
        prepare_reconstruction_kernels()
        if self.log is not None:
            self.log.start()
        self.processing.start()
        self.link.start()

    def run(self) -> None:
        """Start, report status and feed the watchdog until stop() is called, then shut down."""
        self.start()
        period = 1.0 / self.cfg.output.status_rate_hz
        next_status = time.monotonic() + period
        try:
            while not self._stop.wait(min(period, WATCHDOG_CHECK_S)):
                if time.monotonic() >= next_status:
                    next_status = max(next_status + period, time.monotonic())
                    self._status_tick()
                self.health.check_data_path()
        finally:
            self.shutdown()

    def _close_pose_input(self) -> None:
        if self._pose_input is not None:
            try:
                self._pose_input.undeclare()
            except Exception as exc:  # a closed session: nothing more arrives anyway
                log.debug("pose subscriber: %s", exc)
            self._pose_input = None

    def stop(self) -> None:
        self._stop.set()

    def shutdown(self) -> None:
        with self._shutdown_lock:
            if self._shutting_down.is_set():
                return
            self._shutting_down.set()
        self._stop.set()
        self.notifier.stopping()
        self.link.stop()
        self._close_pose_input()
        self.records.stop(timeout=10.0)  # processing first, then the log writes what is queued
        self.output.close()
        self.notifier.close()


def default_log_sink(cfg: DaemonConfig) -> LogSink:
    """The MCAP log of the config's [log] table."""
    from skinmap.daemon.mcaplog import McapLogger
    from skinmap.daemon.rotation import RotationPolicy

    lc = cfg.log
    # The folder is created by the logger when it opens a file: a missing or read-only log
    # folder then shows as log_state 'error' in status while publishing goes on.
    return McapLogger(
        cfg.resolve(lc.directory),
        rotation=RotationPolicy(lc.basename, max_bytes=max(4096, int(lc.max_file_mb * 1024 * 1024)),
                                max_seconds=lc.max_file_minutes * 60.0),
        chunk_size=lc.chunk_kb * 1024,
        compression=lc.compression,
        fsync="chunk" if lc.fsync else "never",  # [log] fsync = false: leave syncing to the OS
        metadata={"skinmap_version": skinmap.__version__, "config_source": cfg.source},
        create_directory=True,
    )


def limit_blas_threads() -> None:
    """One BLAS thread: the matrices are small, and idle BLAS worker threads spin on the cores
    the serial reader and the other processes need (measured: 97 % → 31 % CPU at 10 Hz)."""
    from threadpoolctl import threadpool_limits

    import skinmap.reconstruction  # noqa: F401 - load scipy's own BLAS first, so it is limited too

    threadpool_limits(limits=1)


def prepare_reconstruction_kernels() -> None:
    """Compile the reconstruction kernels, or load them from numba's cache, before the scanner
    link opens: the first start after an install compiles for about 15 s, which must not stall
    the first frames (nor count as dropped scans and latency)."""
    from skinmap.reconstruction import Reconstructor

    t0 = time.perf_counter()
    log.info("preparing the reconstruction kernels (the first start after an install compiles them, about 20 s)")
    kernels = Reconstructor(2, 2).kernels  # the warm-up covers every size: one signature
    log.info("reconstruction kernels ready (%s) in %.1f s", kernels, time.perf_counter() - t0)
