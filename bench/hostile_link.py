"""Hostile-scanner scenarios against the real gateway and the emulated scanner, on loopback.

Each scenario starts the emulator (5×5, pseudo-terminal; a shared TCP socket for the two-host
case), an in-process skinmapd Gateway publishing over Zenoh on tcp/127.0.0.1 (multicast off),
turns on one of the emulator's hostile modes (or injects the fault), samples the gateway's
status every 50 ms and prints one line: what the link counted, the share of status samples
that were healthy, the first warning, and the time from the end of the fault to the next
scan processed. It measures; it asserts nothing.

    .venv/bin/python bench/hostile_link.py               # every scenario
    .venv/bin/python bench/hostile_link.py --only storm  # scenarios whose name contains "storm"
"""
from __future__ import annotations

import argparse
import logging
import socket
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any, Callable

from skinmap.daemon.config import parse_config
from skinmap.daemon.service import Gateway, open_zenoh, zenoh_publishers
from skinmap.emulator.device import ScannerSpec
from skinmap.emulator.emulator import Emulator
from skinmap.emulator.physics import make_shape
from skinmap.emulator.transport import PtyTransport, SharedTcpTransport, TcpTransport
from skinmap.protocol import Start, encode_frame

RATE_HZ = 40.0
FAULT_S = 4.0
SAMPLE_S = 0.05
LINK_KEYS = ("scans_lost", "reboots", "handshake_failures", "reconnects", "stalls")
EXTRA_KEYS = ("unknown_frames", "scans_dropped_by_device", "scans_repeated_index", "scans_wrong_size",
              "index_resyncs", "unsolicited_hellos", "foreign_answers", "rate_mismatches")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class EventCount(logging.Handler):
    """Counts the gateway's log lines (its /log events) that contain a word."""

    def __init__(self) -> None:
        super().__init__(logging.INFO)
        self.lines: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(record.getMessage())

    def count(self, word: str) -> int:
        return sum(word in line for line in self.lines)


def config(port: str, tmp: Path, name: str, **device: Any):
    return parse_config({
        "device": {"port": port, "name": name, "scan_rate_hz": RATE_HZ, "stall_timeout_s": 0.5,
                   "handshake_timeout_s": 0.6, "reconnect_min_s": 0.05, "reconnect_max_s": 0.3, **device},
        "output": {"rate_hz": 10, "status_rate_hz": 4},
        "zenoh": {"listen": [f"tcp/127.0.0.1:{free_port()}"]},
        "log": {"enabled": False},
        "state": {"directory": str(tmp / f"state-{name}")},
    }, source=str(tmp / "skinmapd.toml"), text="")


class Running:
    """A Gateway in a thread with its own Zenoh session."""

    def __init__(self, cfg: Any) -> None:
        self._zcm = open_zenoh(cfg)
        self.gw = Gateway(cfg, publishers=zenoh_publishers(cfg, self._zcm.__enter__()))
        self.thread = threading.Thread(target=self.gw.run, daemon=True)
        self.thread.start()

    def close(self) -> None:
        self.gw.stop()
        self.thread.join(timeout=20)
        self._zcm.__exit__(None, None, None)


def wait(pred: Callable[[], bool], timeout: float) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(0.02)
    return pred()


def snapshot(gw: Gateway) -> dict[str, int]:
    st = gw.status()
    out = {k: int(st[k]) for k in LINK_KEYS}
    out.update({k: int(st["decoder"].get(k, 0)) for k in EXTRA_KEYS})
    out["scans_in"] = int(st["scans_in"])
    return out


def observe(gws: list[Gateway], seconds: float) -> tuple[list[float], list[str]]:
    """Healthy share of status samples per gateway, and the distinct warnings seen."""
    healthy = [0] * len(gws)
    samples = 0
    warnings: list[str] = []
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        for i, gw in enumerate(gws):
            st = gw.status()
            healthy[i] += bool(st["healthy"])
            for w in st["warnings"]:
                if w not in warnings:
                    warnings.append(w)
        samples += 1
        time.sleep(SAMPLE_S)
    return [h / max(samples, 1) for h in healthy], warnings


