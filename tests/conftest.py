"""Shared test helpers: free loopback ports, waiting on conditions, receiving in order, a
gateway running in a background thread, storage that fails on demand, rigid alignment.

Waits are on conditions with generous time-outs (they end as soon as the condition holds, so
only a failing test waits them out): a loaded machine makes things slower, not wrong.
"""
from __future__ import annotations

import contextlib
from pathlib import Path
import socket
import threading
import time
from typing import Any, Callable, Iterator

WAIT_S = 30.0  # default time-out of a wait: long enough for a loaded 2-core machine


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def tactile_gateway_config(folder: Path, device_url: str, name: str, zenoh_port: int) -> Any:
    """A loaded gateway config for a tactile run in ``folder``: the emulated device at
    ``device_url`` scanned at 20 Hz, output at 10 Hz, Zenoh listening on loopback
    ``zenoh_port``, contacts tracked (a baseline of 8 frames), logs and state in ``folder``."""
    from skinmap.daemon.config import load_config

    path = folder / "skinmapd.toml"
    path.write_text(f"""
[device]
port = "{device_url}"
name = "{name}"
scan_rate_hz = 20
[output]
rate_hz = 10
[zenoh]
listen = ["tcp/127.0.0.1:{zenoh_port}"]
[tactile]
enabled = true
baseline_frames = 8
[log]
directory = "logs"
[state]
directory = "state"
""")
    return load_config(path)


def wait_until(predicate: Callable[[], Any], timeout: float = WAIT_S, poll: float = 0.02) -> bool:
    """True as soon as `predicate()` is truthy; False if it is not after `timeout` seconds."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(poll)
    return bool(predicate())


def wait_for(predicate: Callable[[], Any], timeout: float = WAIT_S, what: str = "the condition",
             poll: float = 0.02) -> float:
    """Seconds until `predicate()` held (a figure to print, not to assert); fails naming
    `what` after `timeout`."""
    t0 = time.monotonic()
    if not wait_until(predicate, timeout, poll):
        raise AssertionError(f"timed out after {timeout} s waiting for {what}")
    return time.monotonic() - t0


def receive_elements(client: Any, count: int, timeout: float = WAIT_S) -> list:
    """The next `count` elements messages a SkinmapClient receives; their sequence numbers
    must rise (in order, none repeated)."""
    out = [client.elements(timeout=timeout) for _ in range(count)]
    seqs = [m.seq for m in out]
    assert all(b > a for a, b in zip(seqs, seqs[1:])), f"elements out of order: {seqs}"
    return out


@contextlib.contextmanager
def pty_emulator(link: Any, spec: Any, shape: Any, **emulator_kwargs: Any) -> Iterator[Any]:
    """An emulated scanner (ScannerSpec, shape) on a pseudo-terminal at `link`, stopped on exit."""
    from skinmap.emulator.emulator import Emulator
    from skinmap.emulator.transport import PtyTransport

    emu = Emulator(spec, shape, PtyTransport(link=link), **emulator_kwargs)
    emu.start()
    try:
        yield emu
    finally:
        emu.stop()


def gateway_config(tmp_path: Any, zport: int, port: Any, name: str, scan_rate_hz: float, *,
                   device: dict | None = None, output: dict | None = None, elements: dict | None = None,
                   log: dict | None = None, text: str = "") -> Any:
    """A validated skinmapd configuration for a test: the scanner at `port`, Zenoh listening on
    loopback `zport` only, logs and state under `tmp_path`."""
    from skinmap.daemon.config import parse_config

    return parse_config({
        "device": {"port": str(port), "name": name, "scan_rate_hz": scan_rate_hz, **(device or {})},
        "output": {"rate_hz": 20, "status_rate_hz": 4, **(output or {})},
        "elements": elements or {"layout": "grid", "rows": 1, "cols": 4},
        "zenoh": {"listen": [f"tcp/127.0.0.1:{zport}"]},
        "log": {"directory": str(tmp_path / "logs"), **(log or {})},
        "state": {"directory": str(tmp_path / "state")},
    }, source=str(tmp_path / "skinmapd.toml"), text=text)


def explicit_elements(uv: Any) -> dict:
    """The [elements] table placing one element at each (u, v) mm."""
    return {"layout": "explicit", "explicit": [{"u_mm": float(u), "v_mm": float(v)} for u, v in uv]}


@contextlib.contextmanager
def running_gateway(cfg: Any, **gateway_kwargs: Any) -> Iterator[Any]:
    """Open the config's Zenoh session, run a Gateway in a thread, stop and join it on exit."""
    from skinmap.daemon.service import Gateway, open_zenoh, zenoh_pose_inputs, zenoh_publishers

    with open_zenoh(cfg) as session:
        gw = Gateway(cfg, publishers=zenoh_publishers(cfg, session), pose_inputs=zenoh_pose_inputs(cfg, session),
                     **gateway_kwargs)
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


