"""A fleet on loopback: 3 gateways (skinmapd processes fed by emulators) connected to one
Zenoh router (`skinmap router`'s config, in this process), a recorder and 5 subscribers that
connect only to the router. Prints the end-to-end latency through the router (gateway receive
of the scan -> subscriber), messages lost per subscriber, and how complete the recording is
against each gateway's own log.

    .venv/bin/python bench/fleet.py --seconds 20

Loopback only, no scouting. `Fleet` is also the topology of tests/test_fleet.py.
"""

from __future__ import annotations

import argparse
import contextlib
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from latency import free_port  # bench/latency.py
from skinmap.client import check_message
from skinmap.daemon.cli import start_emulator, stop_process
from skinmap.daemon.fleet import Recorder, discover, router_config
from skinmap.daemon.mcapread import iter_messages_file_order
from skinmap.daemon.zenoh_io import make_session_config, open_session
from skinmap.wire import messages as wire

PREFIX = "fleet"
SCAN_HZ = 20.0
OUTPUT_HZ = 10.0
EXPECTED_STEP = round(SCAN_HZ / OUTPUT_HZ)


def gateway_config(path: Path, device: str, serial_port: int, router: str) -> None:
    path.write_text(f"""
[device]
port = "socket://127.0.0.1:{serial_port}"
name = "{device}"
scan_rate_hz = {SCAN_HZ}
[output]
rate_hz = {OUTPUT_HZ}
surface_rate_hz = 2
strains_rate_hz = 2
[elements]
layout = "grid"
rows = 1
cols = 8
pitch_u_mm = 3.0
[zenoh]
prefix = "{PREFIX}"
listen = []
connect = ["{router}"]
[log]
directory = "logs-{device}"
surface_rate_hz = 1
[state]
directory = "state-{device}"
""")


@dataclass
class SubscriberStats:
    """What one subscriber received: per device, seqs and receive latencies (ms)."""

    seqs: dict[str, list[int]] = field(default_factory=dict)
    latency_ms: list[float] = field(default_factory=list)
    nan_in_valid: int = 0
    rejected: int = 0

    def add(self, device: str, msg: wire.ElementsMessage) -> None:
        self.latency_ms.append((time.time_ns() - msg.host_time_ns) / 1e6)
        self.seqs.setdefault(device, []).append(msg.seq)
        bad = msg.valid & ~np.isfinite(msg.positions).all(axis=1)
        self.nan_in_valid += int(bad.sum())


def _receive(stats: SubscriberStats, sample) -> None:
    device = str(sample.key_expr).split("/")[-2]
    try:
        msg = check_message("elements", sample.payload.to_bytes())
    except wire.MessageError:
        stats.rejected += 1
        return
    stats.add(device, msg)


def missing_at_step(seqs: list[int], step: int) -> int:
    """Messages missing in a seq series at the expected step (host-time decimation: a step
    within half a step of the expected one loses nothing)."""
    d = np.diff(np.asarray(seqs, dtype=np.int64)) % 2**32
    d = d[(d > 0) & (d < 2**31)]
    return int(np.maximum(np.round(d / step) - 1, 0).sum())


class Fleet:
    """Router, gateways, subscribers and a recorder on loopback; a context manager."""

    def __init__(self, workdir: Path, gateways: int = 3, subscribers: int = 5,
                 size: str = "3x3") -> None:
        self.workdir = workdir
        self.devices = [f"gw{i}" for i in range(gateways)]
        self.n_subscribers = subscribers
        self.size = size
        self.router = f"tcp/127.0.0.1:{free_port()}"
        self.stats = [SubscriberStats() for _ in range(subscribers)]
        self.recorder: Recorder | None = None
        self.record_dir = workdir / "recordings"
        self._stack = contextlib.ExitStack()
        self.procs: list[subprocess.Popen] = []

    def __enter__(self) -> "Fleet":
        try:
            self._start()
        except BaseException:
            self._stack.close()
            raise
        return self

    def _start(self) -> None:
        st = self._stack
        st.enter_context(open_session(router_config([self.router])))
        for device in self.devices:
            port = free_port()
            emulator = start_emulator(port, size=self.size, shape="cylinder:radius=40",
                                      rate=SCAN_HZ)
            st.callback(stop_process, emulator)
            cfg = self.workdir / f"{device}.toml"
            gateway_config(cfg, device, port, self.router)
            proc = subprocess.Popen([sys.executable, "-m", "skinmap.daemon.service", "--config",
                                     str(cfg)], stdin=subprocess.DEVNULL,
                                    stdout=subprocess.DEVNULL,
                                    stderr=open(self.workdir / f"{device}.err", "wb"))
            self.procs.append(proc)
            st.callback(stop_process, proc, 30.0)
        self.session = st.enter_context(open_session(
            make_session_config([], [self.router], mode="client")))
        for i in range(self.n_subscribers):
            # One client session per subscriber, on every device's elements; each message is
            # checked as the light client checks it.
            session = st.enter_context(open_session(
                make_session_config([], [self.router], mode="client")))
            sub = session.declare_subscriber(f"{PREFIX}/*/elements",
                                             lambda sample, s=self.stats[i]: _receive(s, sample))
            st.callback(sub.undeclare)

    def wait_streaming(self, timeout: float = 90.0) -> None:
        """Until every subscriber has elements from every device."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if all(len(s.seqs.get(d, ())) >= 3 for s in self.stats for d in self.devices):
                return
            for proc in self.procs:
                if proc.poll() is not None:
                    raise RuntimeError(f"a gateway exited with {proc.returncode}: "
                                       + self._errors())
            time.sleep(0.2)
        raise TimeoutError("not every subscriber receives every device: " + self._errors())

    def _errors(self) -> str:
        return " | ".join((self.workdir / f"{d}.err").read_text(errors="replace")[-400:]
                          for d in self.devices)

    def discover(self) -> list[str]:
        return discover(self.session, PREFIX, timeout=2.0)

    def record(self, seconds: float) -> Recorder:
        with Recorder(self.session, PREFIX, ["*"], self.record_dir) as rec:
            time.sleep(seconds)
        self.recorder = rec
        return rec

    def __exit__(self, *_exc: object) -> None:
        self._stack.close()

    def gateway_logged_seqs(self, device: str) -> list[int]:
        """Elements seqs in the gateway's own log (after it stopped)."""
        seqs = []
        for path in sorted((self.workdir / f"logs-{device}").glob("*.mcap")):
            for m in iter_messages_file_order(path):
                if m.topic == "/elements":
                    seqs.append(wire.decode_header(m.data).seq)
        return seqs


