"""End-to-end figures of skinmapd against the emulator, all on loopback.

For each array size and output mode it starts the emulator and skinmapd as separate processes,
subscribes to the element messages over Zenoh, and prints:

- latency (after a 3 s warm-up) from the host receiving a scan's last byte on the serial port (the element message's
  host time stamp) to this subscriber holding the decoded element coordinates: median, p99;
- the daemon's CPU use (share of one core) and resident memory, from /proc;
- MCAP bytes per hour, from the log folder's growth;
- what the subscriber was told of the elements: the share of messages with some element flagged
  DEGRADED (its σ above skinmap.elements.DEGRADED_SIGMA_MM) and the elements' σ median, in µm;
- with --stages, where the time goes: the daemon runs with timing hooks (this file's
  ``--traced-daemon`` mode, the daemon's own code otherwise) and records per published frame
  the wait from the scan's last byte to the processing thread, the pipeline's stages
  (FrameResult.stage_s), the output up to the elements put, and garbage collections; the
  subscriber's receive time is joined by sequence number.  Printed: median, p99 and max per
  stage, and the stages of the slowest 1 % of frames (end to end), the graph fit of the slowest
  reconstructions, and how many frames were warm, deferred (docs/reconstruction.md) or no graph;
- with --accuracy, in process and in line (no timing): the same emulated scans through two
  FramePipelines, one deferring the cold graph fits a frame needs to a catch-up chain (skinmapd's
  default) and one fitting them in the frame, at each output mode: how many frames deferred,
  their element σ against the undeferred answer's, and how far their element positions are
  from the undeferred run's in units of their σ.

    .venv/bin/python bench/latency.py [--seconds 20] [--sizes 5x5,16x16] [--stages] [--accuracy]
"""
from __future__ import annotations

