"""skinmapd: the gateway service.

Threads, each with one job, joined by bounded queues whose drops are counted:

    link thread ──scans──▶ processing thread ──▶ Zenoh publisher (non-blocking puts)
         │                        │
         └──raw frames──▶ log thread (MCAP) ◀──strains, surfaces, elements
    main thread: status, console line, tare reload, systemd notifications, signals

The link thread never waits on reconstruction, Zenoh or the disk. The systemd watchdog is fed
by the main thread only while the data path works (scans are processed and published, or none
arrive to be processed), so a wedged or failing pipeline gets the service restarted.
"""
from __future__ import annotations

import argparse
import collections
import json
import logging
import os
import queue
import signal
import sys
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

import skinmap
from skinmap.wire import messages
from skinmap.daemon.calibration import Calibration, load_calibration_file, load_tare
from skinmap.daemon.config import ConfigError, DaemonConfig, config_to_toml, load_config
from skinmap.daemon.console import StatusConsole, shape_summary
from skinmap.daemon.link import ScannerLink, open_serial
from skinmap.daemon.notify import SystemdNotifier
from skinmap.daemon.pipeline import ArrayGeometry, FramePipeline, FrameResult
from skinmap.protocol import PROTOCOL_MAJOR, PROTOCOL_MINOR, FaultFlag, Frame, Hello, Scan, encode_frame

__all__ = ["Gateway", "GatewayStats", "main", "pipeline_for_hello", "calibration_for_hello"]

log = logging.getLogger("skinmapd")

PROCESS_QUEUE_SIZE = 2
RECENT_WINDOW_S = 3.0  # status warns about damage and loss seen this recently
MAX_CLOUD_POINTS = 40_000  # the published dense cloud is thinned beyond this (32×32 at 20/pitch is 410k)
# A scan waiting this long with none processed since, or a silent link thread, stops the
# watchdog (at least this; longer when systemd's watchdog period is longer).
DATA_PATH_TIMEOUT_S = 5.0
WATCHDOG_CHECK_S = 0.5  # how often the main loop judges the data path
STOP_GRACE_S = 5.0  # after SIGTERM, the main loop must begin shutting down within this
CLOCK_JUMP_US = 1_000_000  # device time may run ahead of host arrival time by this (buffering)
BLOCK_CLOSE_KEY = "transport/link/tx/queue/congestion_control/block/wait_before_close"
ZENOH_DEFAULT_BLOCK_CLOSE_US = 5_000_000
BLOCK_CLOSE_US = 1_000_000


def geometry_for_hello(hello: Hello, cfg: DaemonConfig) -> ArrayGeometry:
    rc = cfg.reconstruction
    return ArrayGeometry(
        n=hello.n,
        m=hello.m,
        pitch_mm=rc.pitch_mm or hello.pitch_um / 1000.0,
        h_upper_mm=rc.h_upper_mm or hello.h_upper_um / 1000.0,
        h_lower_mm=rc.h_lower_mm or hello.h_lower_um / 1000.0,
        gauge_length_mm=hello.gauge_length_um / 1000.0,
    )


def load_calibration(hello: Hello, cfg: DaemonConfig) -> tuple[Calibration, str]:
    """The scanner's factory calibration with the stored tare applied, and "" -- or, when the
    tare file is no tare of this array, the factory calibration and what is wrong with it."""
    cal = Calibration(hello.gauge_factor(), hello.base_resistance_ohm(), "factory")
    state = cfg.resolve(cfg.state.directory)
    problems = []
    try:
        fit = load_calibration_file(state, hello.serial_number, cal.base_resistance.shape)
        if fit is not None:
            cal = cal.with_mold_fit(fit[0], fit[1], fit[2], f"calibration {fit[3]['created']}", fit[3])
    except ValueError as exc:
        problems.append(f"ignoring calibration {exc}")
        log.warning("%s; using the factory gauge factors", problems[-1])
    try:
        tare = load_tare(state, hello.serial_number, cal.base_resistance.shape)
        if tare is not None:
            cal = cal.with_tare(tare[0], tare[1] if cal.source == "factory" else f"{cal.source}, {tare[1]}")
    except ValueError as exc:
        problems.append(f"ignoring tare {exc}")
        log.warning("%s; using the factory base resistances", problems[-1])
    return cal, "; ".join(problems)


def calibration_for_hello(hello: Hello, cfg: DaemonConfig) -> Calibration:
    """The scanner's factory calibration, with the stored tare applied when there is one."""
    return load_calibration(hello, cfg)[0]


def pipeline_for_hello(hello: Hello, cfg: DaemonConfig, calibration: Calibration | None = None) -> FramePipeline:
    uv, offsets = cfg.elements.material_coordinates()
    return FramePipeline(
        geometry_for_hello(hello, cfg),
        calibration if calibration is not None else calibration_for_hello(hello, cfg),
        np.asarray(uv, dtype=np.float64).reshape(-1, 2),
        np.asarray(offsets, dtype=np.float64),
        strain_sigma=cfg.reconstruction.strain_sigma,
        warm_start=cfg.reconstruction.warm_start,
        convex_solver=cfg.reconstruction.convex_solver,
        graph_fit=cfg.reconstruction.graph_fit,
        twist_sign={"positive": 1, "negative": -1}.get(cfg.reconstruction.twist_sign),
    )


