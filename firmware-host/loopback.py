"""The emulator's device on an in-process line: a null-modem whose far end is the firmware
state machine (:class:`~skinmap.emulator.device.Device`), run in the caller's thread.

    loop = DeviceLoopback(Device(ScannerSpec(n=5, m=5), make_shape("flat")))
    link = ScannerLink(cfg, ..., port_factory=loop.open)

No pseudo-terminal, no socket: the host's ``send`` feeds the device at once and ``recv`` runs
the device up to the moment it returns, waiting for its next scan on the real clock. The line
can be unplugged and plugged in again (the scanner is powered by its link, so it boots afresh),
rebooted, and given a model of what the line does to the device's bytes (e.g.
``FaultyLink(...).apply``). Tests touching the device while a host reads hold :attr:`lock`.
"""
from __future__ import annotations

import threading
import time
from typing import Callable

from skinmap.emulator.device import Device
from skinmap.emulator.transport import TX_HIGH_WATER  # beyond it the device drops scans whole
from skinmap.ports import RECV_CHUNK, PortClosed, PortOpenError, PortVanished, ScannerPort

__all__ = ["DeviceLoopback", "LoopbackPort"]

# The longest a waiting recv sleeps before it looks at the device again: a test may change the
# device (a HELLO storm, a stall) without waking the line.
_MAX_SLEEP_S = 0.02


class LoopbackPort(ScannerPort):
    """The host end of a :class:`DeviceLoopback` (made by :meth:`DeviceLoopback.open`)."""

    def __init__(self, loop: "DeviceLoopback", name: str) -> None:
        super().__init__(name)
        self._loop = loop
        self._rx = bytearray()
        self.vanished = False

    def _deliver(self, data: bytes, now: float) -> None:
        line = self._loop.line
        if data and line is not None:
            data = line(data, now)
        if data:
            self._rx.extend(data)
            self._loop.cond.notify_all()

    def _check_line(self) -> None:
        if self.vanished:
            raise PortVanished(f"port {self.name} vanished: the scanner was unplugged")

    def _send_internal(self, data: bytes) -> None:
        loop = self._loop
        with loop.cond:
            self._check_line()
            now = loop.clock()
            self._deliver(loop.device.on_bytes(data, now), now)

    def _recv_internal(self, timeout: float | None) -> bytes:
        loop = self._loop
        deadline = None if timeout is None else loop.clock() + timeout
        with loop.cond:
            while True:
                self._check_line()
                if self.closed:
                    raise PortClosed(f"port {self.name} was closed while receiving")
                now = loop.clock()
                self._deliver(loop.device.poll(now, tx_ready=len(self._rx) < TX_HIGH_WATER), now)
                if self._rx:
                    data = bytes(self._rx[:RECV_CHUNK])
                    del self._rx[:RECV_CHUNK]
                    return data
                if deadline is not None and now >= deadline:
                    return b""
                wake = min(loop.device.next_event_s(), now + _MAX_SLEEP_S)
                if deadline is not None:
                    wake = min(wake, deadline)
                loop.cond.wait(max(wake - now, 0.001))

    def _reset_input_internal(self) -> None:
        with self._loop.cond:
            self._rx.clear()

    def _close_internal(self) -> None:
        with self._loop.cond:
            self._rx.clear()
            self._loop.cond.notify_all()


class DeviceLoopback:
    """One emulated scanner and the line to it; :meth:`open` is a port factory.

    ``line(data, now_s) -> data`` is applied to every chunk the device sends (None: a perfect
    line). One host at a time holds the port, as with an exclusively opened tty.
    """

    def __init__(self, device: Device, *, name: str = "loop://skinmap-emulator",
                 line: Callable[[bytes, float], bytes] | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.device = device
        self.name = name
        self.line = line
        self.clock = clock
        self.lock = threading.RLock()
        self.cond = threading.Condition(self.lock)
        self.plugged = True
        self.opens = 0
        self.ports: list[LoopbackPort] = []  # every port opened, the current one last

    def open(self) -> LoopbackPort:
        """A new host end (PortOpenError while unplugged or while another is open)."""
        with self.lock:
            if not self.plugged:
                raise PortOpenError(f"could not open port {self.name}: no scanner on the line (unplugged)")
            if self.ports and not (self.ports[-1].closed or self.ports[-1].vanished):
                raise PortOpenError(f"could not open port {self.name}: already open (one host at a time)")
            self.opens += 1
            port = LoopbackPort(self, self.name)
            self.ports.append(port)
            return port

    def unplug(self) -> None:
        """The port vanishes under its host; opening fails until :meth:`replug`."""
        with self.cond:
            self.plugged = False
            for port in self.ports:
                port.vanished = True
            self.cond.notify_all()

    def replug(self, power_cycle: bool = True) -> None:
        """The scanner is back on the line; it boots afresh unless ``power_cycle`` is False
        (the line glitched, the scanner kept its power)."""
        with self.cond:
            if power_cycle:
                self.device.reboot(self.clock(), watchdog=False)
            self.plugged = True

    def reboot(self) -> None:
        """The firmware restarts (watchdog): HELLO with seq 0, sample index from 0, IDLE."""
        with self.cond:
            self.device.reboot(self.clock(), watchdog=True)
            self.cond.notify_all()