import argparse
import json
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
from skinmap.wire.messages import ElementFlag


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
                        rotate_mb: float = 256.0, lead_scans: int | None = None) -> None:
    """A skinmapd config for the benchmarks: emulator on loopback TCP, 64 elements in a row;
    ``lead_scans``: `[output] lead_scans` (None: the daemon's default)."""
    lead = "" if lead_scans is None else f"lead_scans = {lead_scans}"
    path.write_text(f"""
[device]
port = "socket://127.0.0.1:{serial_port}"
name = "{device}"
scan_rate_hz = {scan_rate}
[output]
rate_hz = {output_rate}
{lead}
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


STAGES = ("queue", "strains", "restart", "reconstruct", "uncertainty", "elements", "output", "delivery")


def traced_daemon(config: str, trace_path: str) -> int:
    """skinmapd with timing hooks; at exit writes one JSON object per published frame (times in
    ms): queue (scan's last byte → the processing thread takes it), the pipeline's stage_s,
    output (pipeline done → elements put), and the garbage collections seen."""
    import atexit
    import gc

    from skinmap.daemon import processing, service, zenoh_io

    frames: dict[int, dict] = {}
    current: dict = {}
    collections: list[dict] = []

    take = processing.ProcessingListener._process
    process = processing.FramePipeline.process
    put = zenoh_io.SkinmapPublisher.publish_elements

    def traced_take(self, record, lead=False):
        current.clear()
        current["picked_ns"] = time.time_ns()
        return take(self, record, lead)

    def traced_process(self, *args, **kwargs):
        result = process(self, *args, **kwargs)
        current["result"] = result
        current["processed_ns"] = time.time_ns()
        return result

    def traced_put(self, payload):
        put(self, payload)
        r = current.get("result")
        if r is not None:
            frames[r.seq & 0xFFFFFFFF] = {
                "seq": r.seq & 0xFFFFFFFF, "rx_ns": r.host_time_ns, "put_ns": time.time_ns(),
                "queue": (current["picked_ns"] - r.host_time_ns) / 1e6,
                **{k: v * 1e3 for k, v in r.stage_s.items()},
                "output": (time.time_ns() - current["processed_ns"]) / 1e6,
                "model": str(r.diagnostics.get("status", "")),
                "graph": str(getattr(getattr(r.surface, "diagnostics", None), "extra", {}).get("graph_fit", "")),
            }

    def on_gc(phase: str, info: dict) -> None:
        if phase == "start":
            current["gc_ns"] = time.time_ns()
        elif "gc_ns" in current:
            collections.append({"generation": info["generation"], "start_ns": current["gc_ns"],
                                "ms": (time.time_ns() - current.pop("gc_ns")) / 1e6})

    def write() -> None:
        Path(trace_path).write_text(json.dumps({"frames": list(frames.values()), "gc": collections}))

    processing.ProcessingListener._process = traced_take  # type: ignore[method-assign]
    processing.FramePipeline.process = traced_process  # type: ignore[method-assign]
    zenoh_io.SkinmapPublisher.publish_elements = traced_put  # type: ignore[method-assign]
    gc.callbacks.append(on_gc)
    atexit.register(write)
    return service.main(["--config", config])


def stage_table(trace: dict, received_ns: dict[int, int]) -> list[str]:
    """Lines: per stage median / p99 / max (ms) over the frames the subscriber received after the
    warm-up, and the mean stages of the slowest 1 % of them."""
    frames = [dict(f, delivery=(received_ns[f["seq"]] - f["put_ns"]) / 1e6,
                   total=(received_ns[f["seq"]] - f["rx_ns"]) / 1e6)
              for f in trace["frames"] if f["seq"] in received_ns]
    if not frames:
        return ["  no traced frame was received"]
    lines = [f"  {'stage':<12} {'median':>8} {'p99':>8} {'max':>8}  ms, {len(frames)} frames"]
    for name in (*STAGES, "total"):
        v = np.array([f.get(name, 0.0) for f in frames])
        lines.append(f"  {name:<12} {np.median(v):8.2f} {np.percentile(v, 99):8.2f} {v.max():8.2f}")
    worst = sorted(frames, key=lambda f: -f["total"])[:max(1, len(frames) // 100)]
    lines.append(f"  slowest {len(worst)} (1 %), mean ms: " + ", ".join(
        f"{name} {np.mean([f.get(name, 0.0) for f in worst]):.2f}" for name in (*STAGES, "total")))
    slow = sorted(frames, key=lambda f: -f.get("reconstruct", 0.0))[:max(1, len(frames) // 100)]
    lines.append(f"  slowest {len(slow)} reconstructions, graph fit: " + "; ".join(
        f"{f.get('reconstruct', 0.0):.1f} ms {f.get('graph', '')[:60]!r}" for f in slow))
    kinds: dict[str, int] = {}
    for f in frames:
        how = f.get("graph", "")
        key = ("deferred" if how.startswith("deferred") else how if how in ("warm", "warm: linear start", "linear", "general") else
               "not a graph" if how else "-")
        kinds[key] = kinds.get(key, 0) + 1
    lines.append("  graph fit per frame: " + ", ".join(f"{k} {v}" for k, v in sorted(kinds.items())))
    t0, t1 = min(f["rx_ns"] for f in frames), max(f["put_ns"] for f in frames)
    gcs = [c for c in trace["gc"] if t0 <= c["start_ns"] <= t1]
    for gen in (0, 1, 2):
        ms = [c["ms"] for c in gcs if c["generation"] == gen]
        lines.append(f"  gc generation {gen}: {len(ms)} collections" + (f", max {max(ms):.2f} ms" if ms else ""))
    return lines


def run_case(size: str, scan_rate: float, output_rate: float, seconds: float, workdir: Path,
             shape: str = "palm", stages: bool = False, lead_scans: int | None = None) -> dict:
    serial_port, zenoh_port = free_port(), free_port()
    logs = workdir / f"logs-{size}-{output_rate:g}"
    cfg = workdir / f"bench-{size}-{output_rate:g}.toml"
    write_daemon_config(cfg, device="bench", serial_port=serial_port, zenoh_port=zenoh_port, logs=logs,
                        state=workdir / "state", scan_rate=scan_rate, output_rate=output_rate,
                        lead_scans=lead_scans)
    emulator = start_emulator(serial_port, size=size, shape=shape, rate=scan_rate)
    trace = workdir / f"trace-{size}-{output_rate:g}.json"
    command = ([sys.executable, __file__, "--traced-daemon", str(cfg), str(trace)] if stages
               else [sys.executable, "-m", "skinmap.daemon.service", "--config", str(cfg)])
    daemon = subprocess.Popen(command, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    latencies: list[float] = []
    degraded: list[bool] = []
    sigma_um: list[float] = []
    received_ns: dict[int, int] = {}
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
                now = time.time_ns()
                latencies.append((now - msg.host_time_ns) / 1e6)
                degraded.append(bool((msg.flags & int(ElementFlag.DEGRADED)).any()))
                sigma_um.append(float(np.median(msg.uncertainty)) * 1e6)
                received_ns[msg.seq] = now
            elapsed = time.monotonic() - t0
            cpu = (proc_cpu_seconds(daemon.pid) - cpu0) / elapsed
            rss = proc_rss_mb(daemon.pid)
            mcap_rate = (dir_bytes(logs) - bytes0) / elapsed * 3600
    finally:
        stop_process(daemon, timeout=15)
        stop_process(emulator)
    lat = np.array(latencies)
    stage_lines = stage_table(json.loads(trace.read_text()), received_ns) if stages and trace.exists() else []
    return {"stages": stage_lines,"size": size, "scan_rate": scan_rate, "output": "every scan" if output_rate == 0 else f"{output_rate:g} Hz",
            "n": lat.size, "rate": lat.size / elapsed, "median": float(np.median(lat)), "p99": float(np.percentile(lat, 99)),
            "cpu": cpu * 100, "rss": rss, "mcap_gb_h": mcap_rate / 1e9,
            "degraded": 100.0 * float(np.mean(degraded)) if degraded else 0.0,
            "sigma_um": float(np.median(sigma_um)) if sigma_um else float("nan")}


def accuracy_lines(size: str, scan_rate: float, output_rate: float, seconds: float, shape: str,
                   lead_scans: int | None = None) -> list[str]:
    """Deferred against undeferred cold fits on the same emulated scans (see the docstring), the
    lead scans (``lead_scans``, None: skinmapd's default) reconstructed and not compared."""
    from skinmap.daemon.config import OutputConfig
    from emulated_pipeline import emulated_device, emulated_pipeline, emulated_scans

    n, m = (int(x) for x in size.split("x"))
    device, spec = emulated_device(n, shape, m=m, scan_rate=scan_rate)
    step = 1 if output_rate == 0 else max(1, round(scan_rate / output_rate))
    lead = OutputConfig().lead_scans if lead_scans is None else lead_scans
    scans = [(k, raw) for k, _, raw in emulated_scans(device, spec, seconds, every=step, lead=lead)]
    uv = np.stack([(np.arange(64) - 31.5) * 0.6, np.zeros(64)], axis=1)  # the latency runs' element row
    runs = []
    for defer in (True, False):
        pipe = emulated_pipeline(device, spec, uv, defer_cold_fits=defer)
        runs.append([r for r in (pipe.process(raw, seq, 0, 0, lead=bool(seq % step)) for seq, raw in scans)
                     if r.seq % step == 0])
    ratios, sig_d, sig_u, gaps = [], [], [], []
    for a, b in zip(*runs):
        if a.diagnostics.get("graph_deferred"):
            gap = np.linalg.norm(a.element_positions_mm - b.element_positions_mm, axis=1)
            ratios.append(gap / a.element_sigma_mm)
            gaps.append(gap)
            sig_d.append(a.element_sigma_mm)
            sig_u.append(b.element_sigma_mm)
    differ = sum(not np.array_equal(a.element_positions_mm, b.element_positions_mm) for a, b in zip(*runs))
    mode = "every scan" if output_rate == 0 else f"{output_rate:g} Hz"
    head = (f"  accuracy {size} {mode}: {len(runs[0])} frames, {len(ratios)} deferred, {differ} differ from the "
            f"run that fits cold in the frame")
    if not ratios:
        return [head]
    r, sd, su, g = (np.concatenate(x) for x in (ratios, sig_d, sig_u, gaps))
    worst = np.array([x.max() for x in ratios])
    return [head,
            f"    deferred frames' elements: σ median {np.median(sd) * 1e3:.0f} µm (the cold fit's answer: "
            f"{np.median(su) * 1e3:.0f} µm), {np.mean(sd > 0.5) * 100:.0f} % above 0.5 mm (DEGRADED)",
            f"    distance to the cold fit's answer: median {np.median(g) * 1e3:.1f} µm, max {g.max() * 1e3:.1f} µm; "
            f"in σ: median {np.median(r):.2f}, within 1 σ {np.mean(r <= 1.0) * 100:.1f} % of elements, "
            f"frames wholly within 1 σ {np.mean(worst <= 1.0) * 100:.0f} %, worst {worst.max():.2f}"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--sizes", default="5x5,16x16")
    ap.add_argument("--scan-rate", type=float, default=50.0, help="emulated scans per second")
    ap.add_argument("--shape", default="palm", help="emulated shape spec (default: the moving palm gesture)")
    ap.add_argument("--outputs", default="10,0", help="output rates to measure, Hz (0 = every scan)")
    ap.add_argument("--lead-scans", type=int, default=None,
                    help="[output] lead_scans of the daemon (default: its own default)")
    ap.add_argument("--stages", action="store_true", help="time the daemon's stages per frame (see above)")
    ap.add_argument("--accuracy", action="store_true",
                    help="only compare deferred with in-frame cold graph fits, in process (see above)")
    ap.add_argument("--traced-daemon", nargs=2, metavar=("CONFIG", "TRACE"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.traced_daemon:
        sys.exit(traced_daemon(*args.traced_daemon))
    if args.accuracy:
        for size in args.sizes.split(","):
            for output_rate in (float(x) for x in args.outputs.split(",")):
                print("\n".join(accuracy_lines(size, args.scan_rate, output_rate, max(args.seconds, 32.0), args.shape,
                                                    args.lead_scans)),
                      flush=True)
        return
    print(f"load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}", flush=True)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for size in args.sizes.split(","):
            for output_rate in (float(x) for x in args.outputs.split(",")):
                try:
                    rows.append(run_case(size, args.scan_rate, output_rate, args.seconds, Path(tmp), args.shape,
                                         args.stages, args.lead_scans))
                except Exception as exc:  # noqa: BLE001 - report the case and go on with the others
                    print(f"{size} output {output_rate:g} Hz: FAILED: {exc}", flush=True)
                    continue
                r = rows[-1]
                print(f"{r['size']:>6} scan {r['scan_rate']:g}/s output {r['output']:>10}: {r['n']} msgs "
                      f"({r['rate']:.1f}/s)  latency median {r['median']:.2f} ms  p99 {r['p99']:.2f} ms  "
                      f"CPU {r['cpu']:.1f} %  RSS {r['rss']:.0f} MB  MCAP {r['mcap_gb_h']:.2f} GB/h  "
                      f"DEGRADED {r['degraded']:.1f} % of messages  element σ median {r['sigma_um']:.0f} µm", flush=True)
                for line in r["stages"]:
                    print(line, flush=True)
    print(f"\nload average {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    print("| array | scans/s | output | messages | latency median ms | latency p99 ms | daemon CPU % | RSS MB | MCAP GB/h "
          "| DEGRADED messages % | element σ median µm |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['size']} | {r['scan_rate']:g} | {r['output']} | {r['n']} | {r['median']:.2f} | {r['p99']:.2f} | "
              f"{r['cpu']:.1f} | {r['rss']:.0f} | {r['mcap_gb_h']:.2f} | {r['degraded']:.1f} | {r['sigma_um']:.0f} |")


if __name__ == "__main__":
    main()