def device_name(hello: Hello, cfg: DaemonConfig) -> str:
    if cfg.device.name:
        return cfg.device.name
    safe = "".join(c if c.isalnum() or c in "-_" else "-" for c in hello.serial_number.strip("\0 "))
    return safe or "scanner"


class HostDecimator:
    """Chooses the scans to process from the HOST clock at their arrival: the output keeps its
    rate whatever the scanner's clock does (replay picks the same scans from the logged strains).

    A scan up to a quarter period early still counts (arrival jitter, scans read in bursts), so
    an output rate equal to the scan rate passes every scan. rate_hz = 0 passes every scan.
    """

    def __init__(self, rate_hz: float) -> None:
        self.period_ns = 0 if rate_hz <= 0 else int(round(1e9 / rate_hz))
        self._next_due: int | None = None

    def due(self, host_mono_ns: int) -> bool:
        if self.period_ns == 0:
            return True
        if self._next_due is None or host_mono_ns >= self._next_due + 4 * self.period_ns:
            self._next_due = host_mono_ns  # first scan or a long gap: restart the schedule here
        if host_mono_ns >= self._next_due - self.period_ns // 4:
            self._next_due += self.period_ns
            return True
        return False


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


@dataclass
class GatewayStats:
    started_mono: float = field(default_factory=time.monotonic)
    scans_in: int = 0
    scans_dropped_queue: int = 0
    results: int = 0
    published: int = 0
    publish_errors: int = 0
    log_dropped: int = 0
    processing_errors: int = 0
    last_seq: int = -1
    last_solver_ms: float = 0.0
    latencies_ms: collections.deque = field(default_factory=lambda: collections.deque(maxlen=256))  # recent only
    scan_times: collections.deque = field(default_factory=lambda: collections.deque(maxlen=4096))
    publish_times: collections.deque = field(default_factory=lambda: collections.deque(maxlen=4096))


def _rate(times: collections.deque, window_s: float = 2.0) -> float:
    if not times:
        return 0.0
    now = time.monotonic()
    recent = [t for t in list(times) if now - t <= window_s]
    return len(recent) / window_s


