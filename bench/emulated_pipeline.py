"""The emulated device's scans through skinmapd's frame pipeline, in process: the one loop the
pipeline benches (pipeline_accuracy.py, latency.py --accuracy) and tests/test_pipeline_accuracy.py
share.

The device is the emulator's (`skinmap.emulator.device.Device`: its electrical model, noise
seed and calibration); every unit is read at one instant a scan, so that a moving shape has one
truth a frame.  The pipeline takes the device's HELLO calibration and runs its background work
(restart, catch-up and audit chains) inline, so a run is the same on every machine.
"""
from __future__ import annotations

from typing import Any, Iterator

import numpy as np

from skinmap.daemon.pipeline import ArrayGeometry, FramePipeline, InlineBackground
from skinmap.emulator import physics as ph
from skinmap.emulator.device import Device, ScannerSpec
from skinmap.emulator.electrical import ElectricalConfig
from skinmap.strains import Calibration

__all__ = ["SCAN_RATE", "emulated_device", "emulated_pipeline", "emulated_scans"]

SCAN_RATE = 50.0


def emulated_device(n: int, shape: ph.Shape | str, electrical: ElectricalConfig | None = None, seed: int = 0,
                    m: int | None = None, scan_rate: float = SCAN_RATE, gf_spread: float = 0.0) -> tuple[Device, ScannerSpec]:
    """The emulated scanner over ``shape`` (a Shape or a shape spec): n × m (m = n by default);
    ``gf_spread``: the relative s.d. of its true gauge factors about HELLO's (0: HELLO's are true)."""
    spec = ScannerSpec(n=n, m=n if m is None else m, scan_rate_hz=scan_rate,
                       electrical=ElectricalConfig() if electrical is None else electrical, seed=seed,
                       gf_spread=gf_spread)
    return Device(spec, ph.parse_shape_spec(shape) if isinstance(shape, str) else shape), spec


def emulated_pipeline(device: Device, spec: ScannerSpec, elements_uv: np.ndarray | None = None,
                      **options: Any) -> FramePipeline:
    """A FramePipeline as skinmapd builds it from the device's HELLO (gauge factors and base
    resistances), its background inline unless ``options`` give one; ``elements_uv`` (K, 2) mm,
    none by default (one element at the centre); ``options`` go to FramePipeline."""
    hello = device.hello()
    calibration = Calibration(hello.gauge_factor(), hello.base_resistance_ohm(), "factory")
    geometry = ArrayGeometry(spec.n, spec.m, spec.pitch_mm, spec.h_upper_mm, spec.h_lower_mm, spec.gauge_length_mm)
    uv = np.zeros((1, 2)) if elements_uv is None else np.asarray(elements_uv, dtype=float)
    options.setdefault("background", InlineBackground())
    return FramePipeline(geometry, calibration, uv, np.zeros(len(uv)), **options)


def emulated_scans(device: Device, spec: ScannerSpec, last_s: float, first_s: float = 0.0, every: int = 1,
                   ramp_s: float = 0.0, lead: int = 0) -> Iterator[tuple[int, float, np.ndarray]]:
    """(sample index k, time s, resistances Ω (4, N, M)) of every ``every``-th scan and the
    ``lead`` scans before each (skinmapd's lead scans, `[output] lead_scans`: k % every ≠ 0) from
    ``first_s`` to ``last_s`` (index k counted from t = 0; the scans between them are read too,
    so that the electrical model's state is that of a device scanning throughout).  With
    ``ramp_s``, the shape is pressed from flat over that long (its strains scaled up from none,
    so the gauges' hysteresis reads its loading branch) and then held."""
    rate = spec.scan_rate_hz
    times = np.zeros((2, spec.n, spec.m))  # every unit read at the scan's instant
    for k in range(int(first_s * rate), int(last_s * rate)):
        t = k / rate
        times.fill(t)
        strains = device.strains(times)
        if ramp_s > 0.0:
            strains = min(t / ramp_s, 1.0) * strains
        wire = device.readout.read(strains, t)
        if k % every and k % every < every - lead:
            continue
        yield k, t, np.asarray(wire, dtype=float) * 1e-6
