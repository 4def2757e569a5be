"""The scanner over pyserial: a device path (/dev/serial/by-id/..., a udev symlink, a pty) or a
pyserial URL (``socket://127.0.0.1:PORT`` for the emulator's TCP server)."""
from __future__ import annotations

import select
import time
from typing import Any

import serial

from skinmap.ports.base import RECV_CHUNK, PortOpenError, PortVanished, PortWriteTimeout, ScannerPort

__all__ = ["SerialScannerPort"]

# Ports without a file descriptor to wait on (pyserial's loop:// and similar) are polled this often.
_POLL_S = 0.005


class SerialScannerPort(ScannerPort):
    """Opens at construction; ``exclusive`` locks a real tty against other openers (flock, as
    pyserial does it; URLs have no such lock)."""

    def __init__(self, url: str, baudrate: int = 115200, *, exclusive: bool = True,
                 write_timeout_s: float = 1.0) -> None:
        super().__init__(url)
        # Non-blocking reads: recv waits with select() itself, then takes everything available
        # at once (a blocking read(n) would sit out its timeout, and `in_waiting` of socket://
        # ports only says 0 or 1).
        kwargs: dict[str, Any] = {"baudrate": baudrate, "timeout": 0, "write_timeout": write_timeout_s}
        if exclusive and "://" not in url:
            kwargs["exclusive"] = True
        try:
            self._serial = serial.serial_for_url(url, **kwargs)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise PortOpenError(str(exc)) from exc
        fileno = getattr(self._serial, "fileno", None)
        try:
            self._fd: int | None = fileno() if fileno is not None else None
        except (OSError, AttributeError, NotImplementedError):
            self._fd = None

    def _send_internal(self, data: bytes) -> None:
        try:
            self._serial.write(data)
        except serial.SerialTimeoutException as exc:
            raise PortWriteTimeout(f"{self.name}: {exc}") from exc
        except (serial.SerialException, OSError) as exc:
            raise PortVanished(str(exc)) from exc

    def _recv_internal(self, timeout: float | None) -> bytes:
        try:
            if self._fd is None:
                data = self._serial.read(max(1, min(self._serial.in_waiting, RECV_CHUNK)))
                if not data and timeout != 0:
                    time.sleep(_POLL_S if timeout is None else min(_POLL_S, timeout))
                return bytes(data)
            readable, _, _ = select.select([self._fd], [], [], timeout)
            # pyserial raises SerialException when a readable port yields nothing: the device
            # is gone (or another reader took the bytes; docs/reliability.md).
            return bytes(self._serial.read(RECV_CHUNK)) if readable else b""
        except (serial.SerialException, OSError, ValueError) as exc:  # ValueError: select on a dead fd
            raise PortVanished(str(exc)) from exc

    def _reset_input_internal(self) -> None:
        try:
            self._serial.reset_input_buffer()
        except (serial.SerialException, OSError) as exc:
            raise PortVanished(str(exc)) from exc

    def _close_internal(self) -> None:
        try:
            self._serial.close()
        except Exception:  # noqa: BLE001 - closing a vanished port may fail in many ways; it is gone either way
            pass