class Gateway:
    """The running service. `run()` blocks until `stop()` (or a signal in `main`)."""

    def __init__(
        self,
        cfg: DaemonConfig,
        *,
        zenoh_session: Any = None,
        opener: Callable[[str, int, bool], Any] = open_serial,
        logger_factory: Callable[[DaemonConfig], Any] | None = None,
        console: Callable[[dict[str, Any], dict[str, Any]], None] | None = None,
        notifier: SystemdNotifier | None = None,
    ) -> None:
        self.cfg = cfg
        self._session = zenoh_session
        self._console = console
        self.notifier = notifier or SystemdNotifier()
        self.stats = GatewayStats()
        self._stop = threading.Event()
        self._shutdown_lock = threading.Lock()
        self._shutting_down = threading.Event()
        self._proc_q: queue.Queue = queue.Queue(maxsize=PROCESS_QUEUE_SIZE)
        self._log_q: queue.Queue = queue.Queue(maxsize=cfg.log.queue_size)
        self._decimator = HostDecimator(cfg.output.rate_hz)
        self.clock = DeviceClockCheck()
        self._clock_reported = -float("inf")
        self._hello_lock = threading.Lock()
        self._hello: Hello | None = None
        self._hello_gen = 0
        self._publisher: Any = None
        self._pipeline: FramePipeline | None = None
        self._device = cfg.device.name or ""
        self._tare_mtime: tuple[float | None, float | None] | None = None
        self._contact: Any = None  # the tactile ContactTracker, built with the first pipeline
        self._pose_input: Any = None  # [tactile]: the probe-pose subscriber (skinmap.daemon.poses)
        self._tare_problem = ""  # what is wrong with the tare file in use ("" if nothing)
        self._log_state = "off"
        self._last_log_error = ""
        self._processing_error = ""  # the last scan's failure; empty once a scan succeeds
        self._ready_sent = False
        # Data-path liveness for the watchdog (monotonic seconds; None: nothing waiting).
        self._waiting_since: float | None = None
        self._link_alive_mono = time.monotonic()
        self.watchdog_fed = False  # the last check found the data path working
        self._data_path_problem = ""
        self._surface_decimator = HostDecimator(cfg.output.surface_rate_hz)
        self._strains_decimator = HostDecimator(cfg.output.strains_rate_hz)
        self._log_surface_decimator = HostDecimator(cfg.log.surface_rate_hz)
        self._logger = None
        if cfg.log.enabled:
            factory = logger_factory or _default_logger
            self._logger = factory(cfg)
            self._log_state = "recording"
        self.link = ScannerLink(
            cfg.device,
            on_hello=self._on_hello,
            on_scan=self._on_scan,
            on_frame=self._on_frame,
            on_event=self._on_event,
            on_alive=self._on_link_alive,
            opener=opener,
        )
        self.results: collections.deque[FrameResult] = collections.deque(maxlen=4)  # for tests and the console
        self._threads: list[threading.Thread] = []
        self._recent_marks: collections.deque = collections.deque()

    # -- link callbacks (link thread: enqueue only) ----------------------------------------

    def _on_frame(self, frame: Frame, t_rx_ns: int) -> None:
        self._enqueue_log(("raw", t_rx_ns, frame.raw))

    def _on_hello(self, hello: Hello) -> None:
        with self._hello_lock:
            self._hello = hello
            self._hello_gen += 1
            self.clock.reset()

    def _on_link_alive(self) -> None:
        self._link_alive_mono = time.monotonic()

    def _on_scan(self, scan: Scan, frame: Frame, t_rx_ns: int) -> None:
        t_mono = time.monotonic_ns()
        self.stats.scans_in += 1
        self.stats.scan_times.append(t_mono / 1e9)
        problem = self.clock.check(scan.timestamp_us, scan.sample_index, t_mono)
        if problem and t_mono / 1e9 - self._clock_reported > RECENT_WINDOW_S:
            self._clock_reported = t_mono / 1e9  # named once per window; `clock.faults` counts all
            self._on_event("warning", problem)
        if not self._decimator.due(t_mono):
            return
        if self._waiting_since is None:
            self._waiting_since = t_mono / 1e9
        item = (scan, t_rx_ns, t_mono)
        try:
            self._proc_q.put_nowait(item)
        except queue.Full:
            try:
                self._proc_q.get_nowait()
                self.stats.scans_dropped_queue += 1
            except queue.Empty:
                pass
            self._proc_q.put_nowait(item)

    def _on_event(self, level: str, text: str) -> None:
        getattr(log, level if level in ("info", "warning", "error") else "info")(text)
        self._enqueue_log(("event", time.time_ns(), level, text))

    def _enqueue_log(self, item: tuple) -> None:
        if self._logger is None:
            return
        try:
            self._log_q.put_nowait(item)
        except queue.Full:
            self.stats.log_dropped += 1

    # -- processing thread -----------------------------------------------------------------

    def _ensure_pipeline(self) -> FramePipeline | None:
        with self._hello_lock:
            hello, gen = self._hello, self._hello_gen
        if hello is None:
            return None
        if self._pipeline is None or getattr(self, "_pipeline_gen", -1) != gen:
            cal, self._tare_problem = load_calibration(hello, self.cfg)
            pipeline = pipeline_for_hello(hello, self.cfg, cal)
            pipeline.continue_from(self._pipeline)  # keep the warm start across a reconnect
            self._pipeline = pipeline
            self._pipeline_gen = gen
            self._contact = None  # a new baseline after every (re)connect
            self._tare_mtime = self._tare_file_mtime(hello)
            self._open_publisher(hello)
            self._log_config()
        return self._pipeline

    def _log_config(self) -> None:
        # The HELLO goes along so a log file that starts mid-stream (rotation) replays alone.
        if self._logger is not None and self._pipeline is not None and self._hello is not None:
            doc = self._calibration_doc(self._pipeline.calibration)
            doc["hello_frame_hex"] = encode_frame(self._hello, 0).hex()
            self._enqueue_log(("config", time.time_ns(), config_to_toml(self.cfg), doc))

    def _open_publisher(self, hello: Hello) -> None:
        name = device_name(hello, self.cfg)
        if self._session is not None and (self._publisher is None or name != self._device):
            from skinmap.daemon.zenoh_io import SkinmapPublisher

            if self._publisher is not None:
                self._publisher.close()
            self._publisher = SkinmapPublisher(self._session, self.cfg.zenoh.prefix, name)
            if self.cfg.tactile.enabled:
                from skinmap.daemon.poses import subscribe_poses

                if self._pose_input is not None:
                    self._pose_input.undeclare()
                self._pose_input = subscribe_poses(self._session, self.cfg.zenoh.prefix, name, self._enqueue_log)
        self._device = name
        if self._publisher is not None:
            self._publisher.set_info(self.info())

    def info(self) -> dict[str, Any]:
        assert self._hello is not None and self._pipeline is not None
        return device_info(self._device, self._hello, self._pipeline, self.cfg, source="live")

    @staticmethod
    def _calibration_doc(cal: Calibration) -> dict[str, Any]:
        doc = {
            # Full precision: replay must reproduce the live strains bit for bit.
            "gauge_factor": cal.gauge_factor.ravel().tolist(),
            "r0_ohm": cal.base_resistance.ravel().tolist(),
            "shape": list(cal.gauge_factor.shape),
            "source": cal.source,
        }
        if cal.h_upper_mm is not None:
            doc["h_upper_mm"] = cal.h_upper_mm.ravel().tolist()
            doc["h_lower_mm"] = cal.h_lower_mm.ravel().tolist()
        if cal.summary:
            doc["fit"] = dict(cal.summary)
        return doc

    def _process_loop(self) -> None:
        while not self._stop.is_set():
            try:
                scan, t_rx, t_mono = self._proc_q.get(timeout=0.2)
            except queue.Empty:
                continue
            try:
                self._process(scan, t_rx, t_mono)
            except Exception as exc:  # noqa: BLE001 - one bad frame must not stop the service
                self.stats.processing_errors += 1
                text = f"processing failed: {type(exc).__name__}: {exc}"
                if text != self._processing_error:  # a repeated failure is counted, not re-logged
                    log.exception("processing scan %s failed", getattr(scan, "sample_index", "?"))
                    self._enqueue_log(("event", time.time_ns(), "error", text))
                self._processing_error = text

    def _process(self, scan: Scan, t_rx: int, t_mono: int) -> None:
        pipeline = self._ensure_pipeline()
        if pipeline is None or (scan.n, scan.m) != (pipeline.geometry.n, pipeline.geometry.m):
            return
        result = pipeline.process(scan.resistances_ohm(), scan.sample_index, scan.timestamp_us, t_rx)
        self._processing_error = ""
        self.stats.results += 1
        self.stats.last_seq = result.seq
        self.stats.last_solver_ms = result.solve_time_s * 1e3
        self.results.append(result)
        if self._publish(result, t_mono):
            self._waiting_since = None  # the data path has caught up: the watchdog may be fed
        if not self._ready_sent:
            self._ready_sent = True
            self.notifier.ready(f"streaming from {self.cfg.device.port}")

    def _publish(self, r: FrameResult, t_mono: int) -> bool:
        """Publish one result (and queue it for the log); False if publishing failed."""
        elements = messages.encode_elements(
            r.seq & 0xFFFFFFFF, r.device_time_us, r.host_time_ns,
            r.element_positions_mm / 1000.0, r.element_normals, r.element_sigma_mm / 1000.0, r.element_flags)
        want_surface = self._surface_decimator.due(t_mono)
        want_strains = self._strains_decimator.due(t_mono)
        gauge_flags = (r.gauge_valid[0].astype(np.uint8) * messages.GaugeFlag.UPPER_VALID) | (
            r.gauge_valid[1].astype(np.uint8) * messages.GaugeFlag.LOWER_VALID)
        # The same strains message is published (at the strains rate) and logged (every scan).
        strains = messages.encode_strains(
            r.seq & 0xFFFFFFFF, r.device_time_us, r.host_time_ns,
            np.nan_to_num(r.eps_upper), np.nan_to_num(r.eps_lower), gauge_flags)
        pub = self._publisher
        ok = True
        if pub is not None:
            try:
                pub.publish_elements(elements)
                if want_surface:
                    points = self._points(r)
                    pub.publish_surface(messages.encode_surface(
                        r.seq & 0xFFFFFFFF, r.device_time_us, r.host_time_ns, r.nodes_mm / 1000.0, r.normals,
                        r.node_sigma_mm / 1000.0, points / 1000.0))
                if want_strains:
                    pub.publish_strains(strains)
                self.stats.published += 1
            except Exception as exc:  # noqa: BLE001
                self.stats.publish_errors += 1
                ok = False
                log.warning("publish failed: %s", exc)
        t_done = time.time_ns()
        self.stats.latencies_ms.append((t_done - r.host_time_ns) / 1e6)
        self.stats.publish_times.append(time.monotonic())
        # Everything processed is logged (strains of every processed scan, so replay can pick
        # the same scans); surfaces at the surface rate.
        self._enqueue_log(("strains", r.host_time_ns, strains))
        self._enqueue_log(("elements", r.host_time_ns, elements, self.stats.latencies_ms[-1]))
        self._track_contact(r)
        if self._logger is not None and self._log_surface_decimator.due(t_mono):
            cloud = r.surface.points(per_pitch=self.cfg.log.points_per_pitch) if r.surface is not None else r.nodes_mm
            self._enqueue_log(("surface", r.host_time_ns, messages.encode_surface(
                r.seq & 0xFFFFFFFF, r.device_time_us, r.host_time_ns, r.nodes_mm / 1000.0, r.normals,
                r.node_sigma_mm / 1000.0, np.asarray(cloud).reshape(-1, 3) / 1000.0)))
        return ok

    def _track_contact(self, r: FrameResult) -> None:
        """With [tactile] on: the frame against the baseline, published and logged as `contact`."""
        tc = self.cfg.tactile
        if not tc.enabled or r.surface is None or self._pipeline is None:
            return
        from skinmap.daemon.tactile import ContactTracker, SampleGrid

        g = self._pipeline.geometry
        if self._contact is None or self._contact.grid != SampleGrid.for_array(g.n, g.m, g.pitch_mm, tc.step_mm):
            self._contact = ContactTracker(SampleGrid.for_array(g.n, g.m, g.pitch_mm, tc.step_mm),
                                           tc.baseline_frames, tc.k, tc.min_depth_mm)
        pos, nrm = r.surface.locate(self._contact.grid.uv)
        doc = {"seq": int(r.seq), "host_time_ns": int(r.host_time_ns), **self._contact.update(pos, nrm)}
        if self._publisher is not None:
            try:
                self._publisher.publish_contact(doc)
            except Exception as exc:  # noqa: BLE001 - a failed put must not stop processing
                self.stats.publish_errors += 1
                log.warning("publishing contact failed: %s", exc)
        self._enqueue_log(("contact", r.host_time_ns, doc))

    def _points(self, r: FrameResult) -> np.ndarray:
        cache = getattr(r, "_points_cache", None)
        if cache is None:
            if r.surface is None:
                cache = r.nodes_mm.reshape(-1, 3)
            else:
                g = self._pipeline.geometry if self._pipeline is not None else None
                per_pitch = self.cfg.output.points_per_pitch
                if g is not None:
                    per_pitch = max(1, min(per_pitch, int(MAX_CLOUD_POINTS ** 0.5 / max(g.n, g.m))))
                cache = np.asarray(r.surface.points(per_pitch=per_pitch)).reshape(-1, 3)
            r._points_cache = cache  # type: ignore[attr-defined]
        return cache

    # -- log thread ------------------------------------------------------------------------

    def _log_loop(self) -> None:
        from skinmap.daemon.mcaplog import LogStorageError

        lg = self._logger
        last_tick = time.monotonic()
        while True:
            try:
                item = self._log_q.get(timeout=0.5)
            except queue.Empty:
                item = None
                if self._stop.is_set():
                    break
            try:
                if item is not None:
                    self._write_log_item(lg, item)
                if time.monotonic() - last_tick >= 1.0:
                    last_tick = time.monotonic()
                    lg.tick()
                if lg.healthy and self._log_state == "error":
                    self._log_state = "recording"
                    log.info("logging resumed: %s", lg.current_path)
            except LogStorageError as exc:
                if self._log_state != "error":
                    log.error("logging failed, publishing continues: %s", exc)
                self._log_state = "error"
                self._last_log_error = str(exc)
            except Exception as exc:  # noqa: BLE001
                log.warning("log write failed: %s", exc)
        try:
            lg.close()
        except LogStorageError as exc:
            log.error("closing the log failed: %s", exc)

    @staticmethod
    def _write_log_item(lg: Any, item: tuple) -> None:
        kind = item[0]
        if kind == "raw":
            lg.log_raw_frame(item[1], item[2])
        elif kind == "strains":
            lg.log_strains(item[1], item[2])
        elif kind == "elements":
            lg.log_elements(item[1], item[2], item[3])
        elif kind == "surface":
            lg.log_surface(item[1], item[2])
        elif kind == "status":
            lg.log_status(item[1], item[2])
        elif kind == "contact":
            lg.log_contact(item[1], item[2])
        elif kind == "pose":
            lg.log_pose(item[1], item[2])
        elif kind == "event":
            lg.log_event(item[1], item[2], item[3])
        elif kind == "config":
            lg.log_config(item[1], item[2], item[3])

    # -- status ----------------------------------------------------------------------------

    def status(self) -> dict[str, Any]:
        s, ls = self.stats, self.link.stats
        lat = np.array(s.latencies_ms, dtype=np.float64) if s.latencies_ms else np.zeros(1)
        dec = ls.decoder
        lg = self._logger
        return {
            "device": self._device or "unknown",
            "host_time_ns": time.time_ns(),
            "connected": self.link.streaming.is_set(),
            "link_state": ls.state,
            "seq": max(s.last_seq, 0),
            "scan_rate_hz": round(_rate(s.scan_times), 2),
            "publish_rate_hz": round(_rate(s.publish_times), 2),
            "frames_dropped": int(ls.scans_lost + s.scans_dropped_queue),
            "scans_lost": int(ls.scans_lost),
            "scans_dropped_queue": int(s.scans_dropped_queue),
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
            "log_state": self._log_state,
            "log_error": self._last_log_error,
            "log_dropped": int(s.log_dropped),
            # Refused by failing storage or cut with an abandoned file (disk full, read-only).
            "log_lost": int(lg.messages_dropped + lg.messages_lost) if lg is not None else 0,
            "log_file": (lg.current_path or "") if lg is not None else "",
            "log_bytes": int(lg.bytes_written) if lg is not None else 0,
            "publish_errors": int(s.publish_errors),
            "processing_errors": int(s.processing_errors),
            "calibration": self._pipeline.calibration.source if self._pipeline else "",
            "uptime_s": round(time.monotonic() - s.started_mono, 1),
            **self._conditions(),
        }

    def _conditions(self) -> dict[str, Any]:
        """Current abnormal conditions, named, so dashboards and `skinmap inspect` see them."""
        warnings: list[str] = []
        ls = self.link.stats
        if not self.link.streaming.is_set():
            warnings.append(f"scanner not streaming ({ls.state}): {ls.last_error}".rstrip(": "))
        elif ls.state == "stalled":
            warnings.append(f"scanner stalled: {ls.last_error}")
        if self._log_state == "error":
            warnings.append(f"logging failed (publishing continues): {self._last_log_error}")
        if self._processing_error:
            warnings.append(f"{self._processing_error} (nothing published for these scans)")
        if self._tare_problem:
            warnings.append(f"{self._tare_problem} (factory calibration in use)")
        if self.clock.problem and time.monotonic() - self.clock.problem_mono <= RECENT_WINDOW_S:
            warnings.append(f"{self.clock.problem} ({self.clock.faults} clock fault(s) since start; "
                            "output paced by the host clock)")
        if self._data_path_problem:
            warnings.append(f"{self._data_path_problem}; systemd watchdog not fed")
        faults: list[str] = []
        dev = self.link.device_status
        if dev is not None and dev.fault_flags:
            faults = [f.name for f in FaultFlag if f.value and dev.fault_flags & f.value]
            warnings.append("scanner reports " + ", ".join(faults))
        # Damage and loss in the recent past (counters alone never turn a dashboard red).
        now = time.monotonic()
        marks = self._recent_marks
        marks.append((now, ls.frames_rejected, ls.scans_lost, self.stats.scans_dropped_queue))
        while len(marks) > 1 and now - marks[0][0] > RECENT_WINDOW_S:
            marks.popleft()
        _t0, rejected0, lost0, dropped0 = marks[0]
        if ls.frames_rejected > rejected0:
            warnings.append(f"{ls.frames_rejected - rejected0} damaged frame(s) from the scanner in the last "
                            f"{RECENT_WINDOW_S:g} s (last: {ls.last_frame_error})")
        if ls.scans_lost > lost0:
            warnings.append(f"{ls.scans_lost - lost0} scan(s) lost on the link in the last {RECENT_WINDOW_S:g} s")
        if self.stats.scans_dropped_queue > dropped0:
            warnings.append(f"{self.stats.scans_dropped_queue - dropped0} scan(s) skipped by the processing "
                            f"queue in the last {RECENT_WINDOW_S:g} s (reconstruction slower than the output rate)")
        if self.results:
            last = self.results[-1]
            bad = int((~last.gauge_valid).sum())
            if bad:
                warnings.append(f"{bad} gauge(s) unusable in the last scan (open, saturated or implausible)")
            if last.diagnostics.get("inconsistent"):
                warnings.append("strains of the last scan fit no surface well; elements flagged DEGRADED")
        return {"healthy": not warnings, "warnings": warnings, "device_faults": faults}

    def _status_tick(self) -> None:
        st = self.status()
        if self._publisher is not None:
            try:
                self._publisher.publish_status(st)
            except Exception as exc:  # noqa: BLE001
                log.warning("status publish failed: %s", exc)
        self._enqueue_log(("status", st["host_time_ns"], st))
        self.notifier.status(f"{st['link_state']}, {st['publish_rate_hz']:.1f} Hz, seq {st['seq']}")
        if self._console is not None:
            r = self.results[-1] if self.results else None
            self._console(st, shape_summary(r.nodes_mm if r is not None else None,
                                            r.element_positions_mm if r is not None else None))
        self._check_tare()

    def _tare_file_mtime(self, hello: Hello) -> tuple[float | None, float | None] | None:
        """Modification times of the tare and the calibration file (None: neither exists)."""
        from skinmap.daemon.calibration import calibration_path, tare_path

        state = self.cfg.resolve(self.cfg.state.directory)
        times = []
        for path in (tare_path(state, hello.serial_number), calibration_path(state, hello.serial_number)):
            try:
                times.append(path.stat().st_mtime)
            except OSError:
                times.append(None)
        return None if times == [None, None] else (times[0], times[1])

    def _check_tare(self) -> None:
        """A new tare or calibration written by `skinmap tare` / `calibrate` is picked up without a restart."""
        hello, pipeline = self._hello, self._pipeline
        if hello is None or pipeline is None:
            return
        mtime = self._tare_file_mtime(hello)
        if mtime is not None and mtime != self._tare_mtime:
            self._tare_mtime = mtime
            cal, self._tare_problem = load_calibration(hello, self.cfg)
            pipeline.set_calibration(cal)
            log.info("loaded new tare or calibration (%s)", pipeline.calibration.source)
            self._log_config()
            if self._publisher is not None:
                self._publisher.set_info(self.info())

    # -- lifecycle -------------------------------------------------------------------------

    def start(self) -> None:
        limit_blas_threads()  # before the first solve: replay must see the same arithmetic
        prepare_reconstruction_kernels()
        if self._logger is not None:
            t = threading.Thread(target=self._log_loop, name="skinmap-log", daemon=True)
            t.start()
            self._threads.append(t)
        t = threading.Thread(target=self._process_loop, name="skinmap-process", daemon=True)
        t.start()
        self._threads.append(t)
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
                self._check_data_path()
        finally:
            self.shutdown()

    def data_path_problem(self, now: float | None = None) -> str:
        """Why the data path is not working ("" if it is): a scan has waited for processing too
        long with none processed and published since, or the link thread has gone silent."""
        now = time.monotonic() if now is None else now
        timeout = max(DATA_PATH_TIMEOUT_S, self.notifier.watchdog_interval_s)
        since = self._waiting_since
        if since is not None and now - since > timeout:
            why = self._processing_error or (
                f"{self.stats.publish_errors} publish error(s)" if self.stats.publish_errors else "processing blocked")
            return f"no scan processed and published for {now - since:.1f} s ({why})"
        d = self.cfg.device
        # The link loop reports in at least once per reconnect cycle (back-off plus handshake).
        link_timeout = max(timeout, d.reconnect_max_s + 4 * d.handshake_timeout_s + 1.0)
        if now - self._link_alive_mono > link_timeout:
            return f"scanner link thread silent for {now - self._link_alive_mono:.1f} s"
        return ""

    def _check_data_path(self) -> None:
        problem = self.data_path_problem()
        was_problem, self._data_path_problem = self._data_path_problem, problem
        if problem:
            if not was_problem:
                log.error("%s: not feeding the systemd watchdog", problem)
                self._enqueue_log(("event", time.time_ns(), "error", problem))
            self.watchdog_fed = False
            return
        if was_problem:
            log.info("data path working again; feeding the systemd watchdog")
        self.watchdog_fed = True
        self.notifier.watchdog()

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
        for t in self._threads:
            t.join(timeout=10.0)
        if self._publisher is not None:
            try:
                self._publisher.close()
            except Exception:  # noqa: BLE001
                pass
        self.notifier.close()