def delta(before: dict[str, int], after: dict[str, int]) -> str:
    return " ".join(f"{k}+{after[k] - before[k]}" for k in after if after[k] != before[k]) or "no counter moved"


def recovery(gw: Gateway, t_end: float, timeout: float = 10.0) -> str:
    """Time from the end of the fault to scans processed again, and to a healthy status."""
    n = gw.stats.scans_in
    if not wait(lambda: gw.stats.scans_in > n + 2, timeout):
        return f"no scans within {timeout:g} s"
    scans = time.monotonic() - t_end
    if not wait(lambda: gw.status()["healthy"], timeout):
        return f"scans after {scans:.2f} s, not healthy within {timeout:g} s ({short(gw.status()['warnings'], 2)})"
    return f"scans after {scans:.2f} s, healthy after {time.monotonic() - t_end:.2f} s"


def reboot(emu: Emulator) -> None:
    """A reboot that is not a watchdog reset (WATCHDOG_RESET would stay reported until the next one)."""
    with emu._lock:
        emu.device.reboot(emu.clock(), watchdog=False)


def line(name: str, text: str) -> None:
    print(f"{name:<28} {text}", flush=True)


def short(warnings: list[str], n: int = 1) -> str:
    return " | ".join(w[:150] for w in warnings[:n]) or "-"


# ---------------------------------------------------------------------------------------------


def pty_emulator(tmp: Path, rate_hz: float = RATE_HZ) -> tuple[Emulator, str]:
    link = tmp / "ttySKIN0"
    emu = Emulator(ScannerSpec(n=5, m=5, scan_rate_hz=rate_hz, seed=5), make_shape("flat"), PtyTransport(link=link))
    return emu, str(link)


def hostile_mode(name: str, events: EventCount, word: str, setup: Callable[[Emulator], None],
                 teardown: Callable[[Emulator], None], *, before_start: bool = False) -> None:
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        emu, port = pty_emulator(tmp)
        emu.open()
        if before_start:
            setup(emu)
        emu.start()
        run = Running(config(port, tmp, "hostile"))
        try:
            if not before_start:
                wait(lambda: run.gw.stats.scans_in >= 10, 20.0)
            before = snapshot(run.gw)
            sent0 = emu.device.scans_sent
            events.lines.clear()
            if not before_start:
                setup(emu)
            share, warnings = observe([run.gw], FAULT_S)
            teardown(emu)
            t_end = time.monotonic()
            after = snapshot(run.gw)
            sent = emu.device.scans_sent - sent0
            rec = recovery(run.gw, t_end) if not before_start else "-"
            line(name, f"healthy {share[0]:.0%} of samples; {delta(before, after)}; device sent {sent} scans, "
                       f"gateway took {after['scans_in'] - before['scans_in']}; {events.count(word)} '{word}' log "
                       f"line(s); recovery {rec}; warning: {short(warnings)}")
        finally:
            run.close()
            emu.stop()


def scenario_refused(name: str, events: EventCount, **hostile: Any) -> None:
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        emu, port = pty_emulator(tmp)
        emu.open()
        for k, v in hostile.items():
            setattr(emu.device.hostile, k, v)
        emu.device.on_bytes(encode_frame(Start(9), 0), emu.clock())  # left scanning by an earlier host
        emu.start()
        run = Running(config(port, tmp, "refused"))
        try:
            share, warnings = observe([run.gw], 8.0)
            st = run.gw.status()
            opens = events.count("opened ")
            line(name, f"healthy {share[0]:.0%}; handshake_failures {st['handshake_failures']}, port opened {opens}× "
                       f"in 8 s (last backoff {run.gw.link.stats.backoff_s:g} s); device {emu.device.state.name} "
                       f"after refusal; scans_in {st['scans_in']}; error: {st['last_link_error'][:140]}")
        finally:
            run.close()
            emu.stop()


