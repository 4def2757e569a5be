"""Thin byte transports for the emulator: a pseudo-terminal behind a stable symlink, or a TCP
server on the loopback interface (pyserial opens it as ``socket://127.0.0.1:PORT``).

Both are non-blocking: ``read()`` returns what the host sent, ``send()`` queues bytes and
``flush()`` writes what the OS takes; ``tx_ready`` turns false when the host stops reading and
the queue grows, so the device drops scans instead of the emulator blocking.
"""
from __future__ import annotations

import errno
import os
import socket
import termios
import tty
from pathlib import Path

__all__ = ["Transport", "PtyTransport", "TcpTransport", "SharedTcpTransport", "DEFAULT_LINK"]

DEFAULT_LINK = Path("/tmp/skinmap-emulator/ttySKIN0")
TX_HIGH_WATER = 256 * 1024  # queued bytes beyond which the link counts as busy


class Transport:
    """Interface; subclasses own their file descriptors."""

    def __init__(self) -> None:
        self._tx = bytearray()
        self.bytes_out = 0
        self.bytes_in = 0

    # subclasses implement these
    def open(self) -> None: ...
    def close(self) -> None: ...
    def read_fds(self) -> list[int]:
        return []
    def write_fd(self) -> int | None:
        return None
    def on_readable(self, fd: int) -> bytes:
        return b""
    def _write(self, data: memoryview) -> int:
        return len(data)
    @property
    def connected(self) -> bool:
        return False
    def describe(self) -> str:
        return ""

    # shared queue logic
    @property
    def tx_ready(self) -> bool:
        return self.connected and len(self._tx) < TX_HIGH_WATER

    @property
    def tx_pending(self) -> int:
        return len(self._tx)

    def send(self, data: bytes) -> None:
        if data and self.connected:
            self._tx += data
            self.flush()

    def flush(self) -> None:
        while self._tx and self.connected:
            try:
                n = self._write(memoryview(self._tx))
            except BlockingIOError:
                return
            except OSError as exc:
                if exc.errno in (errno.EAGAIN, errno.EWOULDBLOCK):
                    return
                self._lost_peer()
                return
            if n <= 0:
                return
            self.bytes_out += n
            del self._tx[:n]

    def _lost_peer(self) -> None:
        self._tx.clear()

    def __enter__(self):
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class PtyTransport(Transport):
    """A pseudo-terminal in raw mode; ``link`` is a symlink to its slave path, replaced
    atomically whenever a new pty is made (reconnect), removed on close."""

    def __init__(self, link: str | os.PathLike | None = DEFAULT_LINK):
        super().__init__()
        self.link = Path(link) if link is not None else None
        self.master: int | None = None
        self.slave: int | None = None
        self.path: str | None = None

    def open(self) -> None:
        if self.master is not None:
            return
        master, slave = os.openpty()
        tty.setraw(slave)
        # the host's own settings apply once it opens the port; until then no echo, raw bytes
        attrs = termios.tcgetattr(slave)
        attrs[3] &= ~termios.ECHO
        termios.tcsetattr(slave, termios.TCSANOW, attrs)
        os.set_blocking(master, False)
        self.master, self.slave = master, slave
        self.path = os.ttyname(slave)
        if self.link is not None:
            self.link.parent.mkdir(parents=True, exist_ok=True)
            tmp = self.link.with_name(f".{self.link.name}.{os.getpid()}.tmp")
            try:
                tmp.unlink()
            except FileNotFoundError:
                pass
            os.symlink(self.path, tmp)
            os.replace(tmp, self.link)

    def close(self) -> None:
        """The port vanishes: symlink removed (if it still points at us), fds closed."""
        if self.master is None:
            return
        if self.link is not None:
            try:
                if os.readlink(self.link) == self.path:
                    self.link.unlink()
            except OSError:
                pass
        for fd in (self.master, self.slave):
            if fd is None:
                continue
            try:
                os.close(fd)
            except OSError:
                pass
        self.master = self.slave = None
        self._tx.clear()

    @property
    def connected(self) -> bool:
        return self.master is not None

    def read_fds(self) -> list[int]:
        return [self.master] if self.master is not None else []

    def write_fd(self) -> int | None:
        return self.master if self._tx else None

    def on_readable(self, fd: int) -> bytes:
        try:
            data = os.read(fd, 65536)
        except (BlockingIOError, InterruptedError):
            return b""
        except OSError:
            return b""  # EIO while no process holds the slave open; we keep one, so rare
        self.bytes_in += len(data)
        return data

    def _write(self, data: memoryview) -> int:
        if self.master is None:  # flush() writes only while connected; a closed pty is a lost peer
            raise OSError(errno.EBADF, "pseudo-terminal closed")
        return os.write(self.master, data)

    def describe(self) -> str:
        return f"{self.path}" + (f" (link {self.link})" if self.link is not None else "")