def _default_logger(cfg: DaemonConfig) -> Any:
    from skinmap.daemon.mcaplog import McapLogger

    lc = cfg.log
    # The folder is created by the logger when it opens a file: a missing or read-only log
    # folder then shows as log_state 'error' in status while publishing goes on.
    directory = cfg.resolve(lc.directory)
    return McapLogger(
        directory,
        basename=lc.basename,
        max_bytes=max(4096, int(lc.max_file_mb * 1024 * 1024)),
        max_seconds=lc.max_file_minutes * 60.0,
        chunk_size=lc.chunk_kb * 1024,
        compression=lc.compression,
        fsync="chunk" if lc.fsync else "none",
        metadata={"skinmap_version": skinmap.__version__, "config_source": cfg.source},
        create_directory=True,
    )


def open_zenoh(cfg: DaemonConfig):
    """A context manager yielding the Zenoh session (or None when Zenoh is disabled)."""
    import contextlib

    if not cfg.zenoh.enabled:
        return contextlib.nullcontext(None)
    from skinmap.daemon.zenoh_io import make_session_config, open_session

    zc = cfg.zenoh
    zconf = make_session_config(
        zc.listen, zc.connect, allow_non_loopback=zc.allow_non_loopback, mode=zc.mode,
        config_file=str(cfg.resolve(zc.config_file)) if zc.config_file else None,
        deny_remote_writes=cfg.guarded_key_expr(),
    )
    # A reply takes its query's congestion control (BLOCK by default), so a client that stops
    # reading holds up replies to it until Zenoh closes its link: after 1 s here instead of
    # Zenoh's 5 s, unless a Zenoh config file sets its own value.
    if json.loads(zconf.get_json(BLOCK_CLOSE_KEY)) == ZENOH_DEFAULT_BLOCK_CLOSE_US:
        zconf.insert_json5(BLOCK_CLOSE_KEY, str(BLOCK_CLOSE_US))
    return open_session(zconf)


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


