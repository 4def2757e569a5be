"""`skinmap`: the user's tool.

    skinmap demo                      emulator + skinmapd on loopback, live status, Ctrl-C stops
    skinmap echo [--device D]         live element positions and rates from a running daemon
    skinmap info [--device D]         the daemon's device description (geometry, elements, calibration)
    skinmap replay LOG.mcap           re-run the pipeline from logged raw frames; compare; republish
    skinmap inspect LOG.mcap          topics, rates, gaps, errors; --png T for a surface snapshot
    skinmap recover LOG.mcap.active   rewrite a cut log as a finished file
    skinmap router [--listen EP]      a Zenoh router for several gateways and many clients
    skinmap ls [--connect EP]         the devices alive (liveliness), with their status
    skinmap record [--device D]...    record one or many gateways to MCAP from anywhere
    skinmap foxglove [--port 8765]    the live scene for the Foxglove app (WebSocket, loopback)
    skinmap tare --config FILE        record the flat sheet's resting resistances
    skinmap calibrate --config FILE   guided mold calibration: gauge factors and layer offsets
    skinmap map LOG.mcap --poses CSV  a log's presses stitched into the touched wall's relief
"""
from __future__ import annotations

import argparse
import json
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["main"]

DEFAULT_CONNECT = "tcp/127.0.0.1:7447"


# ------------------------------------------------------------------------------------------
# demo


def _wait_for_tcp(host: str, port: int, timeout: float, proc: subprocess.Popen | None = None) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc is not None and proc.poll() is not None:
            raise RuntimeError(f"the emulator exited early with code {proc.returncode}")
        try:
            with socket.create_connection((host, port), timeout=0.2):
                return
        except OSError:
            time.sleep(0.05)
    raise RuntimeError(f"nothing listens on {host}:{port} after {timeout:g} s")


def _relay_lines(proc: subprocess.Popen, prefix: str) -> None:
    assert proc.stdout is not None
    for line in proc.stdout:
        print(prefix + line.rstrip("\n"), flush=True)


def start_emulator(port: int, *, size: str = "5x5", shape: str = "palm", rate: float = 50.0,
                   mechanics: str = "kinematic", extra: list[str] | None = None,
                   label_output: bool = False) -> subprocess.Popen:
    """The emulator as a child process serving socket://127.0.0.1:PORT (a fresh interpreter,
    never a fork of one that may hold a Zenoh session).  An elastic scene not yet in the solve
    cache is solved before the port opens (up to minutes for a moving scene), so it is waited
    for longer."""
    cmd = [sys.executable, "-m", "skinmap.emulator.command", "--tcp", str(port), "--size", size,
           "--shape", shape, "--rate", str(rate), "--mechanics", mechanics, *(extra or [])]
    proc: subprocess.Popen[str] | subprocess.Popen[bytes]
    if label_output:
        # Its lines are relayed prefixed, so they are told apart from the gateway's (and go
        # above the live status panel, which redirects stdout).
        proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                                stderr=subprocess.STDOUT, text=True, start_new_session=True)
        threading.Thread(target=_relay_lines, args=(proc, "[emulator] "), daemon=True,
                         name="skinmap-emulator-output").start()
    else:
        proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, start_new_session=True)
    try:
        _wait_for_tcp("127.0.0.1", port, 15.0 if mechanics == "kinematic" else 1800.0, proc)
    except Exception:
        stop_process(proc)
        raise
    return proc


def stop_process(proc: subprocess.Popen, timeout: float = 5.0) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def _demo_elements_on_sheet(cfg: Any, size: str) -> Any:
    """The demo config with its element row narrowed to the cells' span where the array asked
    for is too small for it (the row's 46.5 mm fits 5×5 and larger at 12 mm pitch); a malformed
    size is left for the emulator to refuse."""
    import dataclasses

    from skinmap.emulator.device import ScannerSpec

    try:
        _, m = (int(x) for x in size.lower().split("x"))
    except ValueError:
        return cfg
    el = cfg.elements
    span = (m - 1) * (cfg.reconstruction.pitch_mm or ScannerSpec().pitch_mm)  # (0: the emulated scanner's)
    if el.layout != "grid" or el.cols < 2 or (el.cols - 1) * el.pitch_u_mm <= span:
        return cfg
    pitch = span / (el.cols - 1)
    print(f"skinmap demo: the element row narrowed to the {size} array's cells: {el.cols} elements at {pitch:.3g} mm",
          flush=True)
    return dataclasses.replace(cfg, elements=dataclasses.replace(el, pitch_u_mm=pitch, centre_u_mm=0.0))


