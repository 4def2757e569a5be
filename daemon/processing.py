"""The processing thread: scans due at the output rate → pipeline → output.

A `QueuedListener` of the gateway's Notifier: the scans due (chosen on the link thread by the
host clock) wait in a queue of PROCESS_QUEUE_SIZE where the newest wins; the skipped ones are
counted in `dropped` (status `scans_dropped_queue`).  Below the scan rate, the `[output]
lead_scans` scans just before each due one are reconstructed too, not published (their strains
logged as `/strains/lead`), so that the warm fit of the scan due starts one scan back
(docs/architecture.md, "Lead scans"); a lead is skipped where a scan due already waits.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Callable

from skinmap.daemon.device_setup import ScannerState
from skinmap.daemon.fanout import Event, Notifier, QueuedListener, Record, ScanReceived, WireRecord
from skinmap.daemon.output import ResultOutput, encode_result_strains
from skinmap.daemon.pacing import HostDecimator
from skinmap.daemon.pipeline import FramePipeline, FrameResult, WorkerBackground

__all__ = ["ProcessingListener", "PROCESS_QUEUE_SIZE"]

log = logging.getLogger("skinmapd")

PROCESS_QUEUE_SIZE = 2


@dataclass(frozen=True, slots=True)
class _LeadScan(Record):
    """A scan just before one due: reconstructed, so the next warm start is one scan old."""

    received: ScanReceived


class ProcessingListener(QueuedListener):
    """Reconstructs the scans due and hands the results to the output.

    `on_new_pipeline(pipeline)` runs (on this thread) after every (re)connect's new pipeline,
    before its first scan is published; `on_first_result()` once, after the first scan."""

    def __init__(self, rate_hz: float, scanner: ScannerState, output: ResultOutput, notifier: Notifier, *,
                 on_new_pipeline: Callable[[FramePipeline], None],
                 on_first_result: Callable[[], None], lead_scans: int = 0, scan_rate_hz: float = 0.0) -> None:
        super().__init__("skinmap-process", PROCESS_QUEUE_SIZE, keep="newest", drain=False)
        self.scanner = scanner
        self.output = output
        self.notifier = notifier
        self._decimator = HostDecimator(rate_hz)
        # how long before a scan due its lead scans arrive (none at every scan, or unknown rate)
        self._lead_ns = int(round(lead_scans * 1e9 / scan_rate_hz)) if scan_rate_hz > 0 else 0
        self.leads = 0  # lead scans reconstructed
        self.leads_skipped = 0  # lead scans skipped because a scan due was already waiting
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

    def on_record(self, record: Record) -> None:
        if isinstance(record, ScanReceived) and not self._decimator.due(record.t_mono_ns):
            if self._decimator.ahead(record.t_mono_ns, self._lead_ns):
                super().on_record(_LeadScan(record))
            return
        super().on_record(record)

    def accepts(self, record: Record) -> bool:
        # (on_record has passed over the scans not due)
        if isinstance(record, _LeadScan):
            return True
        if not isinstance(record, ScanReceived):
            return False
        if self.waiting_since is None:
            self.waiting_since = record.t_mono_ns / 1e9
        return True

    def handle(self, record: Record) -> None:
        lead = False
        if isinstance(record, _LeadScan):
            if self._queue.qsize():  # a scan due waits: the lead would only delay it
                self.leads_skipped += 1
                return
            record, lead = record.received, True
        assert isinstance(record, ScanReceived)
        try:
            with self._background.busy():  # the restart chain waits while a frame is under way
                self._process(record, lead)
        except Exception as exc:  # noqa: BLE001 - one bad frame must not stop the service
            self.errors += 1
            text = f"processing failed: {type(exc).__name__}: {exc}"
            if text != self.error:  # a repeated failure is counted, not re-logged
                log.exception("processing scan %s failed", record.scan.sample_index)
                self.notifier.notify(Event(time.time_ns(), "error", text))
            self.error = text

    def finish(self) -> None:
        self._background.close()

    def _process(self, record: ScanReceived, lead: bool = False) -> None:
        pipeline, new = self.scanner.ensure_pipeline()
        if pipeline is None:
            return
        if new:
            pipeline.background = self._background
            self._on_new_pipeline(pipeline)
        scan = record.scan
        if (scan.n, scan.m) != (pipeline.geometry.n, pipeline.geometry.m):
            return
        result = pipeline.process(scan.resistances_ohm(), scan.sample_index, scan.timestamp_us, record.t_rx_ns,
                                  lead=lead)
        if lead:
            # logged so that replay reconstructs it too (the chain's next warm start)
            self.leads += 1
            self.notifier.notify(WireRecord("lead", result.host_time_ns, encode_result_strains(result)))
            return
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