def device_info(device: str, hello: Hello, pipeline: Any, cfg: DaemonConfig, *,
                source: str) -> dict[str, Any]:
    """The `info` object of a device (skinmap.wire.messages.INFO_FIELDS and more); `source` is
    'live' for a scanner, or names the log being replayed (clients then know the host times
    are the recorded ones)."""
    g = pipeline.geometry
    uv = pipeline.element_uv
    return {
        "device": device,
        "rows": g.n,
        "cols": g.m,
        "pitch_m": g.pitch_mm / 1000.0,
        "h_upper_m": g.h_upper_mm / 1000.0,
        "h_lower_m": g.h_lower_mm / 1000.0,
        "gauge_length_m": g.gauge_length_mm / 1000.0,
        "serial_number": hello.serial_number,
        "elements": {
            "count": int(uv.shape[0]),
            "layout": cfg.elements.layout,
            "width_m": cfg.elements.pitch_u_mm / 1000.0,
            "height_m": cfg.elements.pitch_v_mm / 1000.0,
            "material_uv_m": (uv / 1000.0).tolist(),
            "offset_m": (pipeline.element_offset / 1000.0).tolist(),
        },
        "calibration": Gateway._calibration_doc(pipeline.calibration),
        "versions": {
            "skinmap": skinmap.__version__,
            "protocol": f"{PROTOCOL_MAJOR}.{PROTOCOL_MINOR}",
            "device_protocol": f"{hello.protocol_major}.{hello.protocol_minor}",
            "firmware": ".".join(str(x) for x in hello.fw_version),
        },
        "source": source,
        "frame": "sensor frame: sheet centre at the origin, normal +z, rows along +x (metres)",
    }


