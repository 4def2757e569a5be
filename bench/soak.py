"""Soak: skinmapd against the emulator at full scan rate for a long time, all on loopback.

Starts the emulator (TCP on 127.0.0.1) and skinmapd as separate processes, skinmapd publishing
every scan and logging to MCAP with rotation, subscribes to the element messages over Zenoh,
and after ``--seconds`` (an hour by default) stops both and reports:

- memory of the daemon: resident set at start (first message) and end, the maximum, and the
  growth rate in MB/h from a least-squares fit over the run and over its second half;
- dropped scans: the daemon's own counters from its last status report (scans lost on the
  link, dropped by the processing queue, log messages dropped) and the sequence gaps this
  subscriber saw;
- latency drift: scan received by the daemon (element host time stamp) to element message
  decoded here, median and p99 in the first and in the last 10 % of the run;
- file integrity: every MCAP file in the log folder read to its end with
  `skinmap.daemon.mcapinspect.inspect` (finished or not, counts per topic, sequence gaps), and
  one finished file replayed through the pipeline with `skinmap.daemon.replay.replay_log`
  (IDENTICAL when every re-computed element message matches the logged one bit for bit).

A progress line is printed every ``--progress-every`` seconds (a minute by default).

    .venv/bin/python bench/soak.py                       # one hour
    .venv/bin/python bench/soak.py --seconds 60 --json soak.json

Exit code 0 when the run completed with every file readable and the replay identical, 1
otherwise (the figures are printed either way).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from latency import free_port, proc_cpu_seconds, proc_rss_mb, write_daemon_config  # bench/latency.py
from skinmap.daemon.cli import start_emulator, stop_process
from skinmap.client import SkinmapClient

DEVICE = "soak"


# ---------------------------------------------------------------------------------------------
# pure summaries


def growth_mb_per_hour(t_s: np.ndarray, rss_mb: np.ndarray) -> float:
    """Least-squares slope of RSS over time, MB per hour (nan with fewer than 2 samples)."""
    t_s, rss_mb = np.asarray(t_s, float), np.asarray(rss_mb, float)
    if t_s.size < 2 or np.ptp(t_s) <= 0:
        return float("nan")
    return float(np.polyfit(t_s, rss_mb, 1)[0] * 3600.0)


def window_stats(values_ms: np.ndarray) -> dict[str, float]:
    values_ms = np.asarray(values_ms, float)
    if values_ms.size == 0:
        return {"n": 0, "median_ms": float("nan"), "p99_ms": float("nan")}
    return {"n": int(values_ms.size), "median_ms": float(np.median(values_ms)),
            "p99_ms": float(np.percentile(values_ms, 99))}


def latency_drift(t_s: np.ndarray, latency_ms: np.ndarray, share: float = 0.1) -> dict[str, Any]:
    """Latency statistics of the first and the last ``share`` of the run (by time)."""
    if not 0 < share <= 0.5:
        raise ValueError(f"share must be in (0, 0.5], got {share!r}")
    t_s, latency_ms = np.asarray(t_s, float), np.asarray(latency_ms, float)
    if t_s.size == 0:
        return {"first": window_stats(latency_ms), "last": window_stats(latency_ms)}
    span = t_s[-1] - t_s[0]
    first = latency_ms[t_s <= t_s[0] + share * span]
    last = latency_ms[t_s >= t_s[-1] - share * span]
    return {"first": window_stats(first), "last": window_stats(last)}


def sequence_gaps(seqs: np.ndarray) -> int:
    """Scans missing between consecutive received sequence numbers (u32 wrap-around)."""
    seqs = np.asarray(seqs, dtype=np.int64)
    if seqs.size < 2:
        return 0
    steps = np.diff(seqs) % 2**32
    return int(np.sum(steps[(steps > 1) & (steps < 2**31)] - 1))


def source_fingerprint() -> str:
    """Hash of the skinmap sources the daemon runs, so a replay can tell whether the code it
    re-runs is the code that wrote the log (a DIFFERENT verdict is expected otherwise)."""
    import hashlib
    import importlib

    digest = hashlib.sha256()
    for name in ("skinmap", "skinmap.protocol", "skinmap.reconstruction", "skinmap.daemon"):
        for folder in importlib.import_module(name).__path__:
            for path in sorted(Path(folder).glob("*.py")):
                digest.update(path.name.encode() + path.read_bytes())
    return digest.hexdigest()[:16]


# ---------------------------------------------------------------------------------------------
# the run


@dataclass
class SoakResult:
    seconds: float
    size: str
    scan_rate_hz: float
    messages: int = 0
    message_rate_hz: float = 0.0
    subscriber_gaps: int = 0
    rss_start_mb: float = float("nan")
    rss_end_mb: float = float("nan")
    rss_max_mb: float = float("nan")
    rss_growth_mb_h: float = float("nan")
    rss_growth_second_half_mb_h: float = float("nan")
    daemon_cpu_percent: float = float("nan")
    load_average: list[float] = field(default_factory=list)  # 1-min load, start and end
    latency: dict[str, Any] = field(default_factory=dict)
    status: dict[str, Any] = field(default_factory=dict)
    daemon_exit_code: int | None = None
    files: list[dict[str, Any]] = field(default_factory=list)
    replay: dict[str, Any] = field(default_factory=dict)
    problems: list[str] = field(default_factory=list)
    source_at_start: str = ""

    @property
    def ok(self) -> bool:
        return not self.problems


def check_files(logs: Path, result: SoakResult, replay: bool) -> None:
    """Read every MCAP file in ``logs``; replay one finished file (``replay``)."""
    from skinmap.daemon.mcapinspect import inspect
    from skinmap.daemon.replay import replay_log
    from skinmap.daemon.gateway import limit_blas_threads

    # The daemon solves with one BLAS thread; a multi-threaded BLAS sums in another order and
    # the replay would differ in the last bits. Must run before this process's first solve.
    limit_blas_threads()

    paths = sorted(p for p in logs.iterdir() if p.name.endswith((".mcap", ".mcap.active")))
    if not paths:
        result.problems.append(f"no MCAP files in {logs}")
    finished = []
    for path in paths:
        entry: dict[str, Any] = {"file": path.name, "bytes": path.stat().st_size}
        try:
            report = inspect(path)
        except Exception as exc:  # noqa: BLE001 - any failure to read is the finding
            entry.update(readable=False, error=f"{type(exc).__name__}: {exc}")
            result.problems.append(f"{path.name} unreadable: {exc}")
        else:
            entry.update(readable=True, finished=report.end.complete, end=report.end.reason,
                         counts={t: s.count for t, s in sorted(report.topics.items())},
                         errors=sum(1 for i in report.issues if i.level == "error"))
            if not report.end.complete:
                result.problems.append(f"{path.name} not finished: {report.end.reason}")
            elif report.topics.get("/raw") is not None:
                finished.append((path, report.topics["/raw"].count))
        result.files.append(entry)
    if replay and finished:
        # The smallest file (bounded replay time) with room for a few restarts of the graph fit
        # (the scans before the first restart in a file are not comparable), else the largest.
        from skinmap.daemon.pipeline import GRAPH_RESTART_SCANS

        roomy = [path for path, raw in finished if raw >= 4 * GRAPH_RESTART_SCANS]
        target = (min(roomy, key=lambda p: p.stat().st_size) if roomy
                  else max((path for path, _ in finished), key=lambda p: p.stat().st_size))
        t0 = time.monotonic()
        rep = replay_log(target)
        same_code = source_fingerprint() == result.source_at_start
        result.replay = {"file": target.name, "identical": rep.identical, "compared": rep.compared,
                         "not_comparable": rep.unsynced,
                         "mismatched": len(rep.mismatched), "seconds": time.monotonic() - t0,
                         "max_position_diff_m": rep.max_position_diff_m, "same_code": same_code}
        if not rep.identical:
            result.problems.append(
                f"replay of {target.name} not identical" + ("" if same_code else
                " (the skinmap sources changed during the run, so this was expected)")
                + f": {rep.format()}")
    elif replay:
        result.problems.append("no finished file with /raw frames to replay")


def run_soak(seconds: float, *, size: str = "5x5", scan_rate: float = 50.0, shape: str = "palm",
             rotate_minutes: float = 10.0, rotate_mb: float = 256.0, progress_every: float = 60.0,
             workdir: Path, replay: bool = True) -> SoakResult:
    if seconds <= 0:
        raise ValueError(f"seconds must be > 0, got {seconds!r}")
    if progress_every <= 0:
        raise ValueError(f"progress_every must be > 0, got {progress_every!r}")
    result = SoakResult(seconds=seconds, size=size, scan_rate_hz=scan_rate,
                        source_at_start=source_fingerprint())
    serial_port, zenoh_port = free_port(), free_port()
    logs, state, cfg = workdir / "logs", workdir / "state", workdir / "soak.toml"
    write_daemon_config(cfg, device=DEVICE, serial_port=serial_port, zenoh_port=zenoh_port, logs=logs, state=state,
                        scan_rate=scan_rate, output_rate=0, rotate_minutes=rotate_minutes, rotate_mb=rotate_mb)

    emulator = start_emulator(serial_port, size=size, shape=shape, rate=scan_rate,
                              extra=["--status-every", "0"])
    daemon_log = (workdir / "skinmapd.log").open("wb")
    daemon = subprocess.Popen([sys.executable, "-m", "skinmap.daemon.service", "--config", str(cfg)],
                              stdin=subprocess.DEVNULL, stdout=daemon_log, stderr=subprocess.STDOUT)
    t_msg: list[float] = []
    latency: list[float] = []
    seqs: list[int] = []
    rss_t: list[float] = []
    rss: list[float] = []
    try:
        with SkinmapClient([f"tcp/127.0.0.1:{zenoh_port}"], prefix="skinmap", device=DEVICE,
                           queue_size=256) as client:
            client.elements(timeout=60.0)  # the daemon streams
            t0 = time.monotonic()
            cpu0 = proc_cpu_seconds(daemon.pid)
            result.load_average.append(os.getloadavg()[0])
            end, next_rss, next_progress = t0 + seconds, t0, t0 + progress_every
            last_report = (0, t0)
            while (now := time.monotonic()) < end:
                if daemon.poll() is not None:
                    result.problems.append(f"skinmapd exited early with code {daemon.returncode}")
                    break
                try:
                    m = client.elements(timeout=1.0)
                except TimeoutError:
                    continue
                t_msg.append(time.monotonic() - t0)
                latency.append((time.time_ns() - m.host_time_ns) / 1e6)
                seqs.append(m.seq)
                if now >= next_rss:
                    rss_t.append(now - t0)
                    rss.append(proc_rss_mb(daemon.pid))
                    next_rss += 1.0
                if now >= next_progress:
                    n0, tp = last_report
                    recent = np.array(latency[n0:])
                    print(f"  t+{now - t0:6.0f} s: {len(seqs)} messages, "
                          f"{(len(seqs) - n0) / (now - tp):.1f}/s, latency median "
                          f"{np.median(recent):.2f} ms p99 {np.percentile(recent, 99):.2f} ms, "
                          f"RSS {rss[-1]:.1f} MB, subscriber gaps {sequence_gaps(np.array(seqs))}",
                          flush=True)
                    last_report = (len(seqs), now)
                    next_progress += progress_every
            elapsed = time.monotonic() - t0
            result.load_average.append(os.getloadavg()[0])
            if daemon.poll() is None:
                result.daemon_cpu_percent = (proc_cpu_seconds(daemon.pid) - cpu0) / elapsed * 100
                rss_t.append(elapsed)
                rss.append(proc_rss_mb(daemon.pid))
                try:
                    result.status = client.status(timeout=3.0)
                except LookupError as exc:
                    result.problems.append(f"no status at the end: {exc}")
            client.close()  # before the daemon stops, so the subscriber does not wait on it
    finally:
        stop_process(daemon, timeout=30)
        stop_process(emulator)
        daemon_log.close()
    result.daemon_exit_code = daemon.returncode
    if daemon.returncode not in (0, None):
        result.problems.append(f"skinmapd exit code {daemon.returncode} (see {workdir / 'skinmapd.log'})")

    result.messages = len(seqs)
    result.message_rate_hz = len(seqs) / elapsed if elapsed > 0 else 0.0
    result.subscriber_gaps = sequence_gaps(np.array(seqs))
    if rss:
        t, r = np.array(rss_t), np.array(rss)
        result.rss_start_mb, result.rss_end_mb, result.rss_max_mb = r[0], r[-1], r.max()
        result.rss_growth_mb_h = growth_mb_per_hour(t, r)
        half = t >= t[-1] / 2
        result.rss_growth_second_half_mb_h = growth_mb_per_hour(t[half], r[half])
    result.latency = latency_drift(np.array(t_msg), np.array(latency))
    if not seqs:
        result.problems.append("no element message received during the run")
    check_files(logs, result, replay)
    return result


# ---------------------------------------------------------------------------------------------
# report


def format_report(r: SoakResult) -> str:
    st = r.status
    lat_f, lat_l = r.latency.get("first", {}), r.latency.get("last", {})
    raw = sum(f.get("counts", {}).get("/raw", 0) for f in r.files)
    lines = [
        f"soak: {r.seconds:g} s, {r.size} at {r.scan_rate_hz:g} scans/s, every scan published",
        f"  messages received {r.messages} ({r.message_rate_hz:.2f}/s), subscriber sequence gaps "
        f"{r.subscriber_gaps}",
        f"  daemon RSS start {r.rss_start_mb:.1f} MB, end {r.rss_end_mb:.1f} MB, max "
        f"{r.rss_max_mb:.1f} MB; growth {r.rss_growth_mb_h:+.2f} MB/h (second half "
        f"{r.rss_growth_second_half_mb_h:+.2f} MB/h); CPU {r.daemon_cpu_percent:.1f} % of a core; "
        f"machine load (1 min) {' -> '.join(f'{x:.2f}' for x in r.load_average)} on "
        f"{os.cpu_count()} CPUs",
        f"  dropped (daemon status): frames_dropped {st.get('frames_dropped', '?')} "
        f"(link {st.get('scans_lost', '?')}, queue {st.get('scans_dropped_queue', '?')}), "
        f"log_dropped {st.get('log_dropped', '?')}, crc_errors {st.get('crc_errors', '?')}, "
        f"reconnects {st.get('reconnects', '?')}, healthy {st.get('healthy', '?')}",
        f"  latency first 10 %: median {lat_f.get('median_ms', float('nan')):.2f} ms, p99 "
        f"{lat_f.get('p99_ms', float('nan')):.2f} ms (n {lat_f.get('n', 0)}); last 10 %: median "
        f"{lat_l.get('median_ms', float('nan')):.2f} ms, p99 {lat_l.get('p99_ms', float('nan')):.2f} ms "
        f"(n {lat_l.get('n', 0)})",
        f"  files: {sum(f.get('readable', False) for f in r.files)}/{len(r.files)} readable, "
        f"{sum(f.get('finished', False) for f in r.files)} finished, /raw frames logged {raw}, "
        f"/elements logged {sum(f.get('counts', {}).get('/elements', 0) for f in r.files)}",
    ]
    for f in r.files:
        lines.append(f"    {f['file']}: {f['bytes']} bytes, "
                     + (f"{'finished' if f['finished'] else 'NOT finished'}, "
                        + ", ".join(f"{t} {n}" for t, n in f['counts'].items())
                        if f.get("readable") else f"UNREADABLE {f.get('error')}"))
    if r.replay:
        rp = r.replay
        lines.append(f"  replay of {rp['file']}: {'IDENTICAL' if rp['identical'] else 'DIFFERENT'} "
                     f"({rp['compared']} element messages compared, {rp['mismatched']} mismatched, "
                     f"{rp.get('not_comparable', 0)} before the graph fit's first restart in the file, "
                     f"max difference {rp['max_position_diff_m'] * 1e3:.3g} mm, {rp['seconds']:.1f} s"
                     + ("" if rp["same_code"] else "; sources changed during the run") + ")")
    lines.append("  result: " + ("OK" if r.ok else "PROBLEMS: " + "; ".join(r.problems)))
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=3600.0, help="run length (default 3600)")
    ap.add_argument("--size", default="5x5", help="emulated array ROWSxCOLS (default 5x5)")
    ap.add_argument("--scan-rate", type=float, default=50.0, help="emulated scans per second (default 50)")
    ap.add_argument("--shape", default="palm", help="emulated shape (default palm: moving)")
    ap.add_argument("--rotate-minutes", type=float, default=10.0, help="MCAP file rotation period")
    ap.add_argument("--rotate-mb", type=float, default=256.0, help="MCAP file rotation size")
    ap.add_argument("--progress-every", type=float, default=60.0, help="progress line period, s")
    ap.add_argument("--no-replay", action="store_true", help="skip the replay of one log file")
    ap.add_argument("--workdir", type=Path, help="keep config, logs and daemon output here "
                                                 "(default: a temporary folder, removed)")
    ap.add_argument("--json", type=Path, help="also write the figures to this JSON file")
    args = ap.parse_args(argv)
    if args.seconds <= 0:
        ap.error(f"--seconds must be > 0, got {args.seconds:g}")

    with tempfile.TemporaryDirectory(prefix="skinmap-soak-") as tmp:
        workdir = args.workdir or Path(tmp)
        workdir.mkdir(parents=True, exist_ok=True)
        print(f"soak: {args.seconds:g} s of {args.size} at {args.scan_rate:g} scans/s, work folder "
              f"{workdir}", flush=True)
        result = run_soak(args.seconds, size=args.size, scan_rate=args.scan_rate, shape=args.shape,
                          rotate_minutes=args.rotate_minutes, rotate_mb=args.rotate_mb,
                          progress_every=args.progress_every, workdir=workdir,
                          replay=not args.no_replay)
    print(format_report(result), flush=True)
    if args.json:
        args.json.write_text(json.dumps({**asdict(result), "ok": result.ok}, indent=1, default=str))
    return 0 if result.ok else 1


if __name__ == "__main__":
    sys.exit(main())