def pipeline_sheet(n: int = 5, m: int = 5, pitch: float = 12.0) -> tuple[Any, Any, Any, Any]:
    """The sheet the pipeline tests run: its geometry (h 0.2 mm), a 3 × 3 grid of elements, and
    per-gauge gauge factors and base resistances spread as the paper's channels are
    (1.24 ± 0.19, 6.55 ± 0.72 Ω; seeded)."""
    import numpy as np

    from skinmap.daemon.pipeline import ArrayGeometry

    elements = np.array([[u, v] for v in (-12.0, 0.0, 12.0) for u in (-18.0, 0.0, 18.0)])
    gf = 1.24 + 0.19 * np.random.default_rng(3).standard_normal((2, 2, n, m))
    r0 = 6.55 + 0.72 * np.random.default_rng(4).standard_normal((2, 2, n, m))
    return ArrayGeometry(n, m, pitch, 0.2, 0.2), elements, gf, r0


def aligned_node_errors(nodes: Any, truth: Any) -> Any:
    """Every node's error (K,) after the best rigid alignment (Kabsch) of ``nodes`` onto ``truth``."""
    import numpy as np

    from skinmap.reconstruction.linalg import aligned_distances

    p, q = np.asarray(nodes, dtype=float).reshape(-1, 3), np.asarray(truth, dtype=float).reshape(-1, 3)
    return aligned_distances(p, q)


def aligned_error(nodes: Any, truth: Any) -> float:
    """Mean node error after the best rigid alignment (Kabsch)."""
    return float(aligned_node_errors(nodes, truth).mean())


def frame_errors(shape: Any, surf: Any, grid: Any) -> Any:
    """Node errors (N, M) in the sensor frame itself, no alignment: the truth (an emulator
    shape) put in the frame by its definition."""
    import numpy as np

    from skinmap.reconstruction import nodes_in_sensor_frame

    return np.linalg.norm(surf.nodes - nodes_in_sensor_frame(grid, shape.position), axis=-1)


def bench_module(name: str) -> Any:
    """A module of the bench folder (tests replay the bench's own cases and loops, not copies)."""
    import importlib
    import sys
    from pathlib import Path

    folder = str(Path(__file__).resolve().parent.parent / "bench")
    if folder not in sys.path:
        sys.path.insert(0, folder)
    return importlib.import_module(name)


def elastic_dataset() -> Any:
    """bench/elastic_dataset.py, the elastic bench's scenes and noise draws."""
    return bench_module("elastic_dataset")


def worst_of_answers(surf: Any, truth: Any) -> list[float]:
    """Largest node error after the best rigid alignment over 3 node_sigma + 0.05 mm, for the
    answer and, where it is flagged ambiguous, its mirror (either may be the right one)."""
    import numpy as np

    from skinmap.reconstruction.linalg import aligned_distances

    bound = 3.0 * surf.node_sigma.reshape(-1) + 0.05
    truth = np.asarray(truth, dtype=float).reshape(-1, 3)
    answers = [surf] + ([surf.mirror] if surf.mirror is not None else [])
    return [float(np.max(aligned_distances(a.nodes.reshape(-1, 3), truth) / bound)) for a in answers]


def within_3_sigma_in_frame(shape: Any, surf: Any, grid: Any) -> bool:
    """Every sensor-frame node error of the answer, or of its mirror where it is flagged
    ambiguous, within 3 node_sigma + 0.05 mm."""
    import numpy as np

    bound = 3.0 * surf.node_sigma + 0.05
    answers = [surf] + ([surf.mirror] if surf.mirror is not None else [])
    return any(bool(np.all(frame_errors(shape, a, grid) <= bound)) for a in answers)


def rigid_motion(src: Any, dst: Any) -> tuple[Any, Any]:
    """R, t minimising |R·src + t − dst| (Kabsch) for (K, 3) point sets, for tests that move
    other points with the same motion (distances alone: `aligned_error`)."""
    import numpy as np

    src, dst = np.asarray(src, dtype=float), np.asarray(dst, dtype=float)
    cs, cd = src.mean(0), dst.mean(0)
    u, _s, vt = np.linalg.svd((src - cs).T @ (dst - cd))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    r = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return r, cd - r @ cs


def _readable_by_others(path: str) -> bool:
    """Whether a user that is neither owner nor group can reach and read `path`."""
    import os
    import stat

    for p in {os.path.abspath(path), os.path.realpath(path)}:  # the link and what it points to
        parts = p.split(os.sep)
        for i in range(2, len(parts)):
            if not os.stat(os.sep.join(parts[:i])).st_mode & stat.S_IXOTH:
                return False
        if not os.stat(p).st_mode & stat.S_IROTH:
            return False
    return True