def run_gateway(cfg: DaemonConfig, *, console: bool | None = None, stop_event: threading.Event | None = None) -> int:
    """Run skinmapd until SIGINT/SIGTERM (or `stop_event`); returns an exit code."""
    limit_blas_threads()
    # The serial reader waits on select() without the GIL; a shorter switch interval hands it
    # the GIL sooner when bytes arrive while the reconstruction runs Python code.
    sys.setswitchinterval(0.001)
    show = cfg.output.console if console is None else console
    from skinmap.daemon.portlock import PortBusy, PortLock

    port_lock = PortLock(cfg.device.port, "skinmapd")
    try:
        port_lock.acquire()
    except PortBusy as exc:
        log.error("%s", exc)
        return 1
    try:
        return _run_gateway_locked(cfg, show, stop_event)
    finally:
        port_lock.release()


def _run_gateway_locked(cfg: DaemonConfig, show: bool, stop_event: threading.Event | None) -> int:
    panel = StatusConsole() if show else None
    with open_zenoh(cfg) as session:
        gw = Gateway(cfg, zenoh_session=session, console=panel.update if panel else None)
        unwatch = _watch_signals(gw) if threading.current_thread() is threading.main_thread() else (lambda: None)
        if stop_event is not None:
            threading.Thread(target=lambda: (stop_event.wait(), gw.stop()), daemon=True).start()
        log.info("skinmapd %s starting: scanner %s, Zenoh %s, logs %s", skinmap.__version__, cfg.device.port,
                 ",".join(cfg.zenoh.listen + cfg.zenoh.connect) if cfg.zenoh.enabled else "off",
                 cfg.resolve(cfg.log.directory) if cfg.log.enabled else "off")
        try:
            gw.run()
        finally:
            unwatch()
            if panel is not None:
                panel.close()
    log.info("skinmapd stopped")
    return 0


