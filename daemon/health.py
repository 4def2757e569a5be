"""The gateway's status and health: counts of scans as they arrive, the scanner clock's sanity,
the `status` report with its named warnings (docs/zenoh.md), and the data-path judgement that
decides whether the systemd watchdog is fed.
"""
from __future__ import annotations

import collections
import logging
import time
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from skinmap.daemon.config import DaemonConfig
from skinmap.daemon.device_setup import ScannerState
from skinmap.daemon.fanout import Event, Listener, Notifier, Record, ScanReceived
from skinmap.daemon.link import ScannerLink
from skinmap.daemon.logsink import LogListener, LogSink
from skinmap.daemon.notify import SystemdNotifier
from skinmap.daemon.output import ResultOutput
from skinmap.daemon.processing import ProcessingListener
from skinmap.protocol import FaultFlag

__all__ = ["DeviceClockCheck", "ScanMonitor", "GatewayStats", "Health", "suspect_gauges", "RECENT_WINDOW_S", "DATA_PATH_TIMEOUT_S"]

log = logging.getLogger("skinmapd")

RECENT_WINDOW_S = 3.0  # status warns about damage and loss seen this recently
# A scan waiting this long with none processed since, or a silent link thread, stops the
# watchdog (at least this; longer when systemd's watchdog period is longer).
DATA_PATH_TIMEOUT_S = 5.0
CLOCK_JUMP_US = 1_000_000  # device time may run ahead of host arrival time by this (buffering)


class DeviceClockCheck:
    """Sanity of the scanner's clock, judged scan by scan against the host's monotonic clock.

    Device time is only data (published and logged with each scan), never a schedule; a clock
    that stands still, runs backwards or jumps ahead is a scanner fault to name in status.
    """

    def __init__(self) -> None:
        self.faults = 0
        self.problem = ""
        self.problem_mono = -float("inf")
        self.reset()

    def reset(self) -> None:
        """A new handshake (reconnect, reboot) restarts the device clock legitimately."""
        self._prev: tuple[int, int, int] | None = None

    def check(self, device_time_us: int, sample_index: int, host_mono_ns: int) -> str:
        """The problem this scan shows ("" if none)."""
        prev, self._prev = self._prev, (device_time_us, sample_index, host_mono_ns)
        if prev is None or sample_index == prev[1]:
            return ""
        d_dev = device_time_us - prev[0]
        d_host_us = (host_mono_ns - prev[2]) // 1000
        if d_dev == 0:
            problem = f"scanner clock stuck at {device_time_us} µs (scans {prev[1]} and {sample_index})"
        elif d_dev < 0:
            problem = (f"scanner clock running backwards: {d_dev / 1e6:+.3f} s from scan {prev[1]} to "
                       f"{sample_index}")
        elif d_dev > d_host_us + CLOCK_JUMP_US:
            problem = (f"scanner clock jumped ahead {d_dev / 1e6:.3f} s from scan {prev[1]} to {sample_index} "
                       f"while {d_host_us / 1e6:.3f} s passed on the host")
        else:
            return ""
        self.faults += 1
        self.problem, self.problem_mono = problem, host_mono_ns / 1e9
        return problem


class ScanMonitor(Listener):
    """Counts every scan as it arrives and checks its clock (on the link thread: cheap)."""

    def __init__(self, on_event: Callable[[str, str], None]) -> None:
        self.clock = DeviceClockCheck()
        self.scans_in = 0
        self.scan_times: collections.deque[float] = collections.deque(maxlen=4096)
        self._on_event = on_event
        self._clock_reported = -float("inf")

    def on_record(self, record: Record) -> None:
        if not isinstance(record, ScanReceived):
            return
        t = record.t_mono_ns / 1e9
        self.scans_in += 1
        self.scan_times.append(t)
        problem = self.clock.check(record.scan.timestamp_us, record.scan.sample_index, record.t_mono_ns)
        if problem and t - self._clock_reported > RECENT_WINDOW_S:
            self._clock_reported = t  # named once per window; `clock.faults` counts all
            self._on_event("warning", problem)


@dataclass(frozen=True)
class GatewayStats:
    """The gateway's counters at one moment."""

    started_mono: float
    scans_in: int
    scans_dropped_queue: int
    results: int
    published: int
    publish_errors: int
    log_dropped: int
    processing_errors: int
    last_seq: int
    last_solver_ms: float


def rate(times: collections.deque[float], window_s: float = 2.0) -> float:
    if not times:
        return 0.0
    now = time.monotonic()
    return sum(1 for t in list(times) if now - t <= window_s) / window_s


