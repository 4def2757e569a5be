"""Zenoh load on a real skinmapd process: subscribers joining and leaving fast, a subscriber
that reads nothing for seconds, 20 subscribers at once. The daemon must keep processing and
publishing, in order, to every subscriber that reads. Rates and memory (RSS from /proc) are
measured and printed, never asserted: they depend on the machine's load.

Everything is on loopback: the daemon listens on tcp/127.0.0.1:PORT, every test session
connects there with multicast scouting off (make_session_config). Figures are printed with
the prefix "FIGURE" (run with -s).
"""
from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import threading
import time
from dataclasses import dataclass, field

import numpy as np
import pytest
import zenoh
from conftest import free_port

from skinmap.daemon.cli import start_emulator, stop_process
from skinmap.client import SkinmapClient
from skinmap.daemon.zenoh_io import key_for, make_session_config

pytestmark = pytest.mark.slow

DEVICE = "load"
SCAN_RATE_HZ = 50.0
OUTPUT_RATE_HZ = 25.0


def rss_mib(pid: int) -> float:
    """Resident set size of a process, MiB, from /proc/PID/status."""
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    raise RuntimeError(f"no VmRSS for process {pid}")


class RssSampler:
    """Samples a process's RSS every `period` s in a thread. RSS of a Zenoh process moves by
    ±10 MiB as its runtime threads' allocator arenas fill and trim, so memory is judged on
    medians and peaks of many samples, not on two readings."""

    def __init__(self, pid: int, period: float = 0.1) -> None:
        self.pid, self.period = pid, period
        self.samples: list[float] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self._stop.is_set():
            self.samples.append(rss_mib(self.pid))
            self._stop.wait(self.period)

    def __enter__(self) -> "RssSampler":
        self._thread.start()
        return self

    def __exit__(self, *_exc: object) -> None:
        self._stop.set()
        self._thread.join()

    def summary(self) -> str:
        a = np.array(self.samples)
        return f"{np.median(a):.1f} (max {a.max():.1f})"


def median_rss(daemon: "Daemon", seconds: float) -> float:
    with RssSampler(daemon.proc.pid) as s:
        time.sleep(seconds)
    return float(np.median(s.samples))


@dataclass
class StatusLog:
    """Every status report the daemon publishes, with its arrival time."""

    reports: list[tuple[float, dict]] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def add(self, st: dict) -> None:
        with self.lock:
            self.reports.append((time.monotonic(), st))

    def latest(self) -> dict:
        with self.lock:
            return self.reports[-1][1]


@dataclass
class Daemon:
    proc: subprocess.Popen
    endpoint: str
    observer: SkinmapClient
    status: StatusLog

    def rss(self) -> float:
        return rss_mib(self.proc.pid)

    def client(self, **kw) -> SkinmapClient:
        return SkinmapClient([self.endpoint], prefix="skinmap", device=DEVICE, **kw)


