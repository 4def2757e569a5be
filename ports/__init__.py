"""skinmap.ports: the byte edge to the scanner behind one interface, :class:`ScannerPort`.

- :class:`SerialScannerPort`: a real scanner (or a pty / ``socket://`` emulator) over pyserial;
- :func:`memory_pair`: two connected in-memory ports, for tests;
- the emulator's device on an in-process line: :class:`skinmap.emulator.loopback.DeviceLoopback`.

The scanner link (:class:`skinmap.daemon.link.ScannerLink`) takes a :data:`PortFactory` and
tells the failures apart by their class (docs/architecture.md, "Scanner ports").
"""
from __future__ import annotations

from skinmap.ports.base import (RECV_CHUNK, PortClosed, PortError, PortFactory, PortOpenError, PortVanished,
                                PortWriteTimeout, ScannerPort)
from skinmap.ports.memory import MemoryPort, memory_pair
from skinmap.ports.serialport import SerialScannerPort

__all__ = ["RECV_CHUNK", "PortClosed", "PortError", "PortFactory", "PortOpenError", "PortVanished",
           "PortWriteTimeout", "ScannerPort", "MemoryPort", "memory_pair", "SerialScannerPort"]
