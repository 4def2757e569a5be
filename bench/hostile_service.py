"""Hostile scenarios against the service: a scanner clock that stops, runs backwards or jumps;
tare files that are no tare (wrong JSON type, a FIFO), at start and on reload; a data path that
fails or blocks (systemd watchdog, SIGTERM); a Zenoh endpoint already in use; querying clients
that stop reading; thousands of subscribers.

Each scenario runs the emulated scanner on a pseudo-terminal in this process and skinmapd on
loopback (a subprocess, except where a fault has to be injected into the pipeline), then prints
one line with what was observed. It measures; it asserts nothing. Zenoh sessions listen and
connect on tcp/127.0.0.1 only, multicast scouting off.

    .venv/bin/python bench/hostile_service.py              # every scenario
    .venv/bin/python bench/hostile_service.py clock tare   # scenarios whose name contains a word
"""
from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import textwrap
import threading
import time
from pathlib import Path
from typing import Any, Callable, Iterator

import zenoh

from latency import free_port  # bench/latency.py
from skinmap.strains import save_tare, tare_path
from skinmap.client import SkinmapClient
from skinmap.daemon.zenoh_io import make_session_config
from skinmap.emulator.device import ScannerSpec
from skinmap.emulator.emulator import Emulator
from skinmap.emulator.physics import make_shape
from skinmap.emulator.transport import PtyTransport

DEVICE = "hostile"
SCAN_HZ, OUTPUT_HZ, N = 40.0, 20.0, 5
WATCHDOG_USEC = 10_000_000  # WatchdogSec=10, as in systemd/skinmapd.service


def wait_until(predicate: Callable[[], Any], timeout: float, poll: float = 0.02) -> float | None:
    """Seconds until `predicate()` held, or None after `timeout`."""
    t0 = time.monotonic()
    while not predicate():
        if time.monotonic() - t0 > timeout:
            return None
        time.sleep(poll)
    return time.monotonic() - t0


def fmt_s(value: float | None) -> str:
    return "never" if value is None else f"{value:.2f} s"