def _link_tree(src: str, dst: str) -> None:
    """Copy a tree as hard links where the file system allows (fast, mtimes kept: numba's cache
    index matches its sources by mtime and size), as copies otherwise."""
    import os
    import shutil

    def link(a: str, b: str) -> None:
        try:
            os.link(a, b)
        except OSError:
            shutil.copy2(a, b)

    shutil.copytree(src, dst, symlinks=True, copy_function=link, dirs_exist_ok=True,
                    ignore=shutil.ignore_patterns("__editable__*", "skinmap-*.dist-info"))


def _declared_packages() -> list[str]:
    import tomllib

    root = Path(__file__).resolve().parents[1]
    return list(tomllib.loads((root / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])


@contextlib.contextmanager
def python_for_other_users(*extra_dirs: str) -> Iterator[tuple[str, dict[str, str], dict[str, str]]]:
    """(interpreter, environment additions, {dir: its readable copy}) with which another user
    (the service's unprivileged one) runs this checkout's skinmap and dependencies.

    A checkout in a private directory (mode 0700, e.g. under /root) is out of that user's reach,
    and so may be the interpreter: then the interpreter, the environment's site-packages, the
    package's folders and `extra_dirs` are linked into a world-readable temporary directory.
    Otherwise everything is used where it is."""
    import importlib
    import os
    import shutil
    import sys
    import sysconfig
    import tempfile

    # every subpackage the project declares (pyproject's package list: one source of truth)
    names = [name for name in _declared_packages() if name.count(".") == 1] + ["skinmap"]
    packages = {name: list(importlib.import_module(name).__path__)[0] for name in names}
    site = sysconfig.get_paths()["purelib"]
    needed = [sys.executable, site, *packages.values(), *extra_dirs]
    if all(_readable_by_others(p) for p in needed):
        yield sys.executable, {}, {d: d for d in extra_dirs}
        return
    tmp = tempfile.mkdtemp(prefix="skinmap-readable-")
    try:
        os.chmod(tmp, 0o755)
        env: dict[str, str] = {"PYTHONNOUSERSITE": "1"}
        python = sys.executable if _readable_by_others(sys.executable) else os.path.realpath(sys.executable)
        if not _readable_by_others(python):
            base = os.path.join(tmp, "python")
            _link_tree(sys.base_prefix, base)
            python = os.path.join(base, "bin", os.path.basename(os.path.realpath(sys.executable)))
            env["LD_LIBRARY_PATH"] = os.path.join(base, "lib")
        _link_tree(site, os.path.join(tmp, "site"))
        for name, path in packages.items():
            _link_tree(path, os.path.join(tmp, "pkg", *name.split(".")))
        copies = {}
        for d in extra_dirs:
            copies[d] = os.path.join(tmp, "extra", os.path.basename(os.path.normpath(d)))
            _link_tree(d, copies[d])
        env["PYTHONPATH"] = os.pathsep.join([os.path.join(tmp, "pkg"), os.path.join(tmp, "site")])
        yield python, env, copies
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def notify_socket(path: Path, timeout: float = 0.05) -> socket.socket:
    """A bound datagram socket standing in for systemd's NOTIFY_SOCKET."""
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(path))
    sock.settimeout(timeout)
    return sock


def drain_notify(sock: socket.socket) -> list[str]:
    """Every sd_notify message waiting on ``sock``."""
    out = []
    while True:
        try:
            out.append(sock.recv(4096).decode())
        except (socket.timeout, BlockingIOError):
            return out


def bench_frame(key: str, seed: int, index: int, n: int, spec: str, draw: int,
                elastic_cache: Any = None) -> tuple[Any, Any, Any, Any]:
    """The elastic bench's scene ``index`` of class ``key`` (``seed``) on an n×n sheet at 12 mm,
    checked to be ``spec``, and its gauges' strains with the bench's noise draw ``draw``: (plan,
    shape, eps_upper, eps_lower).  The shape is the scene's kinematic form, or with
    ``elastic_cache`` (the solver's cache folder) the elastic film itself."""
    from skinmap.emulator import physics as ph
    from skinmap.emulator.scenes import parse_scene_spec

    ed = elastic_dataset()
    plan = ed.class_plans(key, seed, index + 1, n)[index]
    assert plan.spec == spec, plan.spec
    shape = (ed.kinematic_shape(plan) if elastic_cache is None
             else parse_scene_spec(plan.spec, "elastic", n, n, 12.0, cache_dir=elastic_cache))
    eu, el = ph.gauge_strains(shape, n, n, 12.0, 0.2, 0.2, 10.0)
    du, dl = ed.noise_draw(plan, draw, 0.0057e-2, eu.shape)
    return plan, shape, eu + du, el + dl
