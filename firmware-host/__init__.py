"""skinmap.emulator: the scanner-firmware emulator and the physics forward model.

- :mod:`~skinmap.emulator.physics` — shapes and the Kirchhoff–Love gauge forward model (pure numpy)
- :mod:`~skinmap.emulator.mechanics` — the film as an elastic sheet: energy and equilibrium solver
- :mod:`~skinmap.emulator.scenes` — every shape kind's elastic form (molds, membranes, balloon, palm)
- :mod:`~skinmap.emulator.electrical` — calibration, hysteresis, drift, noise, ADC (pure numpy)
- :mod:`~skinmap.emulator.device` — the firmware as a pure state machine (bytes and time in, bytes out)
- :mod:`~skinmap.emulator.linkfaults` — byte-level link faults
- :mod:`~skinmap.emulator.transport`, :mod:`~skinmap.emulator.emulator` — pty / TCP edges and the loop
- :mod:`~skinmap.emulator.command` — the ``skinmap-emulator`` command

See firmware-host/README.md.
"""
from __future__ import annotations

from skinmap.emulator.device import Device, ScannerSpec, ScanRecord
from skinmap.emulator.electrical import GaugeConstants, ElectricalConfig
from skinmap.emulator.emulator import Emulator, FaultSchedule
from skinmap.emulator.linkfaults import LinkFaults
from skinmap.emulator.physics import (
    GroundTruth,
    Shape,
    cell_centres,
    gauge_strains,
    ground_truth,
    make_shape,
    parse_shape_spec,
)
from skinmap.emulator.scenes import make_scene, parse_scene_spec
from skinmap.emulator.transport import PtyTransport, TcpTransport

__all__ = [
    "GaugeConstants", "Device", "ScannerSpec", "ElectricalConfig", "Emulator", "FaultSchedule",
    "GroundTruth", "LinkFaults", "PtyTransport", "ScanRecord", "Shape", "TcpTransport",
    "cell_centres", "gauge_strains", "ground_truth", "make_scene", "make_shape", "parse_scene_spec",
    "parse_shape_spec",
]