def scenario_lost_boot_hello(events: EventCount) -> None:
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        emu, port = pty_emulator(tmp, rate_hz=10.0)  # the device boots at 10 scans/s; configured 40
        emu.start()
        run = Running(config(port, tmp, "boothello"))
        try:
            wait(lambda: run.gw.stats.scans_in >= 10, 20.0)
            before = snapshot(run.gw)
            emu.device.hostile.lose_boot_hello = True
            reboot(emu)
            t0 = time.monotonic()
            rec = recovery(run.gw, t0)
            share, _ = observe([run.gw], 3.0)
            st = run.gw.status()
            line("lost boot HELLO + reboot", f"device now {emu.device.scan_rate_mhz / 1000:g} scans/s (configured "
                                             f"{RATE_HZ:g}, boot default 10); status scan_rate_hz {st['scan_rate_hz']}; "
                                             f"{delta(before, snapshot(run.gw))}; {rec}; "
                                             f"healthy {share[0]:.0%} in the 3 s after")
        finally:
            run.close()
            emu.stop()


def scenario_reboot_storm(events: EventCount) -> None:
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        emu, port = pty_emulator(tmp)
        emu.start()
        run = Running(config(port, tmp, "rebootstorm"))
        try:
            wait(lambda: run.gw.stats.scans_in >= 10, 20.0)
            before = snapshot(run.gw)
            stop = threading.Event()

            def storm() -> None:
                while not stop.wait(0.02):  # 50 reboots/s, each a HELLO with seq 0
                    reboot(emu)

            t = threading.Thread(target=storm, daemon=True)
            t.start()
            share, warnings = observe([run.gw], FAULT_S)
            stop.set()
            t.join()
            t_end = time.monotonic()
            rec = recovery(run.gw, t_end, 20.0)
            line("reboot storm 50/s", f"healthy {share[0]:.0%}; {delta(before, snapshot(run.gw))}; "
                                      f"{events.count('HELLO storm')} 'HELLO storm' log line(s); recovery {rec}; "
                                      f"warning: {short([w for w in warnings if 'storm' in w] or warnings)}")
        finally:
            run.close()
            emu.stop()


def scenario_lost_start_ack(events: EventCount) -> None:
    def setup(emu: Emulator) -> None:
        emu.device.hostile.lose_start_acks = 1
        reboot(emu)

    hostile_mode("lost START ACK after reboot", events, "rebooted", setup, lambda emu: None)


def scenario_two_hosts(events: EventCount) -> None:
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        transport = SharedTcpTransport()
        emu = Emulator(ScannerSpec(n=5, m=5, scan_rate_hz=RATE_HZ, seed=5), make_shape("flat"), transport)
        emu.start()
        first = Running(config(transport.url, tmp, "first"))
        try:
            wait(lambda: first.gw.stats.scans_in >= 10, 20.0)
            n0 = first.gw.stats.scans_in
            t0 = time.monotonic()
            second = Running(config(transport.url, tmp, "second", scan_rate_hz=10.0))
            try:
                share, warnings = observe([first.gw, second.gw], 6.0)
                dt = time.monotonic() - t0
                rate1 = (first.gw.stats.scans_in - n0) / dt
                st1, st2 = first.gw.status(), second.gw.status()
                line("second host, shared socket",
                     f"healthy first {share[0]:.0%} / second {share[1]:.0%}; first took {rate1:.1f} scans/s "
                     f"(configured {RATE_HZ:g}, second asks 10); foreign_answers "
                     f"{st1['decoder']['foreign_answers']}/{st2['decoder']['foreign_answers']}; "
                     f"link_state {st1['link_state']}/{st2['link_state']}; warning: {short(warnings)}")
            finally:
                second.close()
            t_end = time.monotonic()
            rec = recovery(first.gw, t_end, 15.0)
            line("  ... second host leaves", f"first: {rec}")
        finally:
            first.close()
            emu.stop()