def _watch_signals(gw: Gateway) -> Callable[[], None]:
    """Honour SIGTERM/SIGINT whatever the main thread is doing.

    Python runs signal handlers in the main thread only, between bytecodes; a main thread held
    in a blocking call would never see them. The C-level handler also writes the signal number
    to a pipe, which a thread of our own reads: it stops the gateway and, if the main loop has
    not begun shutting down within STOP_GRACE_S, shuts down itself and exits.
    Returns the function that puts the previous handlers back.
    """
    r, w = os.pipe()
    os.set_blocking(w, False)
    previous = {sig: signal.signal(sig, lambda _signum, _frame: None)  # the work happens in the watcher
                for sig in (signal.SIGTERM, signal.SIGINT)}
    previous_fd = signal.set_wakeup_fd(w, warn_on_full_buffer=False)

    def watch() -> None:
        handled = False
        with os.fdopen(r, "rb", buffering=0) as pipe:
            while data := pipe.read(16):  # empty once unwatched (the write end closed)
                signum = next((s for s in data if s in (signal.SIGTERM, signal.SIGINT)), None)
                if signum is None or handled:
                    continue
                handled = True
                log.info("received %s, stopping", signal.Signals(signum).name)
                gw.stop()
                if gw._shutting_down.wait(STOP_GRACE_S):
                    continue
                log.error("the main loop did not begin stopping within %.0f s of %s; shutting down from the "
                          "signal watcher", STOP_GRACE_S, signal.Signals(signum).name)
                gw.shutdown()
                logging.shutdown()
                os._exit(1)

    threading.Thread(target=watch, name="skinmap-signals", daemon=True).start()

    def unwatch() -> None:
        signal.set_wakeup_fd(previous_fd)
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        os.close(w)

    return unwatch