class TcpTransport(Transport):
    """A TCP server on 127.0.0.1 with one client at a time (a newer client replaces the older).
    ``port=0`` picks a free port (see ``.port`` after ``open()``)."""

    def __init__(self, port: int = 0, host: str = "127.0.0.1"):
        super().__init__()
        if host not in ("127.0.0.1", "localhost"):
            raise ValueError(f"the emulator serves the loopback interface only, not {host!r}")
        if not 0 <= int(port) <= 65535:
            raise ValueError(f"TCP port must be 0..65535, got {port!r}")
        self.host = "127.0.0.1"
        self.port = int(port)
        self.server: socket.socket | None = None
        self.client: socket.socket | None = None
        self.clients_accepted = 0

    def open(self) -> None:
        if self.server is not None:
            return
        srv = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        srv.bind((self.host, self.port))
        srv.listen(1)
        srv.setblocking(False)
        self.server = srv
        self.port = srv.getsockname()[1]

    def close(self) -> None:
        self._drop_client()
        if self.server is not None:
            self.server.close()
            self.server = None

    def _drop_client(self) -> None:
        if self.client is not None:
            try:
                self.client.close()
            except OSError:
                pass
            self.client = None
        self._tx.clear()

    def _lost_peer(self) -> None:
        self._drop_client()

    @property
    def connected(self) -> bool:
        return self.client is not None

    def read_fds(self) -> list[int]:
        fds = [self.server.fileno()] if self.server is not None else []
        if self.client is not None:
            fds.append(self.client.fileno())
        return fds

    def write_fd(self) -> int | None:
        return self.client.fileno() if self.client is not None and self._tx else None

    def accept(self) -> bool:
        """Accept a waiting client; True when a new client is connected."""
        if self.server is None:  # closed
            return False
        try:
            conn, _ = self.server.accept()
        except (BlockingIOError, InterruptedError):
            return False
        self._drop_client()
        conn.setblocking(False)
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.client = conn
        self.clients_accepted += 1
        return True

    def on_readable(self, fd: int) -> bytes:
        if self.client is None or fd != self.client.fileno():
            return b""
        try:
            data = self.client.recv(65536)
        except (BlockingIOError, InterruptedError):
            return b""
        except OSError:
            data = b""
        if not data:
            self._drop_client()  # the host hung up
            return b""
        self.bytes_in += len(data)
        return data

    def _write(self, data: memoryview) -> int:
        if self.client is None:
            raise OSError(errno.ENOTCONN, "no host connected")
        return self.client.send(data)

    @property
    def url(self) -> str:
        return f"socket://{self.host}:{self.port}"

    def describe(self) -> str:
        return self.url


class SharedTcpTransport(TcpTransport):
    """Like :class:`TcpTransport`, but as a serial-to-network bridge that allows several
    connections: every client's bytes reach the device and the device's bytes go to every
    client, so two hosts on one scanner see each other's answers. Clients joining or leaving do
    not power-cycle the scanner; it is on while at least one is connected."""

    shared = True

    def __init__(self, port: int = 0, host: str = "127.0.0.1"):
        super().__init__(port, host)
        self.clients: list[socket.socket] = []
        self._queues: dict[int, bytearray] = {}

    def _drop_client(self) -> None:
        for c in self.clients:
            try:
                c.close()
            except OSError:
                pass
        self.clients.clear()
        self._queues.clear()
        self.client = None

    def _remove(self, conn: socket.socket) -> None:
        self._queues.pop(conn.fileno(), None)
        self.clients.remove(conn)
        conn.close()
        self.client = self.clients[0] if self.clients else None

    @property
    def connected(self) -> bool:
        return bool(self.clients)

    @property
    def tx_ready(self) -> bool:
        return any(len(q) < TX_HIGH_WATER for q in self._queues.values())

    @property
    def tx_pending(self) -> int:
        return sum(len(q) for q in self._queues.values())

    def read_fds(self) -> list[int]:
        fds = [self.server.fileno()] if self.server is not None else []
        return fds + [c.fileno() for c in self.clients]

    def write_fd(self) -> int | None:
        for c in self.clients:
            if self._queues.get(c.fileno()):
                return c.fileno()
        return None

    def accept(self) -> bool:
        if self.server is None:  # closed
            return False
        try:
            conn, _ = self.server.accept()
        except (BlockingIOError, InterruptedError):
            return False
        conn.setblocking(False)
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.clients.append(conn)
        self._queues[conn.fileno()] = bytearray()
        self.client = self.clients[0]
        self.clients_accepted += 1
        return True

    def on_readable(self, fd: int) -> bytes:
        conn = next((c for c in self.clients if c.fileno() == fd), None)
        if conn is None:
            return b""
        try:
            data = conn.recv(65536)
        except (BlockingIOError, InterruptedError):
            return b""
        except OSError:
            data = b""
        if not data:
            self._remove(conn)
            return b""
        self.bytes_in += len(data)
        return data

    def send(self, data: bytes) -> None:
        if not data:
            return
        for q in self._queues.values():
            if len(q) < 4 * TX_HIGH_WATER:  # a client that reads nothing loses its bytes, not the others'
                q += data
        self.flush()

    def flush(self) -> None:
        for conn in list(self.clients):
            q = self._queues.get(conn.fileno())
            while q:
                try:
                    n = conn.send(q)
                except (BlockingIOError, InterruptedError):
                    break
                except OSError:
                    self._remove(conn)
                    break
                if n <= 0:
                    break
                self.bytes_out += n
                del q[:n]
