"""One owner per scanner: an advisory lock named after the scanner's port.

skinmapd holds it while it runs; `skinmap tare` and `skinmap calibrate` take it before they open
the port, so a tool never fights the daemon for the scanner (a socket:// emulator or a tty opened
without exclusive access would otherwise be shared, each side reconnecting in turn).  The lock is
an flock on a small file in $XDG_RUNTIME_DIR (else the temp directory) that records the holder's
pid and name; the kernel drops it when the holder exits, however it exits.  A lock file another
user left behind (read-only to this one) still locks: it is opened for reading, and the holder's
name is then not recorded.
"""
from __future__ import annotations

import fcntl
import os
import tempfile
from pathlib import Path

__all__ = ["PortBusy", "PortLock", "lock_path"]


class PortBusy(RuntimeError):
    """Another process holds the scanner."""


def lock_path(port: str) -> Path:
    base = Path(os.environ.get("XDG_RUNTIME_DIR") or tempfile.gettempdir())
    safe = "".join(c if c.isalnum() or c in "-_." else "_" for c in port)[-120:] or "port"
    return base / f"skinmap-port-{safe}.lock"


class PortLock:
    """``with PortLock(port, "skinmapd"):`` or ``acquire()`` / ``release()``; PortBusy names the
    holder."""

    def __init__(self, port: str, holder: str) -> None:
        self.port, self.holder = port, holder
        self.path = lock_path(port)
        self._fd: int | None = None
        self._writable = False

    def acquire(self) -> "PortLock":
        cloexec = getattr(os, "O_CLOEXEC", 0)
        try:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT | cloexec, 0o644)
            writable = True
        except PermissionError:
            # the file another user left (a tool run as root, the service's former dynamic
            # user): it stays, as lock files do, and flock needs no write access to it
            fd = os.open(self.path, os.O_RDONLY | cloexec)
            writable = False
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            try:
                who = os.pread(fd, 200, 0).decode("utf-8", "replace").strip() or "another process"
            finally:
                os.close(fd)
            raise PortBusy(f"the scanner at {self.port} is in use by {who} (lock {self.path}); "
                           f"stop it first (e.g. systemctl stop skinmapd)") from None
        if writable:
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{self.holder} (pid {os.getpid()})\n".encode(), 0)
        self._fd, self._writable = fd, writable
        return self

    def release(self) -> None:
        if self._fd is not None:
            try:
                if self._writable:
                    os.ftruncate(self._fd, 0)
            finally:
                os.close(self._fd)  # closing drops the flock
                self._fd = None

    def __enter__(self) -> "PortLock":
        return self.acquire()

    def __exit__(self, *exc: object) -> None:
        self.release()
