"""From a scanner's HELLO to a running pipeline: geometry, calibration (factory, mold fit, tare),
the device's name and its `info` description, and the pick-up of a new tare or calibration
file while running.

`ScannerState` holds the current HELLO (set on the link thread) and the pipeline built for it
(used on the processing thread); the main loop asks it to reload a changed tare.
"""
from __future__ import annotations

import logging
import threading
from typing import Any

import numpy as np

import skinmap
from skinmap.strains import (Calibration, calibration_path, load_calibration_file, load_tare, response_lag_s,
                             tare_path)
from skinmap.daemon.config import DaemonConfig
from skinmap.daemon.pipeline import ArrayGeometry, FramePipeline
from skinmap.protocol import PROTOCOL_MAJOR, PROTOCOL_MINOR, Hello

__all__ = ["geometry_for_hello", "load_calibration", "calibration_for_hello", "pipeline_for_hello",
           "response_lag_for", "device_name", "device_info", "calibration_doc", "ScannerState"]

log = logging.getLogger("skinmapd")


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


def poisson_for(cfg: DaemonConfig, calibration: Calibration) -> tuple[float, float] | None:
    """The film's Poisson ratio and its s.d.: from the config, else from the calibration file
    (`skinmap calibrate --dome R`); None when neither gives it."""
    rc = cfg.reconstruction
    summary = calibration.summary or {}
    if rc.poisson_ratio > 0:
        return rc.poisson_ratio, rc.poisson_ratio_sd
    if summary.get("poisson_ratio") is not None:
        return float(summary["poisson_ratio"]), float(summary.get("poisson_ratio_sd") or rc.poisson_ratio_sd)
    return None


def poisson_range_for(cfg: DaemonConfig, calibration: Calibration) -> tuple[float, float]:
    """The Poisson interval of the stretch pattern's twist (docs/reconstruction.md): ν ± 2 s.d.
    where the config or the calibration gives ν, else any elastomer's 0.3-0.5."""
    known = poisson_for(cfg, calibration)
    if known is None:
        return (0.3, 0.5)
    nu, sd = known
    return (max(0.0, nu - 2.0 * sd), min(0.5, nu + 2.0 * sd))


def elastic_prior_for(cfg: DaemonConfig, calibration: Calibration, cells: int) -> tuple[Any, str]:
    """The elastic prior's settings for this sheet (None when it is off) and what keeps it off
    although configured ("" if nothing): the Poisson ratio comes from the config, else from
    the calibration file."""
    rc = cfg.reconstruction
    if not rc.elastic_prior:
        return None, ""
    from skinmap.reconstruction import ELASTIC_PRIOR_MAX_CELLS
    from skinmap.reconstruction.positionfit import PositionFitSettings

    if cells > ELASTIC_PRIOR_MAX_CELLS:
        return None, f"elastic prior off: it is for sheets of up to {ELASTIC_PRIOR_MAX_CELLS} cells, this one has {cells}"
    known = poisson_for(cfg, calibration)
    if known is None:
        return None, ("elastic prior off: no Poisson ratio (run `skinmap calibrate --dome R` or set "
                      "[reconstruction] poisson_ratio)")
    return PositionFitSettings(poisson=known[0], poisson_sd=known[1]), ""


def pipeline_for_hello(hello: Hello, cfg: DaemonConfig, calibration: Calibration | None = None) -> FramePipeline:
    uv, offsets = cfg.elements.material_coordinates()
    cal = calibration if calibration is not None else calibration_for_hello(hello, cfg)
    elastic, _ = elastic_prior_for(cfg, cal, hello.n * hello.m)
    return FramePipeline(
        geometry_for_hello(hello, cfg),
        cal,
        np.asarray(uv, dtype=np.float64).reshape(-1, 2),
        np.asarray(offsets, dtype=np.float64),
        strain_sigma=cfg.reconstruction.strain_sigma,
        warm_start=cfg.reconstruction.warm_start,
        convex_solver=cfg.reconstruction.convex_solver,
        graph_fit=cfg.reconstruction.graph_fit,
        twist_sign={"positive": 1, "negative": -1}.get(cfg.reconstruction.twist_sign),
        elastic_prior=elastic,
        poisson_range=poisson_range_for(cfg, cal),
        twist_prior=cfg.reconstruction.twist_prior,
        gain_sd=cfg.reconstruction.gain_sd,
        response_lag_s=response_lag_for(cfg),
    )


def response_lag_for(cfg: DaemonConfig) -> float:
    """The gauges' response lag bound (s) the pipeline carries into σ: a third of the configured
    response time, the time constant of a first-order response that reaches 95 % within it."""
    return response_lag_s(cfg.reconstruction.response_time_ms * 1e-3)


def device_name(hello: Hello, cfg: DaemonConfig) -> str:
    if cfg.device.name:
        return cfg.device.name
    safe = "".join(c if c.isalnum() or c in "-_" else "-" for c in hello.serial_number.strip("\0 "))
    return safe or "scanner"