class Notifications:
    """Every sd_notify datagram the daemon sends, with its arrival time."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(str(path))
        self.sock.settimeout(0.1)
        self.seen: list[tuple[float, str]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                self.seen.append((time.monotonic(), self.sock.recv(4096).decode()))
            except socket.timeout:
                pass
            except OSError:
                return

    def times(self, text: str) -> list[float]:
        return [t for t, m in list(self.seen) if text in m]

    def close(self) -> None:
        self._stop.set()
        self._thread.join()
        self.sock.close()


class Rig:
    """The emulator on a pty in this process and one skinmapd subprocess reading it."""

    def __init__(self, work: Path, *, console: bool = False, stdout: Any = subprocess.DEVNULL,
                 zport: int | None = None, **sections: dict[str, Any]) -> None:
        self.work = work
        work.mkdir(parents=True, exist_ok=True)
        self.emulator = Emulator(ScannerSpec(n=N, m=N, scan_rate_hz=SCAN_HZ, seed=7),
                                 make_shape("cylinder", radius=45.0), PtyTransport(link=work / "tty"))
        self.emulator.start()
        wait_until(lambda: self.emulator.device is not None, 10)
        self.zport = zport or free_port()
        self.endpoint = f"tcp/127.0.0.1:{self.zport}"
        self.config = work / "skinmapd.toml"
        self.config.write_text(daemon_config(work, self.zport, **sections))
        self.console, self.stdout = console, stdout
        self.proc: subprocess.Popen | None = None
        self.notes: Notifications | None = None

    @property
    def tare(self) -> Path:
        return tare_path(self.work / "state", self.emulator.device.serial_number)

    def start(self) -> float:
        self.notes = Notifications(self.work / "notify.sock")
        env = {**os.environ, "NOTIFY_SOCKET": str(self.notes.path), "WATCHDOG_USEC": str(WATCHDOG_USEC)}
        self.stderr = open(self.work / "stderr.txt", "wb")
        self.t_start = time.monotonic()
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "skinmap.daemon.service", "--config", str(self.config),
             *(["--console"] if self.console else [])],
            env=env, stdin=subprocess.DEVNULL, stdout=self.stdout, stderr=self.stderr)
        return self.t_start

    def ready_after(self, timeout: float = 90.0) -> float | None:
        t = wait_until(lambda: self.notes.times("READY=1") or self.proc.poll() is not None, timeout)
        ready = self.notes.times("READY=1")
        return ready[0] - self.t_start if t is not None and ready else None

    def client(self) -> SkinmapClient:
        return SkinmapClient([self.endpoint], prefix="skinmap", device=DEVICE)

    def stop(self, timeout: float = 30.0) -> tuple[int | None, float]:
        t0 = time.monotonic()
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        return (self.proc.returncode if self.proc else None), time.monotonic() - t0

    def stderr_text(self) -> str:
        return (self.work / "stderr.txt").read_text(errors="replace")

    def log_finished(self) -> bool:
        logs = self.work / "logs"
        return bool(list(logs.glob("*.mcap"))) and not list(logs.glob("*.mcap.active"))

    def close(self) -> None:
        self.stop()
        if self.notes is not None:
            self.notes.close()
        if getattr(self, "stderr", None) is not None:
            self.stderr.close()
        self.emulator.stop()


def daemon_config(work: Path, zport: int, **sections: dict[str, Any]) -> str:
    base: dict[str, dict[str, Any]] = {
        "device": {"port": str(work / "tty"), "name": DEVICE, "scan_rate_hz": SCAN_HZ},
        "output": {"rate_hz": OUTPUT_HZ, "status_rate_hz": 4},
        "elements": {"layout": "grid", "rows": 1, "cols": 8},
        "zenoh": {"listen": [f"tcp/127.0.0.1:{zport}"]},
        "log": {"directory": "logs"},
        "state": {"directory": "state"},
    }
    for name, values in sections.items():
        base.setdefault(name, {}).update(values)
    return "".join(f"[{name}]\n" + "".join(f"{k} = {json.dumps(v)}\n" for k, v in values.items())
                   for name, values in base.items())


@contextlib.contextmanager
def rig(work: Path, **kw: Any) -> Iterator[Rig]:
    r = Rig(work, **kw)
    try:
        yield r
    finally:
        r.close()


def received_per_s(client: SkinmapClient, seconds: float) -> float:
    """Elements messages per second arriving here, counting only those computed from now on
    (the client's queue may hold older ones)."""
    t0_ns = time.time_ns()
    while client.elements(timeout=10.0).host_time_ns < t0_ns:
        pass
    n, t0 = 0, time.monotonic()
    while time.monotonic() - t0 < seconds:
        client.elements(timeout=5.0)
        n += 1
    return n / (time.monotonic() - t0)


def fresh_statuses(client: SkinmapClient, n: int) -> list[dict]:
    """The next `n` status reports made from now on (the client's queue may hold older ones)."""
    t0_ns, out = time.time_ns(), []
    while len(out) < n:
        st = client.next("status", timeout=5.0)
        if st["host_time_ns"] >= t0_ns:
            out.append(st)
    return out


def cpu_s(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def status_where(client: SkinmapClient, predicate: Callable[[dict], bool], timeout: float) -> tuple[float | None, dict]:
    t0, t0_ns, last = time.monotonic(), time.time_ns(), {}
    while time.monotonic() - t0 < timeout:
        try:
            st = client.next("status", timeout=2.0)
        except Exception:  # noqa: BLE001 - no report within the wait; keep waiting
            continue
        if st["host_time_ns"] < t0_ns:
            continue  # queued before this wait began
        last = st
        if predicate(last):
            return time.monotonic() - t0, last
    return None, last


def short(text: str, path: Path) -> str:
    return text.replace(str(path), path.name)


def warning_with(st: dict, word: str) -> str:
    return next((w for w in st.get("warnings", []) if word in w), "")


# ---------------------------------------------------------------------------------------------
# scenarios

CLOCKS: dict[str, Callable[[int], int]] = {
    "zero": lambda t: 0,
    "stuck": lambda t: 123_456_789,
    "backwards": lambda t: 10**10 - t,
    "jumping 3 s every 0.5 s": lambda t: t + (t // 500_000) * 3_000_000,
}


def scenario_clock(work: Path, kind: str) -> str:
    with rig(work) as r:
        r.start()
        with r.client() as c:
            before = received_per_s(c, 3.0)
            r.emulator.device.time_us = CLOCKS[kind]
            detect, st = status_where(c, lambda s: bool(warning_with(s, "scanner clock")), 15.0)
            during = received_per_s(c, 3.0)
            r.emulator.device.time_us = None
            healthy, _ = status_where(c, lambda s: s["healthy"], 20.0)
    return (f"clock {kind}: published {before:.1f}/s before, {during:.1f}/s during (output {OUTPUT_HZ:g} Hz); "
            f"status unhealthy {fmt_s(detect)} after the fault: \"{warning_with(st, 'scanner clock')[:90]}\"; "
            f"healthy {fmt_s(healthy)} after the clock was good again")


BAD_TARES = {"[]": "[]", "null": "null", "values null": json.dumps({"shape": [2, 2, N, N], "base_resistance_ohm": None})}


def scenario_tare_at_start(work: Path, kind: str) -> str:
    with rig(work) as r:
        r.tare.parent.mkdir(parents=True, exist_ok=True)
        if kind == "FIFO":
            os.mkfifo(r.tare)
        else:
            r.tare.write_text(BAD_TARES[kind])
        r.start()
        ready = r.ready_after()
        with r.client() as c:
            try:
                c.elements(timeout=30.0)
                first = time.monotonic() - r.t_start
            except Exception:  # noqa: BLE001
                first = None
            _t, st = status_where(c, lambda s: bool(warning_with(s, "tare")), 10.0)
        code, stop_s = r.stop()
    return (f"tare {kind} at start: READY after {fmt_s(ready)}, first elements after {fmt_s(first)}, "
            f"calibration {st.get('calibration')!r}, warning \"{short(warning_with(st, 'tare'), r.tare)}\"; "
            f"SIGTERM: exit {code} in {stop_s:.2f} s")


def scenario_tare_reload(work: Path, kind: str) -> str:
    with rig(work) as r:
        r.start()
        r.ready_after()
        with r.client() as c:
            c.elements(timeout=30.0)
            save_tare(work / "state", r.emulator.device.serial_number, r.emulator.device.hello().base_resistance_ohm(), 1)
            good, _ = status_where(c, lambda s: s["calibration"].startswith("tare"), 10.0)
            r.tare.unlink()
            if kind == "FIFO":
                os.mkfifo(r.tare)
            else:
                r.tare.write_text(BAD_TARES[kind])
            t0 = time.monotonic()
            seen, st = status_where(c, lambda s: s["calibration"] == "factory", 10.0)
            rate = received_per_s(c, 2.0)
            alive = r.proc.poll() is None
        code, stop_s = r.stop()
    return (f"tare {kind} on reload: good tare loaded after {fmt_s(good)}; bad one ignored after {fmt_s(seen)} "
            f"(calibration {st.get('calibration')!r}, \"{short(warning_with(st, 'tare'), r.tare)}\"); daemon running: {alive}, "
            f"published {rate:.1f}/s after; SIGTERM: exit {code} in {stop_s:.2f} s")


def scenario_processing_fails(work: Path) -> str:
    """In-process gateway with the pipeline made to fail every scan, watchdog period 10 s."""
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
    from conftest import running_gateway  # tests/conftest.py

    from skinmap.daemon.config import load_config
    from skinmap.daemon.notify import SystemdNotifier
    from skinmap.daemon.pipeline import FramePipeline

    original = FramePipeline.process
    broken = {"on": False}

    def process(self: Any, *args: Any, **kwargs: Any) -> Any:
        if broken["on"]:
            raise FloatingPointError("injected solver failure")
        return original(self, *args, **kwargs)

    r = Rig(work)
    notes = Notifications(work / "notify.sock")
    os.environ["WATCHDOG_USEC"] = str(WATCHDOG_USEC)
    FramePipeline.process = process
    try:
        with running_gateway(load_config(r.config), notifier=SystemdNotifier(str(notes.path))) as gw:
            wait_until(lambda: gw.stats.results > 10, 60)
            wait_until(lambda: notes.times("WATCHDOG=1"), 10)
            broken["on"] = True
            t_fail = time.monotonic()
            starved = wait_until(lambda: not gw.watchdog_fed, 30)
            feeds = [t for t in notes.times("WATCHDOG=1") if t >= t_fail]
            last_feed = (feeds[-1] - t_fail) if feeds else 0.0
            broken["on"] = False
            t_fix = time.monotonic()
            working = wait_until(lambda: gw.watchdog_fed, 20)
            fed = wait_until(lambda: [t for t in notes.times("WATCHDOG=1") if t > t_fix], 20)
            errors = gw.stats.processing_errors
    finally:
        FramePipeline.process = original
        os.environ.pop("WATCHDOG_USEC", None)
        notes.close()
        r.emulator.stop()
    return (f"processing fails every scan: watchdog last fed {last_feed:.2f} s after the first failure, data path "
            f"declared stalled after {fmt_s(starved)} (systemd restarts {WATCHDOG_USEC / 1e6:g} s after the last "
            f"feed); {errors} scans failed; data path working again {fmt_s(working)} after the fault was removed, "
            f"WATCHDOG=1 {fmt_s(fed)} after (sd_notify pings at most every {WATCHDOG_USEC / 2e6:g} s)")


def scenario_main_loop_blocked(work: Path) -> str:
    """The console line goes to a pipe nobody reads: the main loop blocks in print()."""
    with rig(work, console=True, stdout=subprocess.PIPE, output={"status_rate_hz": 100}) as r:
        r.start()
        ready = r.ready_after()
        t_ready = time.monotonic()
        wait_until(lambda: time.monotonic() - max(r.notes.times("WATCHDOG=1") or [t_ready]) > 6.0, 60)
        feeds = r.notes.times("WATCHDOG=1")
        last_feed = (feeds[-1] - t_ready) if feeds else 0.0
        code, stop_s = r.stop()
        finished = r.log_finished()
        r.proc.stdout.close()
    return (f"main loop blocked (console pipe full): READY after {fmt_s(ready)}, watchdog last fed {last_feed:+.2f} s "
            f"from READY, then never; SIGTERM: exit {code} in {stop_s:.2f} s, log finished: {finished}")


def scenario_zenoh_in_use(work: Path) -> str:
    with rig(work / "a") as first:
        first.start()
        first.ready_after()
        with first.client() as c:
            before = received_per_s(c, 2.0)
            st0 = fresh_statuses(c, 1)[0]
            second = work / "b"
            second.mkdir(parents=True)
            (second / "skinmapd.toml").write_text(daemon_config(second, first.zport))
            t0 = time.monotonic()
            proc = subprocess.run([sys.executable, "-m", "skinmap.daemon.service", "--config", str(second / "skinmapd.toml")],
                                  capture_output=True, text=True, timeout=120)
            took = time.monotonic() - t0
            after = received_per_s(c, 2.0)
            st1 = fresh_statuses(c, 1)[0]
    lines = [line for line in proc.stderr.splitlines() if line.startswith("skinmapd:")]
    return (f"Zenoh endpoint in use: second daemon exit {proc.returncode} after {took:.1f} s, "
            f"{'no traceback' if 'Traceback' not in proc.stderr else 'TRACEBACK'}, \"{lines[-1] if lines else ''}\"; "
            f"first daemon published {before:.1f}/s before, {after:.1f}/s after, scans_lost "
            f"{st0['scans_lost']} -> {st1['scans_lost']}, reconnects {st0['reconnects']} -> {st1['reconnects']}")


STALLED_QUERIER = textwrap.dedent("""
    import sys, time, zenoh
    from skinmap.daemon.zenoh_io import make_session_config
    endpoint, selector, n = sys.argv[1], sys.argv[2], int(sys.argv[3])
    with zenoh.open(make_session_config([], [endpoint])) as session:
        handlers = [session.get(selector, zenoh.handlers.FifoChannel(1), timeout=60.0) for _ in range(n)]
        print("stalled", flush=True)
        time.sleep(60)
""")


def scenario_stalled_querier(work: Path, n_queries: int) -> str:
    with rig(work, output={"points_per_pitch": 50}) as r:
        r.start()
        r.ready_after()
        with r.client() as c:
            c.surface(timeout=30.0)
            arrivals: list[float] = []
            c.on_message("elements", lambda _m: arrivals.append(time.monotonic()))
            stalled = subprocess.Popen([sys.executable, "-c", STALLED_QUERIER, r.endpoint, f"skinmap/{DEVICE}/*",
                                        str(n_queries)], stdout=subprocess.PIPE, text=True)
            try:
                stalled.stdout.readline()
                t_stall = time.monotonic()
                waits, failed, waits_failed = [], 0, []
                while time.monotonic() < t_stall + 6.0:
                    with r.client() as other:
                        t0 = time.monotonic()
                        try:
                            other.info(timeout=5.0)
                            waits.append(time.monotonic() - t0)
                        except LookupError:
                            failed += 1
                            waits_failed.append(round(t0 - t_stall, 2))
                time.sleep(max(0.0, t_stall + 6.0 - time.monotonic()))
            finally:
                stalled.kill()
                stalled.wait()
                stalled.stdout.close()
    window = [t for t in arrivals if t >= t_stall - 1.0]
    gap = max((b - a for a, b in zip(window, window[1:])), default=float("nan"))
    worst = max(waits) if waits else float("nan")
    return (f"querying client stalled with {n_queries} unread queries (40 000-point surfaces): other clients' "
            f"info answered {len(waits)}x in 6 s, slowest {worst * 1e3:.0f} ms, {failed} timed out (5 s; asked "
            f"{', '.join(f'{t:.1f}' for t in waits_failed) or '-'} s after the stall); "
            f"another subscriber's longest gap in elements {gap * 1e3:.0f} ms")


SUBSCRIBERS = textwrap.dedent("""
    import sys, time, zenoh
    from skinmap.daemon.zenoh_io import make_session_config
    endpoint, prefix, n, mode = sys.argv[1], sys.argv[2], int(sys.argv[3]), sys.argv[5]
    count = [0]
    def on_sample(_sample):
        count[0] += 1
    # "ring": samples land in Rust ring channels of one, no Python per sample in this process;
    # "callback": a Python callback per sample and subscriber.
    with zenoh.open(make_session_config([], [endpoint])) as session:
        subs = [session.declare_subscriber(prefix + "/" + ("elements", "surface", "strains")[i % 3],
                                           zenoh.handlers.RingChannel(1) if mode == "ring" else on_sample)
                for i in range(n)]
        print("subscribed", flush=True)
        time.sleep(float(sys.argv[4]))
        got = sum(s.handler.try_recv() is not None for s in subs) if mode == "ring" else count[0]
        print(got, flush=True)
""")

CPU_HOG = "import time\nt = time.monotonic() + float(__import__('sys').argv[1])\nwhile time.monotonic() < t: pass\n"


def scenario_many_subscribers(work: Path, n_subs: int, mode: str) -> str:
    with rig(work) as r:
        r.start()
        r.ready_after()
        with r.client() as c:
            c.elements(timeout=30.0)
            time.sleep(2.5)
            cpu0, t0 = cpu_s(r.proc.pid), time.monotonic()
            st0 = fresh_statuses(c, 12)
            rates0 = [s["publish_rate_hz"] for s in st0]
            cpu_before = (cpu_s(r.proc.pid) - cpu0) / (time.monotonic() - t0)
            if mode == "cpu-hog":
                cmd = [sys.executable, "-c", CPU_HOG, "9"]
            else:
                cmd = [sys.executable, "-c", SUBSCRIBERS, r.endpoint, f"skinmap/{DEVICE}", str(n_subs), "9", mode]
            subs = subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True)
            hog_cpu0 = 0.0
            try:
                t0 = time.monotonic()
                if mode != "cpu-hog":
                    subs.stdout.readline()
                declared = time.monotonic() - t0
                time.sleep(2.5)
                cpu0, hog_cpu0, t0 = cpu_s(r.proc.pid), cpu_s(subs.pid), time.monotonic()
                st = fresh_statuses(c, 12)
                rates = [s["publish_rate_hz"] for s in st]
                cpu_with = (cpu_s(r.proc.pid) - cpu0) / (time.monotonic() - t0)
                hog_cpu = (cpu_s(subs.pid) - hog_cpu0) / (time.monotonic() - t0)
                mine = received_per_s(c, 2.0)
                got = int(subs.stdout.readline() or 0) if mode != "cpu-hog" else 0
            finally:
                subs.kill()
                subs.wait()
                subs.stdout.close()
    what = ("a process spinning on one core (control)" if mode == "cpu-hog" else
            f"{n_subs} subscribers ({mode}) in one session, declared in {declared:.1f} s")
    return (f"{what}: daemon publish rate {min(rates0):.1f}-{max(rates0):.1f} Hz before, "
            f"{min(rates):.1f}-{max(rates):.1f} Hz with it (scans in {min(s['scan_rate_hz'] for s in st):.1f}-"
            f"{max(s['scan_rate_hz'] for s in st):.1f}/s); daemon CPU {cpu_before * 100:.0f} % -> {cpu_with * 100:.0f} % "
            f"of a core, the other process {hog_cpu * 100:.0f} %; another subscriber receives {mine:.1f}/s"
            + (f"; samples counted by the subscribers: {got}" if mode != "cpu-hog" else ""))


def scenarios() -> dict[str, Callable[[Path], str]]:
    out: dict[str, Callable[[Path], str]] = {}
    for kind in CLOCKS:
        out[f"clock {kind}"] = lambda w, k=kind: scenario_clock(w, k)
    for kind in (*BAD_TARES, "FIFO"):
        out[f"tare {kind} at start"] = lambda w, k=kind: scenario_tare_at_start(w, k)
    for kind in ("null", "FIFO"):
        out[f"tare {kind} on reload"] = lambda w, k=kind: scenario_tare_reload(w, k)
    out["watchdog processing fails"] = scenario_processing_fails
    out["watchdog main loop blocked"] = scenario_main_loop_blocked
    out["zenoh endpoint in use"] = scenario_zenoh_in_use
    for n in (200, 2000):
        out[f"zenoh stalled querier {n}"] = lambda w, k=n: scenario_stalled_querier(w, k)
    for n, mode in ((20, "callback"), (2000, "ring"), (2000, "callback"), (0, "cpu-hog")):
        out[f"zenoh subscribers {n} {mode}"] = lambda w, k=n, m=mode: scenario_many_subscribers(w, k, m)
    return out


def main(argv: list[str]) -> int:
    chosen = {name: fn for name, fn in scenarios().items() if not argv or any(a in name for a in argv)}
    if not chosen:
        print(f"no scenario matches {argv}; scenarios: {', '.join(scenarios())}", file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory(prefix="skinmap-hostile-") as tmp:
        for i, (name, fn) in enumerate(chosen.items()):
            try:
                line = fn(Path(tmp) / f"s{i}")
            except Exception as exc:  # noqa: BLE001 - report the scenario and go on with the next
                line = f"{name}: scenario error {type(exc).__name__}: {exc}"
            print(line, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
