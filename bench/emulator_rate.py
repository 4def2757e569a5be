"""Highest sustained scan rate of the emulator: scans/s requested vs actually delivered.

Runs `skinmap-emulator` as a separate process on a pseudo-terminal (as it is used), asks for
increasing scan rates with SET_SCAN_RATE, reads for a fixed window with pyserial and the
protocol's StreamDecoder, and prints one table row per (array size, requested rate):
delivered scans/s, the device's acquisition rate (sample_index span, which also counts scans the
device dropped), and the share of scans lost.

    .venv/bin/python bench/emulator_rate.py            # 5x5, 16x16, 32x32, static shape
    .venv/bin/python bench/emulator_rate.py --shape palm --window 2
    .venv/bin/python bench/emulator_rate.py --mechanics elastic --shape membrane --sizes 5x5

With ``--mechanics elastic`` the scene is solved (or loaded from the solve cache) before the
first rate is measured; a moving elastic scene streams from its key frames (per-gauge monotone
cubic interpolation in time), which is what is measured.
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import serial

from skinmap import protocol as p

SIZES = ((5, 5), (16, 16), (32, 32))
RATES = (10, 50, 100, 200, 500, 1000, 2000, 5000)
STEP_LIMIT = 400_000.0  # lift the DAQ limit so the emulator itself is what is measured


def measure(port: serial.Serial, rate_hz: float, window_s: float, rid: int) -> tuple[float, float, int] | None:
    """(delivered/s, acquired/s, scans lost) over the window; None if the rate is refused."""
    dec = p.StreamDecoder()
    seq = 0

    def send(msg) -> None:
        nonlocal seq
        port.write(p.encode_frame(msg, seq))
        seq += 1

    def wait_ack(request_id: int) -> p.Frame:
        end = time.monotonic() + 3.0
        while time.monotonic() < end:
            for f in dec.feed(port.read(port.in_waiting or 1)):
                if f.msg_type in (p.MsgType.ACK, p.MsgType.NAK) and f.msg.request_id == request_id:
                    return f
        raise RuntimeError(f"no answer to request {request_id}")

    send(p.Stop(rid))
    wait_ack(rid)
    send(p.SetScanRate(rid + 1, int(round(rate_hz * 1000))))
    if wait_ack(rid + 1).msg_type == p.MsgType.NAK:
        return None
    port.reset_input_buffer()
    send(p.Start(rid + 2))
    first = last = None
    count = 0
    t_first = t_last = None
    end = time.monotonic() + window_s
    while time.monotonic() < end:
        for f in dec.feed(port.read(port.in_waiting or 1)):
            if f.msg_type != p.MsgType.SCAN:
                continue
            if first is None:
                first, t_first = f.msg.sample_index, time.monotonic()
                continue  # the window starts at the first scan
            last, t_last = f.msg.sample_index, time.monotonic()
            count += 1
    if last is None or t_last <= t_first:
        return 0.0, 0.0, 0
    elapsed = t_last - t_first
    return count / elapsed, (last - first) / elapsed, (last - first) - count


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--shape", default="gaussian:height=4,fwhm=18,u0=3,v0=-2")
    ap.add_argument("--window", type=float, default=1.5, help="seconds measured per rate")
    ap.add_argument("--rates", type=float, nargs="*", default=RATES)
    ap.add_argument("--mechanics", choices=("kinematic", "elastic"), default="kinematic")
    ap.add_argument("--sizes", default=",".join(f"{n}x{m}" for n, m in SIZES),
                    help="arrays to measure, e.g. 5x5,16x16")
    args = ap.parse_args()
    sizes = [tuple(int(v) for v in s.lower().split("x")) for s in args.sizes.split(",")]

    print(f"emulator scan rate over a pty, shape {args.shape!r} ({args.mechanics}), {args.window:g} s per point, "
          "full electrical model (noise, hysteresis, drift, ADC)")
    print(f"{'array':>6} {'requested/s':>12} {'delivered/s':>12} {'acquired/s':>11} {'lost':>6} {'MB/s':>7}")
    for n, m in sizes:
        with tempfile.TemporaryDirectory() as tmp:
            link = Path(tmp) / "tty"
            proc = subprocess.Popen(
                [sys.executable, "-m", "skinmap.emulator.command", "--size", f"{n}x{m}", "--shape", args.shape,
                 "--link", str(link), "--max-step-rate", str(STEP_LIMIT), "--status-every", "0",
                 "--mechanics", args.mechanics],
                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
            )
            try:
                while "serving" not in (line := proc.stdout.readline()):
                    if not line:
                        raise RuntimeError(f"the emulator exited: {proc.stderr.read()}")
                best = 0.0
                with serial.Serial(str(link), timeout=0.02) as port:
                    for k, rate in enumerate(args.rates):
                        result = measure(port, rate, args.window, 10 * k + 1)
                        if result is None:
                            print(f"{n:>3}x{m:<2} {rate:>12g}   refused (above max_scan_rate)")
                            break
                        delivered, acquired, lost = result
                        mbps = delivered * (p.Scan.payload_size(n, m) + 13) / 1e6
                        print(f"{n:>3}x{m:<2} {rate:>12g} {delivered:>12.1f} {acquired:>11.1f} "
                              f"{lost:>6d} {mbps:>7.2f}", flush=True)
                        if delivered >= 0.98 * rate and lost <= 0.005 * acquired * args.window:
                            best = rate
                        elif delivered < 0.5 * rate:
                            break  # far beyond what it sustains
                print(f"{n:>3}x{m:<2} highest sustained rate tried: {best:g} scans/s", flush=True)
            finally:
                proc.terminate()
                proc.wait(timeout=10)


if __name__ == "__main__":
    main()