def setup_logging(verbose: bool = False) -> None:
    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s" if sys.stderr.isatty() or "INVOCATION_ID" not in os.environ
        else "%(levelname)s %(name)s: %(message)s",  # journald adds its own time stamps
        stream=sys.stderr,
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="skinmapd", description="skinmap gateway: scanner → reconstruction → Zenoh + MCAP")
    parser.add_argument("--config", "-c", required=True, help="TOML config file (see config/demo.toml)")
    parser.add_argument("--check", action="store_true", help="validate the config and exit")
    parser.add_argument("--console", action="store_true", help="print a live status line every status period")
    parser.add_argument("--verbose", "-v", action="store_true")
    args = parser.parse_args(argv)
    setup_logging(args.verbose)
    try:
        cfg = load_config(args.config)
    except ConfigError as exc:
        print(f"skinmapd: {exc}", file=sys.stderr)
        return 2
    if args.check:
        from skinmap.daemon.config import check_environment

        found = check_environment(cfg)
        for level, message in found:
            print(f"{args.config}: {level}: {message}", file=sys.stderr if level == "error" else sys.stdout)
        errors = sum(level == "error" for level, _ in found)
        if errors:
            print(f"{args.config}: {errors} problem(s): skinmapd would not run as configured", file=sys.stderr)
            return 2
        print(f"{args.config}: OK (syntax, values, and the files and folders it needs)")
        return 0
    try:
        return run_gateway(cfg, console=True if args.console else None)
    except (ValueError, OSError) as exc:
        print(f"skinmapd: cannot start: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