def cmd_demo(args: argparse.Namespace) -> int:
    from skinmap.daemon.config import DEMO_CONFIG, ConfigError, load_config, parse_config
    from skinmap.daemon.service import run_gateway, setup_logging
    import tomllib

    setup_logging(args.verbose)
    try:
        if args.config:
            cfg = load_config(args.config)
        else:
            cfg = parse_config(tomllib.loads(DEMO_CONFIG), source=str(Path.cwd() / "skinmap-demo.toml"), text=DEMO_CONFIG)
    except ConfigError as exc:
        print(f"skinmap demo: {exc}", file=sys.stderr)
        return 2
    if not args.config:
        cfg = _demo_elements_on_sheet(cfg, args.size)
    port = int(cfg.device.port.rsplit(":", 1)[1]) if cfg.device.port.startswith("socket://") else 7600
    print(f"skinmap demo: starting the emulator ({args.size}, shape '{args.shape}', {args.mechanics} mechanics) "
          f"on socket://127.0.0.1:{port}", flush=True)
    gauges = [*(["--response-tau", repr(args.response_tau)] if args.response_tau else []),
              *(["--relaxation", repr(args.relaxation)] if args.relaxation else [])]
    emulator = start_emulator(port, size=args.size, shape=args.shape, rate=cfg.device.scan_rate_hz,
                              mechanics=args.mechanics, extra=gauges, label_output=True)
    try:
        print(f"skinmap demo: skinmapd publishing on {', '.join(cfg.zenoh.listen)} under '{cfg.zenoh.prefix}/{cfg.device.name or '<serial>'}', "
              f"logging to {cfg.resolve(cfg.log.directory)}; Ctrl-C stops", flush=True)
        stop = threading.Event()
        if args.duration:
            threading.Timer(args.duration, stop.set).start()
        return run_gateway(cfg, console=True, stop_event=stop)
    finally:
        stop_process(emulator)
        print("skinmap demo: stopped", flush=True)


# ------------------------------------------------------------------------------------------
# echo / info


def _client(args: argparse.Namespace):
    from skinmap.client import SkinmapClient

    return SkinmapClient([args.connect], prefix=args.prefix, device=args.device)