def scenario_two_hosts_replacing(events: EventCount) -> None:
    """The emulator's ordinary TCP server: a new client replaces the old one (and powers the
    scanner up afresh), so two hosts take the port from each other in turn."""
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        transport = TcpTransport()
        emu = Emulator(ScannerSpec(n=5, m=5, scan_rate_hz=RATE_HZ, seed=5), make_shape("flat"), transport)
        emu.start()
        first = Running(config(transport.url, tmp, "first"))
        try:
            wait(lambda: first.gw.stats.scans_in >= 10, 20.0)
            n0 = first.gw.stats.scans_in
            t0 = time.monotonic()
            second = Running(config(transport.url, tmp, "second"))
            try:
                share, warnings = observe([first.gw, second.gw], 10.0)
                dt = time.monotonic() - t0
                rate1 = (first.gw.stats.scans_in - n0) / dt
                st1, st2 = first.gw.status(), second.gw.status()
                line("second host, TCP replacing",
                     f"healthy first {share[0]:.0%} / second {share[1]:.0%}; first took {rate1:.1f} scans/s "
                     f"(configured {RATE_HZ:g}); reconnects {st1['reconnects']}/{st2['reconnects']}; "
                     f"warning: {short([w for w in warnings if 'unstable' in w] or warnings)}")
            finally:
                second.close()
            rec = recovery(first.gw, time.monotonic(), 20.0)
            line("  ... second host leaves", f"first: {rec}")
        finally:
            first.close()
            emu.stop()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", default="", help="run only scenarios whose name contains this")
    args = ap.parse_args()
    events = EventCount()
    logging.getLogger().addHandler(events)
    logging.getLogger().setLevel(logging.INFO)
    for noisy in ("zenoh", "skinmap.reconstruction"):
        logging.getLogger(noisy).setLevel(logging.WARNING)

    def set_(**kw: Any) -> Callable[[Emulator], None]:
        return lambda emu: [setattr(emu.device.hostile, k, v) for k, v in kw.items()]

    scenarios: list[tuple[str, Callable[[], None]]] = [
        ("gauge length 0", lambda: scenario_refused("gauge length 0", events, hello_gauge_length_um=0)),
        ("gauge length 20 mm > pitch", lambda: scenario_refused("gauge length 20 mm > pitch", events,
                                                                hello_gauge_length_um=20_000)),
        ("major version 2", lambda: scenario_refused("major version 2", events, hello_protocol_major=2)),
        ("lost boot HELLO", lambda: scenario_lost_boot_hello(events)),
        ("repeated sample index", lambda: hostile_mode("repeated sample index", events, "repeated",
                                                       set_(repeat_sample_index=True), set_(repeat_sample_index=False))),
        ("index jump 0x7FFFFF00", lambda: hostile_mode("index jump 0x7FFFFF00", events, "resynchronised",
                                                       set_(index_jump=0x7FFFFF00), lambda emu: None)),
        ("scan size 6x6", lambda: hostile_mode("scan size 6x6 vs HELLO 5x5", events, "scan size",
                                               set_(scan_dims=(6, 6)), set_(scan_dims=None))),
        ("vendor frames", lambda: hostile_mode("vendor frames 50/s", events, "unknown type",
                                               set_(vendor_frame_hz=50.0), set_(vendor_frame_hz=0.0))),
        ("device drops", lambda: hostile_mode("device drops every 4th scan", events, "lost",
                                              set_(drop_every=4), set_(drop_every=0))),
        ("lost START ACK", lambda: scenario_lost_start_ack(events)),
        ("HELLO storm", lambda: hostile_mode("HELLO storm 50/s (no reboot)", events, "unsolicited HELLO",
                                             set_(hello_storm_hz=50.0), set_(hello_storm_hz=0.0))),
        ("reboot storm", lambda: scenario_reboot_storm(events)),
        ("two hosts shared", lambda: scenario_two_hosts(events)),
        ("two hosts replacing", lambda: scenario_two_hosts_replacing(events)),
    ]
    for name, run in scenarios:
        if args.only.lower() in name.lower():
            events.lines.clear()
            try:
                run()
            except Exception as exc:  # noqa: BLE001 - report and go on with the next scenario
                line(name, f"scenario failed: {type(exc).__name__}: {exc}")
    sys.stdout.flush()


if __name__ == "__main__":
    main()
