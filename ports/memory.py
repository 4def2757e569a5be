"""Two connected in-memory scanner ports, for tests and in-process wiring: what one end sends,
the other receives. Closing one end makes the other's port vanish (after it has read what was
already sent), as when the far end of a cable is unplugged."""
from __future__ import annotations

import threading

from skinmap.ports.base import RECV_CHUNK, PortClosed, PortVanished, ScannerPort

__all__ = ["MemoryPort", "memory_pair"]


class _Line:
    """Both directions of one pair and the condition both ends wait on."""

    def __init__(self) -> None:
        self.cond = threading.Condition()
        self.inbox = (bytearray(), bytearray())  # inbox[i]: bytes waiting for end i
        self.closed = [False, False]


class MemoryPort(ScannerPort):
    """One end of :func:`memory_pair`; thread-safe."""

    def __init__(self, line: _Line, side: int, name: str) -> None:
        super().__init__(name)
        self._line, self._side = line, side

    @property
    def in_waiting(self) -> int:
        """Bytes received and not read yet."""
        with self._line.cond:
            return len(self._line.inbox[self._side])

    def _gone(self) -> str:
        line = self._line
        if line.closed[1 - self._side]:
            return f"port {self.name} vanished: the other end closed"
        return ""

    def _send_internal(self, data: bytes) -> None:
        line = self._line
        with line.cond:
            gone = self._gone()
            if gone:
                raise PortVanished(gone)
            line.inbox[1 - self._side].extend(data)
            line.cond.notify_all()

    def _recv_internal(self, timeout: float | None) -> bytes:
        line = self._line
        box = line.inbox[self._side]
        with line.cond:
            line.cond.wait_for(lambda: bool(box) or bool(self._gone()) or line.closed[self._side], timeout)
            if line.closed[self._side]:
                raise PortClosed(f"port {self.name} was closed while receiving")
            if box:  # what the other end sent before it went away is still delivered
                data = bytes(box[:RECV_CHUNK])
                del box[:RECV_CHUNK]
                return data
            gone = self._gone()
            if gone:
                raise PortVanished(gone)
            return b""

    def _reset_input_internal(self) -> None:
        with self._line.cond:
            self._line.inbox[self._side].clear()

    def _close_internal(self) -> None:
        with self._line.cond:
            self._line.closed[self._side] = True
            self._line.cond.notify_all()


def memory_pair(name: str = "memory") -> tuple[MemoryPort, MemoryPort]:
    """(host end, far end) of a new line; their names are ``name`` + ``:0`` / ``:1``."""
    line = _Line()
    return MemoryPort(line, 0, f"{name}:0"), MemoryPort(line, 1, f"{name}:1")