def suspect_gauges(diagnostics: dict[str, Any]) -> list[str]:
    """The gauges the reconstruction's gauge screen named in a scan's diagnostics (layer,
    direction, cell and apparent gain each; reconstruction/robust.py), [] if none."""
    text = diagnostics.get("suspect_gauges", "")
    return [part for part in text.split("; ") if part] if isinstance(text, str) else []


class Health:
    """Status report and data-path judgement over the gateway's parts."""

    def __init__(self, cfg: DaemonConfig, link: ScannerLink, monitor: ScanMonitor, processing: ProcessingListener,
                 output: ResultOutput, scanner: ScannerState, log_listener: LogListener | None, sink: LogSink,
                 systemd: SystemdNotifier, notifier: Notifier) -> None:
        self.cfg, self.link, self.monitor, self.processing = cfg, link, monitor, processing
        self.output, self.scanner, self.log_listener, self.sink = output, scanner, log_listener, sink
        self.systemd, self.notifier = systemd, notifier
        self.started_mono = time.monotonic()
        self.link_alive_mono = time.monotonic()
        self.watchdog_fed = False  # the last check found the data path working
        self.data_path_problem_text = ""
        self._recent_marks: collections.deque[tuple[float, int, int, int]] = collections.deque()

    def stats(self) -> GatewayStats:
        p, o = self.processing, self.output.stats
        return GatewayStats(self.started_mono, self.monitor.scans_in, p.dropped, p.results_count, o.published,
                            o.publish_errors, self.log_listener.dropped if self.log_listener else 0, p.errors,
                            p.last_seq, p.last_solver_ms)

    @property
    def log_state(self) -> str:
        return self.log_listener.state if self.log_listener is not None else "off"

    def status(self) -> dict[str, Any]:
        s, ls, o = self.stats(), self.link.stats, self.output.stats
        lat = np.array(o.latencies_ms, dtype=np.float64) if o.latencies_ms else np.zeros(1)
        dec = ls.decoder
        pipeline = self.scanner.pipeline
        return {
            "device": self.output.device or "unknown",
            "host_time_ns": time.time_ns(),
            "connected": self.link.streaming.is_set(),
            "link_state": ls.state,
            "seq": max(s.last_seq, 0),
            "scan_rate_hz": round(rate(self.monitor.scan_times), 2),
            "publish_rate_hz": round(rate(o.publish_times), 2),
            "frames_dropped": int(ls.scans_lost + s.scans_dropped_queue),
            "scans_lost": int(ls.scans_lost),
            "scans_dropped_queue": int(s.scans_dropped_queue),
            "lead_scans": int(self.processing.leads),
            "lead_scans_skipped": int(self.processing.leads_skipped),
            "scans_in": int(s.scans_in),
            "results": int(s.results),
            "crc_errors": int(dec.get("crc_errors", 0)),
            "decoder": dict(dec),
            "reconnects": int(ls.reconnects),
            "stalls": int(ls.stalls),
            "reboots": int(ls.reboots),
            "handshake_failures": int(ls.handshake_failures),
            "last_link_error": ls.last_error,
            "solver_time_ms": round(s.last_solver_ms, 3),
            "latency_ms_median": round(float(np.median(lat)), 3),
            "latency_ms_p99": round(float(np.percentile(lat, 99)), 3),
            "log_state": self.log_state,
            "log_error": self.log_listener.last_error if self.log_listener else "",
            "log_dropped": int(s.log_dropped),
            # Refused by failing storage or cut with an abandoned file (disk full, read-only).
            "log_lost": int(self.sink.messages_dropped + self.sink.messages_lost),
            "log_file": self.sink.current_path or "",
            "log_bytes": int(self.sink.bytes_written),
            "publish_errors": int(s.publish_errors),
            "processing_errors": int(s.processing_errors),
            "calibration": pipeline.calibration.source if pipeline else "",
            "uptime_s": round(time.monotonic() - s.started_mono, 1),
            **self.conditions(),
        }

    def conditions(self) -> dict[str, Any]:
        """Current abnormal conditions, named, so dashboards and `skinmap inspect` see them."""
        warnings: list[str] = []
        ls = self.link.stats
        if not self.link.streaming.is_set():
            warnings.append(f"scanner not streaming ({ls.state}): {ls.last_error}".rstrip(": "))
        elif ls.state == "stalled":
            warnings.append(f"scanner stalled: {ls.last_error}")
        if self.log_state == "error" and self.log_listener is not None:
            warnings.append(f"logging failed (publishing continues): {self.log_listener.last_error}")
        if self.processing.error:
            warnings.append(f"{self.processing.error} (nothing published for these scans)")
        if self.scanner.tare_problem:
            warnings.append(f"{self.scanner.tare_problem} (factory calibration in use)")
        if self.scanner.elastic_problem:
            warnings.append(self.scanner.elastic_problem)
        if self.scanner.elements_problem:
            warnings.append(self.scanner.elements_problem)
        clock = self.monitor.clock
        if clock.problem and time.monotonic() - clock.problem_mono <= RECENT_WINDOW_S:
            warnings.append(f"{clock.problem} ({clock.faults} clock fault(s) since start; "
                            "output paced by the host clock)")
        if self.data_path_problem_text:
            warnings.append(f"{self.data_path_problem_text}; systemd watchdog not fed")
        faults: list[str] = []
        dev = self.link.device_status
        if dev is not None and dev.fault_flags:
            faults = [str(f.name) for f in FaultFlag if f.value and dev.fault_flags & f.value]
            warnings.append("scanner reports " + ", ".join(faults))
        warnings += self._recent_trouble()
        results = self.processing.results
        if results:
            last = results[-1]
            bad = int((~last.gauge_valid).sum())
            if bad:
                warnings.append(f"{bad} gauge(s) unusable in the last scan (open, saturated or implausible)")
            if last.diagnostics.get("inconsistent"):
                warnings.append("strains of the last scan fit no surface well; elements flagged DEGRADED")
        suspects = suspect_gauges(results[-1].diagnostics) if results else []
        if suspects:
            warnings.append("gauge(s) contradicted by the others in the last scan, left out of the shape: "
                            + "; ".join(suspects) + " (check its calibration: gain off?)")
        return {"healthy": not warnings, "warnings": warnings, "device_faults": faults, "suspect_gauges": suspects}

    def _recent_trouble(self) -> list[str]:
        """Damage and loss in the recent past (counters alone never turn a dashboard red)."""
        ls, dropped = self.link.stats, self.processing.dropped
        now = time.monotonic()
        marks = self._recent_marks
        marks.append((now, ls.frames_rejected, ls.scans_lost, dropped))
        while len(marks) > 1 and now - marks[0][0] > RECENT_WINDOW_S:
            marks.popleft()
        _t0, rejected0, lost0, dropped0 = marks[0]
        out = []
        if ls.frames_rejected > rejected0:
            out.append(f"{ls.frames_rejected - rejected0} damaged frame(s) from the scanner in the last "
                       f"{RECENT_WINDOW_S:g} s (last: {ls.last_frame_error})")
        if ls.scans_lost > lost0:
            out.append(f"{ls.scans_lost - lost0} scan(s) lost on the link in the last {RECENT_WINDOW_S:g} s")
        if dropped > dropped0:
            out.append(f"{dropped - dropped0} scan(s) skipped by the processing queue in the last "
                       f"{RECENT_WINDOW_S:g} s (reconstruction slower than the output rate)")
        return out

    def data_path_problem(self, now: float | None = None) -> str:
        """Why the data path is not working ("" if it is): a scan has waited for processing too
        long with none processed and published since, or the link thread has gone silent."""
        now = time.monotonic() if now is None else now
        timeout = max(DATA_PATH_TIMEOUT_S, self.systemd.watchdog_interval_s)
        since = self.processing.waiting_since
        if since is not None and now - since > timeout:
            errors = self.output.stats.publish_errors
            why = self.processing.error or (f"{errors} publish error(s)" if errors else "processing blocked")
            return f"no scan processed and published for {now - since:.1f} s ({why})"
        d = self.cfg.device
        # The link loop reports in at least once per reconnect cycle (back-off plus handshake).
        link_timeout = max(timeout, d.reconnect_max_s + 4 * d.handshake_timeout_s + 1.0)
        if now - self.link_alive_mono > link_timeout:
            return f"scanner link thread silent for {now - self.link_alive_mono:.1f} s"
        return ""

    def check_data_path(self) -> None:
        """Feed the systemd watchdog while the data path works; say so when it stops and resumes."""
        problem = self.data_path_problem()
        was_problem, self.data_path_problem_text = self.data_path_problem_text, problem
        if problem:
            if not was_problem:
                log.error("%s: not feeding the systemd watchdog", problem)
                self.notifier.notify(Event(time.time_ns(), "error", problem))
            self.watchdog_fed = False
            return
        if was_problem:
            log.info("data path working again; feeding the systemd watchdog")
        self.watchdog_fed = True
        self.systemd.watchdog()