@pytest.fixture(scope="module")
def daemon(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("zenoh-load")
    eport, zport = free_port(), free_port()
    emulator = start_emulator(eport, size="5x5", shape="cylinder:radius=40", rate=SCAN_RATE_HZ)
    cfg = tmp / "skinmapd.toml"
    cfg.write_text(textwrap.dedent(f"""
        [device]
        port = "socket://127.0.0.1:{eport}"
        name = "{DEVICE}"
        scan_rate_hz = {SCAN_RATE_HZ}
        [output]
        rate_hz = {OUTPUT_RATE_HZ}
        status_rate_hz = 2
        [zenoh]
        listen = ["tcp/127.0.0.1:{zport}"]
        [log]
        directory = "logs"
        [state]
        directory = "state"
    """))
    proc = subprocess.Popen([sys.executable, "-m", "skinmap.daemon.service", "--config", str(cfg)],
                            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    endpoint = f"tcp/127.0.0.1:{zport}"
    status = StatusLog()
    observer = SkinmapClient([endpoint], prefix="skinmap", device=DEVICE)
    try:
        observer.open()
        observer.on_message("status", status.add)
        observer.elements(timeout=60.0)
        deadline = time.monotonic() + 20
        # Warm up until the rate window is full and steady.
        while time.monotonic() < deadline and not (
                status.reports and status.latest()["publish_rate_hz"] >= 0.8 * OUTPUT_RATE_HZ):
            time.sleep(0.2)
        time.sleep(1.0)
        assert proc.poll() is None, proc.stderr.read().decode()[-2000:]
        yield Daemon(proc, endpoint, observer, status)
    finally:
        observer.close()
        stop_process(proc, timeout=20)
        stop_process(emulator)
        err = proc.stderr.read().decode()
        proc.stderr.close()
    assert proc.returncode == 0, err[-2000:]
    assert "Traceback" not in err, err[-3000:]


def received_in_order(client: SkinmapClient, count: int = 10) -> float:
    """Receive `count` elements messages (generous time-outs); their sequence numbers must
    rise. Returns the rate they came at, for the printed figure only."""
    client.subscribe("elements")
    seqs = [client.elements(timeout=30.0).seq]
    t0 = time.monotonic()
    for _ in range(count):
        seqs.append(client.elements(timeout=30.0).seq)
    assert all(b > a for a, b in zip(seqs, seqs[1:])), seqs
    return count / (time.monotonic() - t0)


# Warnings a loaded machine may raise without anything being wrong: the bounded processing
# queue skips scans by design when reconstruction falls behind the output rate.
_LOAD_WARNINGS = ("skipped by the processing queue",)


def check_kept_publishing(daemon: Daemon, t0: float, t1: float, what: str) -> np.ndarray:
    """The daemon processed and published throughout [t0, t1], without errors."""
    deadline = time.monotonic() + 30.0
    while time.monotonic() < deadline and daemon.status.reports[-1][0] <= t1:
        time.sleep(0.2)  # wait for one report after the window
    with daemon.status.lock:
        window = [st for t, st in daemon.status.reports if t0 <= t]
    assert len(window) >= 2, f"no status reports during {what}"
    first, last = window[0], window[-1]
    assert last["results"] > first["results"] and last["seq"] > first["seq"], f"nothing published during {what}"
    assert last["publish_errors"] == first["publish_errors"], what
    assert last["processing_errors"] == first["processing_errors"], what
    assert all(st["connected"] for st in window), what
    unexpected = [w for st in window for w in st["warnings"] if not any(k in w for k in _LOAD_WARNINGS)]
    assert not unexpected, unexpected
    return np.array([st["publish_rate_hz"] for st in window])


def test_subscribers_joining_and_leaving_fast(daemon):
    keys = [key_for("skinmap", DEVICE, kind) for kind in ("elements", "surface", "strains", "status")]
    conf = make_session_config([], [daemon.endpoint])

    def churn(sessions: int, per_session: int) -> int:
        cycles = 0
        for _ in range(sessions):
            session = zenoh.open(conf)
            try:
                for k in range(per_session):
                    sub = session.declare_subscriber(keys[k % len(keys)], lambda s: None)
                    sub.undeclare()
                    cycles += 1
            finally:
                session.close()
        return cycles

    churn(5, 10)  # let the daemon reach its working size
    base = median_rss(daemon, 1.0)
    t0 = time.monotonic()
    with RssSampler(daemon.proc.pid) as first:
        cycles_a = churn(20, 10)
    with RssSampler(daemon.proc.pid) as second:
        cycles_b = churn(20, 10)
    t1 = time.monotonic()
    after = median_rss(daemon, 1.0)
    rates = check_kept_publishing(daemon, t0, t1, "subscriber churn")
    with daemon.client() as late:  # and a new subscriber is served as before
        rate = received_in_order(late)
    peak = max(first.samples + second.samples)
    print(f"FIGURE zenoh churn: {cycles_a + cycles_b} subscriber and 40 session open/close cycles in "
          f"{t1 - t0:.1f} s; daemon publish rate {rates.min():.1f}..{rates.max():.1f} Hz (set {OUTPUT_RATE_HZ:g}); "
          f"RSS MiB median before {base:.1f}, first half {first.summary()}, second half {second.summary()}, "
          f"after {after:.1f}, peak {peak:.1f}; a late subscriber then receives {rate:.1f}/s")
    assert cycles_a + cycles_b == 400
    assert daemon.proc.poll() is None


SLOW_SUBSCRIBER = textwrap.dedent("""
    import sys, time, zenoh
    from skinmap.daemon.zenoh_io import make_session_config
    endpoint, prefix, seconds = sys.argv[1], sys.argv[2], float(sys.argv[3])
    with zenoh.open(make_session_config([], [endpoint])) as session:
        # A small FIFO nobody reads: once full it blocks this session's receive path, so the
        # daemon's link to it backs up.
        subs = [session.declare_subscriber(prefix + "/" + kind, zenoh.handlers.FifoChannel(2))
                for kind in ("elements", "surface", "strains")]
        print("subscribed", flush=True)
        time.sleep(seconds)
        print("done", flush=True)
""")


def test_a_subscriber_that_reads_nothing_does_not_slow_the_daemon_or_others(daemon):
    base = median_rss(daemon, 1.0)
    slow = subprocess.Popen([sys.executable, "-c", SLOW_SUBSCRIBER, daemon.endpoint, f"skinmap/{DEVICE}", "6"],
                            stdout=subprocess.PIPE, text=True)
    try:
        assert slow.stdout.readline().strip() == "subscribed"
        with RssSampler(daemon.proc.pid) as during:
            time.sleep(1.0)
            t0 = time.monotonic()
            with daemon.client() as fast:
                rate = received_in_order(fast, 20)
            t1 = time.monotonic()
        assert slow.poll() is None  # still stuck, still connected
        assert slow.stdout.readline().strip() == "done"
    finally:
        slow.kill()
        slow.wait()
        slow.stdout.close()
    after = median_rss(daemon, 1.0)
    rates = check_kept_publishing(daemon, t0, t1, "a stuck subscriber")
    print(f"FIGURE zenoh stuck subscriber (6 s, reads nothing): daemon publish rate "
          f"{rates.min():.1f}..{rates.max():.1f} Hz; another subscriber receives {rate:.1f}/s; "
          f"RSS MiB median before {base:.1f}, during {during.summary()}, after {after:.1f}")
    assert daemon.proc.poll() is None


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of a process so far, from /proc/PID/stat."""
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def test_twenty_subscribers_at_once(daemon):
    keys = [key_for("skinmap", DEVICE, kind) for kind in ("elements", "surface")]
    conf = make_session_config([], [daemon.endpoint])

    def round_of_twenty(seconds: float) -> tuple[np.ndarray, RssSampler, float]:
        """20 sessions, each subscribed to elements and surface; elements received by each."""
        sessions = [zenoh.open(conf) for _ in range(20)]
        try:
            # Ring buffers filled on Zenoh's side: the test's own CPU use stays small.
            subs = [[s.declare_subscriber(k, zenoh.handlers.RingChannel(4096)) for k in keys] for s in sessions]
            time.sleep(1.0)  # every subscription reaches the daemon
            for elements, _surface in subs:
                while elements.try_recv() is not None:
                    pass
            cpu0 = cpu_seconds(daemon.proc.pid)
            with RssSampler(daemon.proc.pid) as rss:
                time.sleep(seconds)
            cpu = cpu_seconds(daemon.proc.pid) - cpu0
            got = np.zeros(20)
            for i, (elements, _surface) in enumerate(subs):
                while elements.try_recv() is not None:
                    got[i] += 1
            return got / seconds, rss, cpu / seconds
        finally:
            for s in sessions:
                s.close()

    base = median_rss(daemon, 1.0)
    cpu0 = cpu_seconds(daemon.proc.pid)
    time.sleep(2.0)
    idle_cpu = (cpu_seconds(daemon.proc.pid) - cpu0) / 2.0
    t0 = time.monotonic()
    rate_a, rss_a, cpu_a = round_of_twenty(2.5)
    t1 = time.monotonic()
    rate_b, rss_b, cpu_b = round_of_twenty(2.5)
    after = median_rss(daemon, 1.0)
    rates = check_kept_publishing(daemon, t0, t1, "20 subscribers")
    per_sub = np.concatenate([rate_a, rate_b])
    print(f"FIGURE zenoh 20 subscribers (elements + surface each): daemon publish rate "
          f"{rates.min():.1f}..{rates.max():.1f} Hz; each subscriber received {per_sub.min():.1f}..{per_sub.max():.1f} "
          f"elements/s (set {OUTPUT_RATE_HZ:g}); daemon CPU {idle_cpu * 100:.0f} % with 1 subscriber, "
          f"{cpu_a * 100:.0f} / {cpu_b * 100:.0f} % with 20; RSS MiB median before {base:.1f}, first 20 "
          f"{rss_a.summary()}, second 20 {rss_b.summary()}, after {after:.1f}")
    # every one of the 40 subscribers was served
    assert (per_sub > 0).all(), per_sub
    assert daemon.proc.poll() is None
