"""The scanner port: a byte stream to and from one scanner, behind one small interface.

Modelled on python-can's ``BusABC``: the public methods check the port's state and the
arguments once, then call the implementation's ``_send_internal`` / ``_recv_internal`` /
``_close_internal``. Every failure is a :class:`PortError`, and its kind says what happened:

- :class:`PortOpenError`: the port could not be opened (no such device, held by another process);
- :class:`PortVanished`: the device went away under an open port (unplugged, peer hung up);
- :class:`PortWriteTimeout`: the device did not take the bytes in time (it is there, but stuck);
- :class:`PortClosed`: this side closed the port, and it was used afterwards.

A receive timeout is no error: ``recv`` returns ``b""``. So a silent device and a vanished one
are told apart by the caller without looking at error texts.
"""
from __future__ import annotations

import math
import time
from abc import ABC, abstractmethod
from typing import Callable

__all__ = ["PortError", "PortOpenError", "PortVanished", "PortWriteTimeout", "PortClosed", "ScannerPort",
           "PortFactory", "RECV_CHUNK"]

#: The most bytes one ``recv`` returns (a 32×32 scan is 16 kB).
RECV_CHUNK = 65536


class PortError(OSError):
    """A scanner port failed (an OSError, as the serial and socket errors it stands for)."""


class PortOpenError(PortError):
    """The port could not be opened."""


class PortVanished(PortError):
    """The device went away under an open port."""


class PortWriteTimeout(PortError):
    """The device did not take the bytes within the port's write timeout."""


class PortClosed(PortError):
    """The port was used after it was closed by this side."""


class ScannerPort(ABC):
    """One open connection to a scanner. Use as a context manager, or call :meth:`close`.

    Subclasses implement ``_send_internal(data)`` (write all of ``data`` or raise),
    ``_recv_internal(timeout)`` (wait at most ``timeout`` seconds, ``None``: without limit, for
    bytes; return what is there, ``b""`` if nothing came) and ``_close_internal()`` (release the
    device; must not raise). They raise only :class:`PortError` subclasses.
    """

    def __init__(self, name: str) -> None:
        self.name = name
        self._closed = False

    @property
    def closed(self) -> bool:
        return self._closed

    def _check_open(self) -> None:
        if self._closed:
            raise PortClosed(f"port {self.name} is closed")

    def send(self, data: bytes) -> None:
        """Write every byte of ``data`` (PortVanished, PortWriteTimeout, PortClosed)."""
        self._check_open()
        if data:
            self._send_internal(bytes(data))

    def recv(self, timeout: float | None = None) -> bytes:
        """The bytes received, at most :data:`RECV_CHUNK`, waiting up to ``timeout`` seconds
        (0: do not wait; None: until some arrive). ``b""`` when the time ran out; PortVanished
        when the device is gone, PortClosed after :meth:`close`."""
        self._check_open()
        if timeout is not None and not (math.isfinite(timeout) and timeout >= 0):
            raise ValueError(f"recv timeout must be a finite number >= 0 s or None, got {timeout!r}")
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            left = None if deadline is None else max(0.0, deadline - time.monotonic())
            data = self._recv_internal(left)
            # An implementation may return early with nothing (a spurious wake-up): wait on
            # until the caller's timeout is used up.
            if data or (deadline is not None and time.monotonic() >= deadline):
                return data
            self._check_open()

    def reset_input(self) -> None:
        """Discard whatever was received and not read yet (stale bytes of an earlier session)."""
        self._check_open()
        self._reset_input_internal()

    def close(self) -> None:
        """Release the device; closing again, or closing a vanished port, does nothing."""
        if not self._closed:
            self._closed = True
            self._close_internal()

    def __enter__(self) -> "ScannerPort":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.name}{' closed' if self._closed else ''}>"

    @abstractmethod
    def _send_internal(self, data: bytes) -> None: ...

    @abstractmethod
    def _recv_internal(self, timeout: float | None) -> bytes: ...

    @abstractmethod
    def _reset_input_internal(self) -> None: ...

    @abstractmethod
    def _close_internal(self) -> None: ...


#: What the scanner link calls to (re)open its port: a new open ScannerPort, or PortOpenError.
PortFactory = Callable[[], ScannerPort]
