"""The processing thread: scans due at the output rate → pipeline → output.

A `QueuedListener` of the gateway's Notifier: the scans due (chosen on the link thread by the
host clock) wait in a queue of PROCESS_QUEUE_SIZE where the newest wins; the skipped ones are
counted in `dropped` (status `scans_dropped_queue`).
"""
from __future__ import annotations

import logging
import time
from typing import Callable

from skinmap.daemon.device_setup import ScannerState
from skinmap.daemon.fanout import Event, Notifier, QueuedListener, Record, ScanReceived
from skinmap.daemon.output import ResultOutput
from skinmap.daemon.pacing import HostDecimator
from skinmap.daemon.pipeline import FramePipeline, FrameResult, WorkerBackground

__all__ = ["ProcessingListener", "PROCESS_QUEUE_SIZE"]

log = logging.getLogger("skinmapd")

PROCESS_QUEUE_SIZE = 2


class ProcessingListener(QueuedListener):
    """Reconstructs the scans due and hands the results to the output.

    `on_new_pipeline(pipeline)` runs (on this thread) after every (re)connect's new pipeline,
    before its first scan is published; `on_first_result()` once, after the first scan."""

    def __init__(self, rate_hz: float, scanner: ScannerState, output: ResultOutput, notifier: Notifier, *,
                 on_new_pipeline: Callable[[FramePipeline], None],
                 on_first_result: Callable[[], None]) -> None:
        super().__init__("skinmap-process", PROCESS_QUEUE_SIZE, keep="newest", drain=False)
        self.scanner = scanner
        self.output = output
        self.notifier = notifier
        self._decimator = HostDecimator(rate_hz)
        self._on_new_pipeline = on_new_pipeline
        self._on_first_result: Callable[[], None] | None = on_first_result
        self.results_count = 0
        self.errors = 0
        self.last_seq = -1
        self.last_solver_ms = 0.0
        self.error = ""  # the last scan's failure; empty once a scan succeeds
        # Since when a scan has waited with none processed and published (None: nothing waits).
        self.waiting_since: float | None = None
        self.results: list[FrameResult] = []  # the latest few, for tests and the console
        # the graph fit's restart chains run here, beside the published frames
        self._background = WorkerBackground()

    def accepts(self, record: Record) -> bool:
        if not isinstance(record, ScanReceived) or not self._decimator.due(record.t_mono_ns):
            return False
        if self.waiting_since is None:
            self.waiting_since = record.t_mono_ns / 1e9
        return True

    def handle(self, record: Record) -> None:
        assert isinstance(record, ScanReceived)
        try:
            with self._background.busy():  # the restart chain waits while a frame is under way
                self._process(record)
        except Exception as exc:  # noqa: BLE001 - one bad frame must not stop the service
            self.errors += 1
            text = f"processing failed: {type(exc).__name__}: {exc}"
            if text != self.error:  # a repeated failure is counted, not re-logged
                log.exception("processing scan %s failed", record.scan.sample_index)
                self.notifier.notify(Event(time.time_ns(), "error", text))
            self.error = text

    def finish(self) -> None:
        self._background.close()

    def _process(self, record: ScanReceived) -> None:
        pipeline, new = self.scanner.ensure_pipeline()
        if pipeline is None:
            return
        if new:
            pipeline.background = self._background
            self._on_new_pipeline(pipeline)
        scan = record.scan
        if (scan.n, scan.m) != (pipeline.geometry.n, pipeline.geometry.m):
            return
        result = pipeline.process(scan.resistances_ohm(), scan.sample_index, scan.timestamp_us, record.t_rx_ns)
        self.error = ""
        self.results_count += 1
        self.last_seq = result.seq
        self.last_solver_ms = result.solve_time_s * 1e3
        self.results = [*self.results[-3:], result]
        if self.output.publish(result, record.t_mono_ns, pipeline):
            self.waiting_since = None  # the data path has caught up: the watchdog may be fed
        if self._on_first_result is not None:
            first, self._on_first_result = self._on_first_result, None
            first()