def recorded(path_dir: Path) -> dict[str, list[bytes]]:
    out: dict[str, list[bytes]] = {}
    for path in sorted(path_dir.glob("*.mcap")):
        for m in iter_messages_file_order(path):
            out.setdefault(m.topic, []).append(m.data)
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--size", default="3x3")
    args = ap.parse_args()
    from threadpoolctl import threadpool_limits

    threadpool_limits(1)
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        with Fleet(work, size=args.size) as fleet:
            fleet.wait_streaming()
            found = fleet.discover()
            for s in fleet.stats:  # measure from here on
                s.seqs.clear()
                s.latency_ms.clear()
            rec = fleet.record(args.seconds)
            stats = fleet.stats
        lat = np.concatenate([np.asarray(s.latency_ms) for s in stats])
        print(f"fleet: {len(fleet.devices)} gateways ({args.size}, {SCAN_HZ:g} scans/s, "
              f"{OUTPUT_HZ:g} Hz out), 1 router, 1 recorder, {len(stats)} subscribers, "
              f"{args.seconds:g} s; discovered {found}")
        print(f"FIGURE fleet latency (gateway receive -> subscriber via router): p50 "
              f"{np.percentile(lat, 50):.1f} ms, p95 {np.percentile(lat, 95):.1f} ms, p99 "
              f"{np.percentile(lat, 99):.1f} ms, max {lat.max():.1f} ms over {lat.size} messages")
        # Lost: published by the gateway (its own log holds every published elements message)
        # within the subscriber's window and never received. Skipped: seq steps beyond the
        # decimation that the gateway itself never published (a busy reconstruction).
        logged = {d: fleet.gateway_logged_seqs(d) for d in fleet.devices}
        lost, expected = [], []
        for s in stats:
            n_lost = n_expected = 0
            for d in fleet.devices:
                got = set(s.seqs.get(d, []))
                if got:
                    window = {q for q in logged[d] if min(got) <= q <= max(got)}
                    n_lost += len(window - got)
                    n_expected += len(window)
            lost.append(n_lost)
            expected.append(n_expected)
        skipped = sum(missing_at_step(logged[d], EXPECTED_STEP) for d in fleet.devices)
        print(f"FIGURE fleet loss through the router: per subscriber {lost} of {expected} published "
              f"elements messages not received; nan in VALID elements {sum(s.nan_in_valid for s in stats)}; "
              f"rejected {sum(s.rejected for s in stats)} (scans the gateways skipped before publishing: "
              f"{skipped} over their whole run)")
        for device in fleet.devices:
            rec_seqs = [wire.decode_header(p).seq for p in
                        recorded(fleet.record_dir).get(f"/{device}/elements", [])]
            logged = fleet.gateway_logged_seqs(device)
            if not rec_seqs:
                print(f"FIGURE fleet recording {device}: nothing recorded")
                continue
            lo, hi = min(rec_seqs), max(rec_seqs)
            window = {s for s in logged if lo <= s <= hi}
            share = len(window & set(rec_seqs)) / len(window) if window else float("nan")
            print(f"FIGURE fleet recording {device}: {len(set(rec_seqs))} of {len(window)} elements "
                  f"messages the gateway logged in the window ({100 * share:.2f} %); recorder "
                  f"dropped {rec.dropped}, rejected {rec.counts.get(device).rejected if device in rec.counts else 0}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
