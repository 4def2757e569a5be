"""End-to-end figures of skinmapd against the emulator, all on loopback.

For each array size and output mode it starts the emulator and skinmapd as separate processes,
subscribes to the element messages over Zenoh, and prints:

- latency (after a 3 s warm-up) from the host receiving a scan's last byte on the serial port (the element message's
  host time stamp) to this subscriber holding the decoded element coordinates: median, p99;
- the daemon's CPU use (share of one core) and resident memory, from /proc;
- MCAP bytes per hour, from the log folder's growth.

    .venv/bin/python bench/latency.py [--seconds 20] [--sizes 5x5,16x16]
"""
from __future__ import annotations

import argparse
import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from skinmap.daemon.cli import start_emulator, stop_process
from skinmap.client import SkinmapClient


WARM_UP_S = 3.0


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def proc_cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def proc_rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def dir_bytes(path: Path) -> int:
    return sum(p.stat().st_size for p in path.glob("*") if p.is_file())


def write_daemon_config(path: Path, *, device: str, serial_port: int, zenoh_port: int, logs: Path, state: Path,
                        scan_rate: float, output_rate: float, rotate_minutes: float = 60.0,
                        rotate_mb: float = 256.0) -> None:
    """A skinmapd config for the benchmarks: emulator on loopback TCP, 64 elements in a row."""
    path.write_text(f"""
[device]
port = "socket://127.0.0.1:{serial_port}"
name = "{device}"
scan_rate_hz = {scan_rate}
[output]
rate_hz = {output_rate}
[elements]
layout = "grid"
rows = 1
cols = 64
pitch_u_mm = 0.6
[zenoh]
listen = ["tcp/127.0.0.1:{zenoh_port}"]
[log]
directory = "{logs}"
max_file_minutes = {rotate_minutes}
max_file_mb = {rotate_mb}
[state]
directory = "{state}"
""")


def run_case(size: str, scan_rate: float, output_rate: float, seconds: float, workdir: Path,
             shape: str = "palm") -> dict:
    serial_port, zenoh_port = free_port(), free_port()
    logs = workdir / f"logs-{size}-{output_rate:g}"
    cfg = workdir / f"bench-{size}-{output_rate:g}.toml"
    write_daemon_config(cfg, device="bench", serial_port=serial_port, zenoh_port=zenoh_port, logs=logs,
                        state=workdir / "state", scan_rate=scan_rate, output_rate=output_rate)
    emulator = start_emulator(serial_port, size=size, shape=shape, rate=scan_rate)
    daemon = subprocess.Popen([sys.executable, "-m", "skinmap.daemon.service", "--config", str(cfg)],
                              stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    latencies: list[float] = []
    try:
        with SkinmapClient([f"tcp/127.0.0.1:{zenoh_port}"], prefix="skinmap", device="bench") as client:
            client.elements(timeout=60.0)  # wait until the daemon streams
            # Steady state only: the first seconds build per-geometry caches (factorisations,
            # uncertainty responses) and are not representative of a running service.
            warm_end = time.monotonic() + WARM_UP_S
            while time.monotonic() < warm_end:
                client.elements(timeout=10.0)
            cpu0, t0, bytes0 = proc_cpu_seconds(daemon.pid), time.monotonic(), dir_bytes(logs)
            end = t0 + seconds
            while time.monotonic() < end:
                msg = client.elements(timeout=5.0)
                latencies.append((time.time_ns() - msg.host_time_ns) / 1e6)
            elapsed = time.monotonic() - t0
            cpu = (proc_cpu_seconds(daemon.pid) - cpu0) / elapsed
            rss = proc_rss_mb(daemon.pid)
            mcap_rate = (dir_bytes(logs) - bytes0) / elapsed * 3600
    finally:
        stop_process(daemon, timeout=15)
        stop_process(emulator)
    lat = np.array(latencies)
    return {"size": size, "scan_rate": scan_rate, "output": "every scan" if output_rate == 0 else f"{output_rate:g} Hz",
            "n": lat.size, "rate": lat.size / elapsed, "median": float(np.median(lat)), "p99": float(np.percentile(lat, 99)),
            "cpu": cpu * 100, "rss": rss, "mcap_gb_h": mcap_rate / 1e9}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--sizes", default="5x5,16x16")
    ap.add_argument("--scan-rate", type=float, default=50.0, help="emulated scans per second")
    ap.add_argument("--shape", default="palm", help="emulated shape spec (default: the moving palm gesture)")
    ap.add_argument("--outputs", default="10,0", help="output rates to measure, Hz (0 = every scan)")
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for size in args.sizes.split(","):
            for output_rate in (float(x) for x in args.outputs.split(",")):
                try:
                    rows.append(run_case(size, args.scan_rate, output_rate, args.seconds, Path(tmp), args.shape))
                except Exception as exc:  # noqa: BLE001 - report the case and go on with the others
                    print(f"{size} output {output_rate:g} Hz: FAILED: {exc}", flush=True)
                    continue
                r = rows[-1]
                print(f"{r['size']:>6} scan {r['scan_rate']:g}/s output {r['output']:>10}: {r['n']} msgs "
                      f"({r['rate']:.1f}/s)  latency median {r['median']:.2f} ms  p99 {r['p99']:.2f} ms  "
                      f"CPU {r['cpu']:.1f} %  RSS {r['rss']:.0f} MB  MCAP {r['mcap_gb_h']:.2f} GB/h", flush=True)
    print()
    print("| array | scans/s | output | messages | latency median ms | latency p99 ms | daemon CPU % | RSS MB | MCAP GB/h |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['size']} | {r['scan_rate']:g} | {r['output']} | {r['n']} | {r['median']:.2f} | {r['p99']:.2f} | "
              f"{r['cpu']:.1f} | {r['rss']:.0f} | {r['mcap_gb_h']:.2f} |")


if __name__ == "__main__":
    main()