def cmd_echo(args: argparse.Namespace) -> int:
    with _client(args) as client:
        try:
            source = client.info(timeout=min(args.timeout, 2.0)).get("source", "live")
        except (TimeoutError, LookupError):
            source = "unknown"
        live = source == "live"
        if not live:
            print(f"source: {source}: latency is shown only for live data (these host times are "
                  "not now)" if source != "unknown" else
                  "source: unknown (no info answered): latency is shown only for live data",
                  file=sys.stderr)
        t_last = time.monotonic()
        count = 0
        rate = 0.0
        end = time.monotonic() + args.duration if args.duration else None
        try:
            while end is None or time.monotonic() < end:
                try:
                    msg = client.elements(timeout=args.timeout)
                except TimeoutError:
                    print(f"no element message within {args.timeout:g} s (is skinmapd running under '{args.prefix}/{args.device}'?)",
                          file=sys.stderr)
                    return 1
                count += 1
                now = time.monotonic()
                if now - t_last >= 1.0:
                    rate = count / (now - t_last)
                    count, t_last = 0, now
                # host_time_ns is when the gateway received the scan: now minus it is the
                # latency only for live data (a replay carries the recorded times).
                latency = f"latency {(time.time_ns() - msg.host_time_ns) / 1e6:6.2f} ms" if live else \
                    f"device t {msg.device_time_us / 1e6:9.3f} s"
                pos = msg.positions * 1000.0
                k = pos.shape[0]
                pick = sorted({0, k // 2, k - 1}) if k else []
                shown = "  ".join(f"#{i}({pos[i, 0]:+7.2f},{pos[i, 1]:+7.2f},{pos[i, 2]:+7.2f})" for i in pick)
                valid = int(np.count_nonzero(msg.flags & 1))
                print(f"seq {msg.seq:>7}  {rate:5.1f} Hz  {latency}  valid {valid}/{k}  mm: {shown}", flush=True)
        except KeyboardInterrupt:
            pass
    return 0


def cmd_info(args: argparse.Namespace) -> int:
    with _client(args) as client:
        try:
            info = client.info()
        except (TimeoutError, LookupError) as exc:
            print(f"no info from '{args.prefix}/{args.device}': {exc}", file=sys.stderr)
            return 1
    if args.json:
        print(json.dumps(info, indent=2))
    else:
        cal = info.get("calibration", {})
        print(f"device     {info['device']}  (serial {info.get('serial_number', '?')})")
        print(f"array      {info['rows']}×{info['cols']} cells, pitch {info['pitch_m'] * 1000:g} mm")
        print(f"elements   {info['elements'].get('count')} ({info['elements'].get('layout', '?')})")
        print(f"calibration {cal.get('source', '?')}")
        fit = cal.get("fit")
        if isinstance(fit, dict):
            res, sd = fit.get("residual_strain_rms_median"), fit.get("gauge_factor_rel_sd_median")
            print(f"           {fit.get('method', '?')}; residual {res if res is None else f'{res:.1e}'} strain rms, "
                  f"gauge-factor s.d. {sd if sd is None else f'{100 * sd:.2f} %'} (medians); "
                  f"layer offsets {'fitted' if fit.get('offsets_determined') else 'nominal'}")
        unc = info.get("uncertainty")
        if isinstance(unc, dict):
            lag = unc.get("response_lag_s")
            print(f"σ carries  strain noise {unc.get('strain_sigma')}, a shared gain of s.d. {unc.get('gain_sd', 0.0):.4g}, "
                  f"the gauges' lag {'(left out)' if not lag else f'up to {1e3 * lag:.0f} ms'} while the sheet "
                  f"moves, twist prior {unc.get('twist_prior')}")
        print(f"versions   {info.get('versions')}")
    return 0


# ------------------------------------------------------------------------------------------
# fleet: router / ls / record


def _wait_until_stopped(duration: float) -> None:
    end = time.monotonic() + duration if duration else None
    while end is None or time.monotonic() < end:
        time.sleep(0.2 if end is None else max(0.0, min(0.2, end - time.monotonic())))


def cmd_router(args: argparse.Namespace) -> int:
    from skinmap.daemon.fleet import router_config
    from skinmap.daemon.zenoh_io import open_session

    config = router_config(args.listen, allow_non_loopback=args.allow_non_loopback,
                           config_file=args.zenoh_config)
    with open_session(config):
        print(f"skinmap router: routing on {', '.join(args.listen)} (no scouting); gateways set "
              f"[zenoh] connect = {json.dumps(args.listen)}, clients use --connect "
              f"{args.listen[0]}; Ctrl-C stops", flush=True)
        try:
            _wait_until_stopped(args.duration)
        except KeyboardInterrupt:
            pass
    print("skinmap router: stopped", flush=True)
    return 0


def _client_session(args: argparse.Namespace):
    from skinmap.wire.session import make_session_config, open_session

    return open_session(make_session_config([], [args.connect], mode="client"))


def cmd_ls(args: argparse.Namespace) -> int:
    from skinmap.client import discover  # ls needs the light client only
    from skinmap.wire import messages as wire

    with _client_session(args) as session:
        devices = discover(session, args.prefix, timeout=args.timeout)
        if not devices:
            print(f"no device alive under '{args.prefix}/*' via {args.connect}", file=sys.stderr)
            return 1
        for device in devices:
            line = f"{args.prefix}/{device}"
            try:
                reply = next((r for r in session.get(f"{args.prefix}/{device}/status",
                                                     timeout=args.timeout) if r.ok is not None), None)
                st = wire.decode_status(reply.ok.payload.to_bytes()) if reply else None
            except wire.MessageError as exc:
                st, line = None, line + f"  (status rejected: {exc})"
            if st is not None:
                line += (f"  {st.get('link_state', '?')}  seq {st['seq']}  "
                         f"{st['publish_rate_hz']:.1f} Hz  log {st['log_state']}")
            elif "rejected" not in line:
                line += "  (alive; no status published yet)"
            print(line, flush=True)
    return 0


def cmd_record(args: argparse.Namespace) -> int:
    from skinmap.daemon.fleet import Recorder, discover

    with _client_session(args) as session:
        devices = args.device or ["*"]
        with Recorder(session, args.prefix, devices, args.output) as rec:
            print(f"skinmap record: recording {', '.join(f'{args.prefix}/{d}' for d in devices)} via "
                  f"{args.connect} to {args.output}; Ctrl-C stops", flush=True)
            alive = discover(session, args.prefix, timeout=1.0)
            print(f"skinmap record: devices alive now: {', '.join(alive) or 'none'}", flush=True)
            try:
                _wait_until_stopped(args.duration)
            except KeyboardInterrupt:
                pass
        for device, counts in sorted(rec.counts.items()):
            kinds = ", ".join(f"{k} {n}" for k, n in sorted(counts.messages.items()))
            print(f"  {device}: {kinds}; rejected {counts.rejected}", flush=True)
        print(f"skinmap record: wrote {', '.join(rec.logger.finished_paths) or 'nothing'}"
              f"{f'; {rec.dropped} message(s) dropped (writer behind)' if rec.dropped else ''}", flush=True)
    return 0


def cmd_foxglove(args: argparse.Namespace) -> int:
    from skinmap.daemon.bridge import FoxgloveBridge

    with _client_session(args) as session:
        devices = args.device or ["*"]
        with FoxgloveBridge(session, args.prefix, devices, host=args.host, port=args.port) as bridge:
            print(f"skinmap foxglove: serving the live scene of {', '.join(f'{args.prefix}/{d}' for d in devices)} "
                  f"on ws://{args.host}:{bridge.port} (Foxglove: Open connection -> Foxglove WebSocket); "
                  "Ctrl-C stops", flush=True)
            try:
                _wait_until_stopped(args.duration)
            except KeyboardInterrupt:
                pass
        print(f"skinmap foxglove: stopped; {bridge.forwarded} messages forwarded, {bridge.rejected} rejected",
              flush=True)
    return 0


# ------------------------------------------------------------------------------------------
# replay


def cmd_replay(args: argparse.Namespace) -> int:
    from skinmap.daemon.replay import replay_log

    publisher_ctx = None
    if args.publish:
        from skinmap.daemon.zenoh_io import make_session_config, open_session

        publisher_ctx = open_session(make_session_config([args.listen], [],
                                                         deny_remote_writes=f"{args.prefix}/**"))
    def announce(key: str) -> None:
        device = key.rsplit("/", 1)[1]
        print(f"skinmap replay: publishing on {args.listen} under '{key}' (info answered; "
              f"host times are the recorded ones). Watch with:\n  skinmap echo --connect "
              f"{args.listen} --prefix {args.prefix} --device {device}", file=sys.stderr, flush=True)

    try:
        session = publisher_ctx.__enter__() if publisher_ctx else None
        report = replay_log(args.log, session=session, prefix=args.prefix, speed=args.speed,
                            progress=not args.quiet, max_record_bytes=_record_limit(args),
                            on_publish=announce)
    finally:
        if publisher_ctx:
            publisher_ctx.__exit__(None, None, None)
    print(report.format())
    return 0 if report.identical or args.publish else 1


# ------------------------------------------------------------------------------------------
# inspect / recover


def _record_limit(args: argparse.Namespace) -> int:
    if not 0.001 <= args.max_record_mb <= 1 << 20:
        raise ValueError(f"--max-record-mb must be between 0.001 and {1 << 20}, got {args.max_record_mb:g}")
    return int(args.max_record_mb * 1024 * 1024)


def _add_record_limit(p: argparse.ArgumentParser) -> None:
    p.add_argument("--max-record-mb", type=float, default=64.0,
                   help="skip records and chunks larger than this (MiB, uncompressed); default 64")


def cmd_inspect(args: argparse.Namespace) -> int:
    from skinmap.daemon.mcapinspect import inspect
    from skinmap.daemon.mcapsnapshot import render_surface_png

    report = inspect(args.log, gap_threshold_s=args.gap, max_record_bytes=_record_limit(args))
    print(report.format())
    if args.png:
        snap = render_surface_png(args.log, args.at, args.png)
        print(f"surface at seq {getattr(snap, 'seq', '?')} written to {args.png}")
    return 0


def cmd_recover(args: argparse.Namespace) -> int:
    from skinmap.daemon.mcaprecover import recover

    report = recover(args.log, args.output, max_record_bytes=_record_limit(args))
    print(report.format())
    return 0


# ------------------------------------------------------------------------------------------
# tare


def cmd_tare(args: argparse.Namespace) -> int:
    from skinmap.daemon.calibrate import tare_problem
    from skinmap.strains import compute_tare, save_tare
    from skinmap.daemon.config import ConfigError, load_config
    from skinmap.daemon.portlock import PortBusy, PortLock
    from skinmap.daemon.replay import resistances_from_log

    try:
        cfg = load_config(args.config)
    except ConfigError as exc:
        print(f"skinmap tare: {exc}", file=sys.stderr)
        return 2
    if args.from_log:
        serial, scans = resistances_from_log(args.from_log, start_s=args.at, count=args.scans)
        hello = _hello_from_log(args.from_log)
    else:
        try:
            with PortLock(cfg.device.port, "skinmap tare"):
                serial, scans, hello = _tare_from_scanner(cfg, args.scans)
        except PortBusy as exc:
            print(f"skinmap tare: {exc}; nothing written", file=sys.stderr)
            return 1
    if len(scans) == 0:
        print("skinmap tare: no scans received; nothing written", file=sys.stderr)
        return 1
    stack = np.stack(scans)
    if hello is not None:
        h_u = cfg.reconstruction.h_upper_mm or hello.h_upper_um / 1000.0
        h_l = cfg.reconstruction.h_lower_mm or hello.h_lower_um / 1000.0
        problem = tare_problem(stack, hello.gauge_factor(), hello.base_resistance_ohm(), h_u, h_l)
        if problem:
            print(f"skinmap tare: not a tare: {problem}; nothing written", file=sys.stderr)
            return 1
    base = compute_tare(stack)
    path = save_tare(cfg.resolve(cfg.state.directory), serial, base, len(scans))
    finite = base[np.isfinite(base)]
    print(f"tare of {len(scans)} scans from scanner {serial} written to {path} "
          f"(R0 {finite.min():.4f}…{finite.max():.4f} Ω; {np.count_nonzero(~np.isfinite(base))} gauges without data)")
    return 0


def _hello_from_log(log_path: str) -> Any:
    """The scanner's HELLO as logged with the config (None if the log has none)."""
    from skinmap.daemon.mcapread import iter_messages_file_order
    from skinmap.protocol import Hello, StreamDecoder

    decoder = StreamDecoder()
    for m in iter_messages_file_order(str(log_path)):
        if m.topic == "/raw":
            for frame in decoder.feed(m.data):
                if isinstance(frame.msg, Hello):
                    return frame.msg
    return None


def _tare_from_scanner(cfg: Any, count: int) -> tuple[str, list[np.ndarray], Any]:
    """Open the scanner directly (the port lock keeps skinmapd off it meanwhile)."""
    from skinmap.daemon.link import ScannerLink

    scans: list[np.ndarray] = []
    done = threading.Event()

    def on_scan(scan, _frame, _t):
        if len(scans) < count:
            scans.append(scan.resistances_ohm())
        if len(scans) >= count:
            done.set()

    link = ScannerLink(cfg.device, on_hello=lambda h: None, on_scan=on_scan,
                       on_event=lambda level, text: print(f"{level}: {text}", file=sys.stderr))
    link.start()
    try:
        done.wait(timeout=max(10.0, 3 * count / cfg.device.scan_rate_hz))
    finally:
        link.stop()
    serial = link.hello.serial_number if link.hello else "unknown"
    return serial, scans, link.hello


# ------------------------------------------------------------------------------------------
# calibrate


def _radii(text: str) -> tuple[float, ...]:
    try:
        radii = tuple(float(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"radii must be comma-separated numbers in mm, got {text!r}") from None
    if len(set(radii)) < 1 or any(not (5.0 <= r <= 10000.0) for r in radii):
        raise argparse.ArgumentTypeError(f"radii must be 5..10000 mm, got {text!r}")
    return radii


def cmd_calibrate(args: argparse.Namespace) -> int:
    from skinmap.daemon.calibrate import (CalibrationAborted, EmulatedPlacer, LinkFeed, PromptPlacer,
                                          run_calibration, summarise)
    from skinmap.daemon.config import ConfigError, DeviceConfig, load_config
    from skinmap.daemon.moldcal import standard_poses
    from skinmap.daemon.portlock import PortBusy, PortLock

    cfg = None
    if args.config:
        try:
            cfg = load_config(args.config)
        except ConfigError as exc:
            print(f"skinmap calibrate: {exc}", file=sys.stderr)
            return 2
    elif not args.emulate:
        print("skinmap calibrate: give --config (the scanner's port and state directory) or --emulate", file=sys.stderr)
        return 2
    state_dir = Path(args.state_dir) if args.state_dir else (cfg.resolve(cfg.state.directory) if cfg else Path("state"))
    if args.dome and args.mechanics == "kinematic" and args.emulate:
        print("skinmap calibrate: --dome needs --mechanics elastic with --emulate (a kinematic sheet has no "
              "Poisson ratio)", file=sys.stderr)
        return 2
    poses = standard_poses(args.radii, 0.0 if args.no_stretch else args.stretch, args.dome)
    emulator = None
    if args.emulate:
        from skinmap.emulator.device import ScannerSpec as EmulatedDevice
        from skinmap.emulator.emulator import Emulator
        from skinmap.emulator.physics import Flat
        from skinmap.emulator.transport import TcpTransport

        n, m = (int(x) for x in args.emulate.lower().split("x"))
        tcp = TcpTransport(0)
        emulator = Emulator(EmulatedDevice(n=n, m=m, scan_rate_hz=50.0, seed=args.seed, gf_spread=args.gf_spread,
                                           offset_spread=args.offset_spread), Flat(), tcp)
        placer: Any = EmulatedPlacer(emulator, args.mechanics, args.seed, args.axis_error, args.offset)
        print(f"skinmap calibrate: emulated {n}x{m} scanner ({args.mechanics} molds; hidden gauge-factor spread "
              f"{100 * args.gf_spread:g} %, offset spread {100 * args.offset_spread:g} %); solving the poses", flush=True)
        placer.prepare(poses)
        emulator.start()
        device_cfg = DeviceConfig(port=tcp.url, scan_rate_hz=50.0)
    else:
        placer = PromptPlacer()
        assert cfg is not None  # without --emulate, --config is required (checked above)
        device_cfg = cfg.device
    feed = LinkFeed(device_cfg, on_event=lambda level, text: print(f"  {level}: {text}", file=sys.stderr)
                    if level != "info" else None)
    try:
        with PortLock(device_cfg.port, "skinmap calibrate"):
            hello = feed.start()
            try:
                h_u = (cfg.reconstruction.h_upper_mm if cfg else 0.0) or hello.h_upper_um / 1000.0
                h_l = (cfg.reconstruction.h_lower_mm if cfg else 0.0) or hello.h_lower_um / 1000.0
                print(f"skinmap calibrate: scanner {hello.serial_number}, {hello.n}x{hello.m}; {len(poses)} poses; "
                      f"each is taken when {args.window} scans in a row are static", flush=True)
                run = run_calibration(feed, placer, poses, hello, state_dir=state_dir, h_upper_mm=h_u, h_lower_mm=h_l,
                                      window=args.window, timeout_s=args.timeout)
            finally:
                feed.stop()
    except PortBusy as exc:
        print(f"skinmap calibrate: {exc}; nothing written", file=sys.stderr)
        return 1
    except CalibrationAborted as exc:
        print(f"skinmap calibrate: {exc}", file=sys.stderr)
        return 1
    finally:
        if emulator is not None:
            emulator.stop()
    for line in summarise(run.fit, hello.gauge_factor()):
        print(f"  {line}")
    if run.poisson is not None:
        print(f"  film Poisson ratio {run.poisson.poisson:.3f} ± {run.poisson.sd:.3f} (dome, {run.poisson.units} units; "
              f"residual {run.poisson.residual_rms:.1e} strain)")
    print(f"calibration written to {run.calibration_file}, tare to {run.tare_file} ({run.duration_s:.1f} s)")
    if emulator is not None and run.poisson is not None:
        from skinmap.emulator.scenes import ELASTIC_PARAMETERS

        print(f"  against the emulator's film: Poisson ratio {float(ELASTIC_PARAMETERS['poisson'] or 0.0):g}, "
              f"{run.poisson.poisson - float(ELASTIC_PARAMETERS['poisson'] or 0.0):+.3f} off")
    if emulator is not None:
        truth = emulator.hidden_truth()
        gf_err = run.fit.gauge_factor / truth["gauge_factor"] - 1.0
        hu_err = run.fit.h_upper_mm / truth["h_upper_mm"] - 1.0
        hl_err = run.fit.h_lower_mm / truth["h_lower_mm"] - 1.0
        print(f"  against the emulator's hidden truth: gauge factors {100 * np.sqrt(np.mean(gf_err ** 2)):.2f} % rms "
              f"(factory values {100 * np.sqrt(np.mean((hello.gauge_factor() / truth['gauge_factor'] - 1) ** 2)):.1f} %), "
              f"h_upper {100 * np.sqrt(np.mean(hu_err ** 2)):.2f} %, h_lower {100 * np.sqrt(np.mean(hl_err ** 2)):.2f} % rms")
    return 0


# ------------------------------------------------------------------------------------------
# map


def cmd_map(args: argparse.Namespace) -> int:
    from skinmap.daemon.tactile import CELL_QUANTILE, CONTACT_RIM_MM
    from skinmap.daemon.tactilemap import map_log, write_ply, write_png

    report = map_log(args.log, args.poses, estimate=args.estimate, baseline_frames=args.baseline_frames,
                     step_mm=args.step, k=args.k, min_depth_mm=args.min_depth, wall_size_mm=args.wall_size, cell_mm=args.cell,
                     reference="rim" if args.rim else args.reference, probe_length_mm=args.probe_length,
                     fit_length=args.fit_probe_length,
                     cell_quantile=CELL_QUANTILE if args.cell_quantile is None else args.cell_quantile,
                     rim_mm=CONTACT_RIM_MM if args.rim_mm is None else args.rim_mm)
    print(report.format())
    if (args.png or args.ply) and report.relief is None:
        print("skinmap map: the log holds no relief to write", file=sys.stderr)
    if args.png and report.relief is not None:
        write_png(report.relief, args.png)
        print(f"height map written to {args.png}")
    if args.ply and report.relief is not None:
        count = write_ply(report.relief, args.ply)
        print(f"{count} relief points written to {args.ply}")
    return 0


# ------------------------------------------------------------------------------------------


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="skinmap", description="skinmap shape-sensor tools")
    sub = p.add_subparsers(dest="command", required=True)

    d = sub.add_parser("demo", help="run the emulator and skinmapd on loopback with live output")
    d.add_argument("--config", help="use this config instead of the embedded demo config")
    d.add_argument("--size", default="5x5", help="emulated array, e.g. 5x5 or 16x16")
    d.add_argument("--shape", default="palm", help="emulated shape spec (see skinmap-emulator --help)")
    d.add_argument("--mechanics", choices=("kinematic", "elastic"), default="kinematic",
                   help="the emulated film's physics (see skinmap-emulator --help)")
    d.add_argument("--duration", type=float, default=0.0, help="stop after this many seconds (0 = until Ctrl-C)")
    d.add_argument("--response-tau", type=float, default=0.0, metavar="S",
                   help="the emulated gauges' first-order response time constant, s (the paper's 170 ms "
                        "response at 95 %%: 0.057; default 0, instantaneous)")
    d.add_argument("--relaxation", type=float, default=0.0, metavar="F",
                   help="the share of a held strain's reading the emulated gauges lose (the paper: 0.035; default 0)")
    d.add_argument("--verbose", "-v", action="store_true")
    d.set_defaults(func=cmd_demo)

    for name, func, helptext in (("echo", cmd_echo, "print live element positions and rates"),
                                 ("info", cmd_info, "print the daemon's device description")):
        e = sub.add_parser(name, help=helptext)
        e.add_argument("--connect", default=DEFAULT_CONNECT, help="Zenoh endpoint of skinmapd")
        e.add_argument("--prefix", default="skinmap")
        e.add_argument("--device", default="demo")
        e.add_argument("--timeout", type=float, default=5.0)
        if name == "echo":
            e.add_argument("--duration", type=float, default=0.0, help="stop after this many seconds")
        else:
            e.add_argument("--json", action="store_true")
        e.set_defaults(func=func)

    ro = sub.add_parser("router", help="run a Zenoh router for several gateways and clients")
    ro.add_argument("--listen", action="append", default=None,
                    help=f"endpoint to listen on (repeatable); default {DEFAULT_CONNECT}")
    ro.add_argument("--allow-non-loopback", action="store_true",
                    help="allow endpoints off loopback (use TLS: --zenoh-config)")
    ro.add_argument("--zenoh-config", help="Zenoh JSON5 file (TLS, access control)")
    ro.add_argument("--duration", type=float, default=0.0, help="stop after this many seconds")
    ro.set_defaults(func=cmd_router)

    ls = sub.add_parser("ls", help="list the devices alive behind a router or gateway")
    ls.add_argument("--connect", default=DEFAULT_CONNECT)
    ls.add_argument("--prefix", default="skinmap")
    ls.add_argument("--timeout", type=float, default=2.0)
    ls.set_defaults(func=cmd_ls)

    rec = sub.add_parser("record", help="record one or many gateways to MCAP from another machine")
    rec.add_argument("--connect", default=DEFAULT_CONNECT)
    rec.add_argument("--prefix", default="skinmap")
    rec.add_argument("--device", action="append", help="device to record (repeatable; default: every device)")
    rec.add_argument("--output", "-o", default="recordings", help="folder for the MCAP files")
    rec.add_argument("--duration", type=float, default=0.0, help="stop after this many seconds")
    rec.set_defaults(func=cmd_record)

    fg = sub.add_parser("foxglove", help="serve the live scene to the Foxglove app (WebSocket)")
    fg.add_argument("--connect", default=DEFAULT_CONNECT)
    fg.add_argument("--prefix", default="skinmap")
    fg.add_argument("--device", action="append", help="device to show (repeatable; default: every device)")
    fg.add_argument("--host", default="127.0.0.1", help="WebSocket host (loopback only)")
    fg.add_argument("--port", type=int, default=8765)
    fg.add_argument("--duration", type=float, default=0.0, help="stop after this many seconds")
    fg.set_defaults(func=cmd_foxglove)

    r = sub.add_parser("replay", help="re-run the pipeline from a log's raw frames")
    r.add_argument("log")
    r.add_argument("--publish", action="store_true", help="republish the results over Zenoh")
    r.add_argument("--listen", default="tcp/127.0.0.1:7448", help="Zenoh listen endpoint when publishing")
    r.add_argument("--prefix", default="skinmap-replay")
    r.add_argument("--speed", type=float, default=0.0, help="1 = recorded speed, 0 = as fast as possible")
    r.add_argument("--quiet", "-q", action="store_true")
    _add_record_limit(r)
    r.set_defaults(func=cmd_replay)

    i = sub.add_parser("inspect", help="summarise a log; optionally draw the surface")
    i.add_argument("log")
    i.add_argument("--gap", type=float, default=1.0, help="report time gaps longer than this (s)")
    i.add_argument("--png", help="write a PNG of the surface to this path")
    i.add_argument("--at", type=float, default=None, help="seconds after the log's start (default: last)")
    _add_record_limit(i)
    i.set_defaults(func=cmd_inspect)

    rc = sub.add_parser("recover", help="rewrite a cut (.mcap.active) log as a finished file")
    rc.add_argument("log")
    rc.add_argument("--output", "-o")
    _add_record_limit(rc)
    rc.set_defaults(func=cmd_recover)

    t = sub.add_parser("tare", help="record the flat sheet's resting resistances")
    t.add_argument("--config", "-c", required=True)
    t.add_argument("--scans", type=int, default=50)
    t.add_argument("--from-log", help="take the scans from a log instead of the scanner")
    t.add_argument("--at", type=float, default=0.0, help="with --from-log: seconds after the log's start")
    t.set_defaults(func=cmd_tare)

    c = sub.add_parser("calibrate", help="guided mold calibration: per-gauge gauge factors and layer offsets")
    c.add_argument("--config", "-c", help="skinmapd's config (the scanner's port and the state directory)")
    c.add_argument("--state-dir", help="write the tare and calibration here instead of the config's state directory")
    c.add_argument("--radii", type=_radii, default=(40.0, 80.0), help="mold radii, mm (default 40,80)")
    c.add_argument("--stretch", type=float, default=0.05, help="the stretching frame's strain (default 0.05)")
    c.add_argument("--dome", type=float, default=0.0, metavar="R_MM",
                   help="end with a lubricated dome of this radius (mm, e.g. 60): measures the film's Poisson ratio")
    c.add_argument("--no-stretch", action="store_true",
                   help="no stretched pose: gauge factors only, the layer offsets kept nominal")
    c.add_argument("--window", type=int, default=30, help="scans per pose, all static (default 30)")
    c.add_argument("--timeout", type=float, default=30.0, help="seconds to wait for a pose to be static")
    c.add_argument("--emulate", metavar="NxM", help="calibrate an in-process emulated scanner of this size")
    c.add_argument("--mechanics", choices=("kinematic", "elastic"), default="kinematic",
                   help="with --emulate: the molds as closed-form wraps or solved elastic films")
    c.add_argument("--seed", type=int, default=0, help="with --emulate: the device's seed")
    c.add_argument("--gf-spread", type=float, default=0.15, help="with --emulate: hidden gauge-factor spread")
    c.add_argument("--offset-spread", type=float, default=0.10, help="with --emulate: hidden layer-offset spread")
    c.add_argument("--axis-error", type=float, default=3.0, help="with --emulate: placement error of the mold axis, deg")
    c.add_argument("--offset", type=float, default=5.0, help="with --emulate: placement off the mold's centre, mm")
    c.set_defaults(func=cmd_calibrate)

    mp = sub.add_parser("map", help="stitch a log's contact events into the touched wall's relief")
    mp.add_argument("log")
    mp.add_argument("--poses", help="CSV of probe poses: x_mm, y_mm, angle_deg, depth_mm, one row a press "
                                    "(default: the log's /pose topic, else the [tactile] poses it was recorded with)")
    mp.add_argument("--estimate", action="store_true",
                    help="estimate the poses by registering each contact against the map so far (a known first "
                         "pose anchors the map; contacts whose overlap cannot decide are left out and named). "
                         "Unverified: a pressurised probe's contacts hardly fix their place (docs/tactile.md)")
    mp.add_argument("--reference", choices=("bending", "floor", "rim"), default="bending",
                    help="given poses: place each contact by its free cells' bending (default: the rim's push read "
                         "from the bending round the contact, with the probe's stiffness length), level it on the "
                         "wall's base plane where the press touched it (floor), or keep it registered by its rim")
    mp.add_argument("--rim", action="store_true", help="the same as --reference rim")
    mp.add_argument("--probe-length", type=float, default=None,
                    help="the probe's stiffness length, mm (default: the log's [tactile] probe_length_mm, else "
                         "tactile.PROBE_LENGTH_MM, 14.6, the paper's balloon)")
    mp.add_argument("--fit-probe-length", action="store_true",
                    help="the log's presses are of a flat plate at the poses' depths: fit the probe's stiffness "
                         "length on them, print it (for [tactile] probe_length_mm) and map with it")
    mp.add_argument("--baseline-frames", type=int, default=10, help="surfaces before the first press (default 10)")
    mp.add_argument("--k", type=float, default=3.0, help="contact: pressed in by more than k·σ of the baseline")
    mp.add_argument("--min-depth", type=float, default=0.5, help="contact: and by more than this, mm")
    mp.add_argument("--step", type=float, default=2.0, help="sampling of the sheet, mm")
    mp.add_argument("--wall-size", type=float, default=120.0, help="the mapped wall's side, mm")
    mp.add_argument("--cell", type=float, default=1.0, help="the relief map's cell, mm")
    mp.add_argument("--cell-quantile", type=float, default=None,
                    help="the quantile of a cell's readings (one a contact) that is its height (default "
                         "tactile.CELL_QUANTILE, 0.5, the median; 2/3, the upper third, takes back the low reading of "
                         "contacts levelled on the floor or registered by their rim)")
    mp.add_argument("--rim-mm", type=float, default=None,
                    help="each contact's outer ring left out of the map, mm (default tactile.CONTACT_RIM_MM, 0: the "
                         "whole contact)")
    mp.add_argument("--png", help="write the height and confidence maps to this PNG")
    mp.add_argument("--ply", help="write the relief's touched cells to this PLY point cloud")
    mp.set_defaults(func=cmd_map)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if getattr(args, "func", None) is cmd_router and args.listen is None:
        args.listen = [DEFAULT_CONNECT]
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        return 130
    except (OSError, ValueError, RuntimeError) as exc:
        print(f"skinmap {args.command}: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
