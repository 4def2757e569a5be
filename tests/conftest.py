"""Shared test helpers: free loopback ports and a gateway running in a background thread."""
from __future__ import annotations

import contextlib
import socket
import threading
from typing import Any, Iterator


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextlib.contextmanager
def running_gateway(cfg: Any, **gateway_kwargs: Any) -> Iterator[Any]:
    """Open the config's Zenoh session, run a Gateway in a thread, stop and join it on exit."""
    from skinmap.daemon.service import Gateway, open_zenoh

    with open_zenoh(cfg) as session:
        gw = Gateway(cfg, zenoh_session=session, **gateway_kwargs)
        runner = threading.Thread(target=gw.run, daemon=True, name="test-gateway")
        runner.start()
        try:
            yield gw
        finally:
            gw.stop()
            runner.join(timeout=20)


class CheckedFile:
    """A raw file for McapLogger's `open_file` whose writes first pass `check(n_bytes)`, which
    may raise OSError: tests make storage fail on demand (disk full, read-only)."""

    def __init__(self, path: str, check: Any) -> None:
        self.raw = open(path, "xb", buffering=0)
        self.check = check

    def write(self, data: Any) -> int:
        self.check(len(data))
        return self.raw.write(data)

    def flush(self) -> None:
        self.raw.flush()

    def fileno(self) -> int:
        return self.raw.fileno()

    def close(self) -> None:
        self.raw.close()


def aligned_error(nodes, truth) -> float:
    """Mean node error after the best rigid alignment (Kabsch)."""
    import numpy as np

    p, q = np.asarray(nodes).reshape(-1, 3), np.asarray(truth).reshape(-1, 3)
    pc, qc = p.mean(0), q.mean(0)
    u, _, vt = np.linalg.svd((p - pc).T @ (q - qc))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    r = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return float(np.linalg.norm((p - pc) @ r.T + qc - q, axis=1).mean())
