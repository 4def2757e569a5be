"""systemd readiness and watchdog notifications (sd_notify), without libsystemd.

The protocol is one datagram per message to the AF_UNIX socket named by $NOTIFY_SOCKET;
outside systemd the variable is unset and every call is a cheap no-op.
"""
from __future__ import annotations

import os
import socket
import time

__all__ = ["SystemdNotifier"]


class SystemdNotifier:
    def __init__(self, socket_path: str | None = None) -> None:
        path = socket_path if socket_path is not None else os.environ.get("NOTIFY_SOCKET", "")
        self._addr: str | None = None
        self._sock: socket.socket | None = None
        if path:
            # A leading '@' names an abstract-namespace socket.
            self._addr = "\0" + path[1:] if path.startswith("@") else path
            self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        usec = os.environ.get("WATCHDOG_USEC", "")
        # Ping at half the watchdog period, as sd_watchdog_enabled(3) recommends.
        self.watchdog_interval_s = int(usec) / 2e6 if usec.isdigit() and int(usec) > 0 else 0.0
        self._last_watchdog = 0.0

    @property
    def enabled(self) -> bool:
        return self._sock is not None

    def notify(self, message: str) -> None:
        if self._sock is None or self._addr is None:
            return
        try:
            self._sock.sendto(message.encode("utf-8"), self._addr)
        except OSError:
            pass  # systemd gone or socket full: never take the data path down for it

    def ready(self, status: str = "") -> None:
        self.notify("READY=1" + (f"\nSTATUS={status}" if status else ""))

    def status(self, status: str) -> None:
        self.notify(f"STATUS={status}")

    def stopping(self) -> None:
        self.notify("STOPPING=1")

    def watchdog(self) -> None:
        """Feed the watchdog; throttled, so the data path may call it every frame."""
        if self._sock is None:
            return
        now = time.monotonic()
        if now - self._last_watchdog >= max(self.watchdog_interval_s, 0.5):
            self._last_watchdog = now
            self.notify("WATCHDOG=1")

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None