def calibration_doc(cal: Calibration) -> dict[str, Any]:
    """The calibration as logged (`/config`) and served (`info`)."""
    doc: dict[str, Any] = {
        # Full precision: replay must reproduce the live strains bit for bit.
        "gauge_factor": cal.gauge_factor.ravel().tolist(),
        "r0_ohm": cal.base_resistance.ravel().tolist(),
        "shape": list(cal.gauge_factor.shape),
        "source": cal.source,
    }
    if cal.h_upper_mm is not None and cal.h_lower_mm is not None:
        doc["h_upper_mm"] = cal.h_upper_mm.ravel().tolist()
        doc["h_lower_mm"] = cal.h_lower_mm.ravel().tolist()
    if cal.summary:
        doc["fit"] = dict(cal.summary)
    return doc


def device_info(device: str, hello: Hello, pipeline: FramePipeline, cfg: DaemonConfig, *,
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
        "calibration": calibration_doc(pipeline.calibration),
        # what the published σ carries besides the strain noise (docs/reconstruction.md)
        "uncertainty": {
            "strain_sigma": pipeline.strain_sigma,
            "gain_sd": pipeline.gain_sd,
            "response_lag_s": pipeline.response_lag_s,
            "twist_prior": pipeline.twist_prior,
        },
        "versions": {
            "skinmap": skinmap.__version__,
            "protocol": f"{PROTOCOL_MAJOR}.{PROTOCOL_MINOR}",
            "device_protocol": f"{hello.protocol_major}.{hello.protocol_minor}",
            "firmware": ".".join(str(x) for x in hello.fw_version),
        },
        "source": source,
        "frame": "sensor frame: sheet centre at the origin, its best-fit plane z = 0 (+z upper side), rows along +x (metres)",
    }


FileTimes = tuple[float | None, float | None]


class ScannerState:
    """The current scanner (its HELLO) and the pipeline built for it."""

    def __init__(self, cfg: DaemonConfig) -> None:
        self.cfg = cfg
        self._lock = threading.Lock()
        self._hello: Hello | None = None
        self._gen = 0
        self._pipeline_gen = -1
        self.pipeline: FramePipeline | None = None
        self.tare_problem = ""  # what is wrong with the tare file in use ("" if nothing)
        self.elastic_problem = ""  # why a configured elastic prior is off ("" if nothing)
        self.elements_problem = ""  # which configured elements lie off the scanner's sheet ("" if none)
        self._file_times: FileTimes | None = None
        self._prepared: tuple[int, FramePipeline] | None = None  # (HELLO generation, the pipeline it prepared)

    @property
    def hello(self) -> Hello | None:
        return self._hello

    def on_hello(self, hello: Hello) -> None:
        """A handshake (link thread, before the scanner is started): the next scan processed
        builds a new pipeline; a reconstructor for a new geometry is prepared here, so that the
        first scans are not the slow ones (FramePipeline.prepare)."""
        with self._lock:
            self._hello = hello
            self._gen += 1
            gen = self._gen
        try:
            probe = pipeline_for_hello(hello, self.cfg, Calibration(hello.gauge_factor(), hello.base_resistance_ohm(),
                                                                    "factory"))
            probe.continue_from(self.pipeline)
            if probe.prepare():  # False: the running pipeline's reconstructor carries over
                self._prepared = (gen, probe)
        except Exception as exc:  # the first frame does the work instead
            log.warning("preparing the reconstruction failed (%s: %s); the first frames will be slower",
                        type(exc).__name__, exc)

    def ensure_pipeline(self) -> tuple[FramePipeline | None, bool]:
        """The pipeline for the current HELLO (None before one), and whether it is new."""
        with self._lock:
            hello, gen = self._hello, self._gen
        if hello is None:
            return None, False
        if self.pipeline is not None and self._pipeline_gen == gen:
            return self.pipeline, False
        cal, self.tare_problem = load_calibration(hello, self.cfg)
        pipeline = pipeline_for_hello(hello, self.cfg, cal)
        self.elastic_problem = elastic_prior_for(self.cfg, cal, hello.n * hello.m)[1]
        if self.elastic_problem:
            log.warning("%s", self.elastic_problem)
        self.elements_problem = pipeline.elements_problem
        if self.elements_problem:
            log.warning("%s", self.elements_problem)
        pipeline.continue_from(self.pipeline)  # keep the warm start across a reconnect
        prepared, self._prepared = self._prepared, None
        if prepared is not None and prepared[0] == gen:
            pipeline.adopt_prepared(prepared[1])
        self.pipeline, self._pipeline_gen = pipeline, gen
        self._file_times = self._calibration_file_times(hello)
        return pipeline, True

    def reload_if_changed(self) -> bool:
        """Load a tare or calibration written by `skinmap tare` / `calibrate` since the last
        look; True if the pipeline's calibration changed."""
        hello, pipeline = self._hello, self.pipeline
        if hello is None or pipeline is None:
            return False
        times = self._calibration_file_times(hello)
        if times is None or times == self._file_times:
            return False
        self._file_times = times
        cal, self.tare_problem = load_calibration(hello, self.cfg)
        pipeline.set_calibration(cal)
        log.info("loaded new tare or calibration (%s)", pipeline.calibration.source)
        return True

    def _calibration_file_times(self, hello: Hello) -> FileTimes | None:
        """Modification times of the tare and the calibration file (None: neither exists)."""
        state = self.cfg.resolve(self.cfg.state.directory)
        times: list[float | None] = []
        for path in (tare_path(state, hello.serial_number), calibration_path(state, hello.serial_number)):
            try:
                times.append(path.stat().st_mtime)
            except OSError:
                times.append(None)
        return None if times == [None, None] else (times[0], times[1])
