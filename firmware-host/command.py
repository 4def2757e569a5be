"""``skinmap-emulator``: run an emulated scanner on a pseudo-terminal or a loopback TCP port.

    skinmap-emulator --size 5x5 --shape "gaussian:height=4,fwhm=18,u0=3,v0=-2" --rate 10
    skinmap-emulator --size 16x16 --shape palm --tcp 5799 --truth-file truth.jsonl
    skinmap-emulator --shape "gaussian:height=4,fwhm=18,u0=3" --mechanics elastic
    skinmap-emulator --shape cylinder:radius=40 --garbage-rate 2 --bit-flip-rate 1e-5 \\
        --disconnect-every 20 --disconnect-for 3 --dead-gauge upper,row,2,3
"""
from __future__ import annotations

import argparse
import json
import re
import signal
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from skinmap.emulator.device import ScannerSpec
from skinmap.emulator.electrical import ElectricalConfig
from skinmap.emulator.emulator import Emulator, FaultSchedule
from skinmap.emulator.linkfaults import LinkFaults
from skinmap.emulator.mechanics import MechanicsError
from skinmap.emulator.physics import SHAPE_KINDS
from skinmap.emulator.scenes import cache_directory, parse_scene_spec
from skinmap.emulator.transport import DEFAULT_LINK, PtyTransport, TcpTransport

_LAYERS = {"upper": 0, "u": 0, "0": 0, "lower": 1, "l": 1, "1": 1}
_DIRECTIONS = {"row": 0, "r": 0, "x": 0, "0": 0, "col": 1, "column": 1, "c": 1, "y": 1, "1": 1}


def parse_size(text: str) -> tuple[int, int]:
    m = re.fullmatch(r"\s*(\d+)\s*[xX×]\s*(\d+)\s*", text)
    if not m:
        raise argparse.ArgumentTypeError(f"size must look like 5x5 (rows x cols), got {text!r}")
    return int(m.group(1)), int(m.group(2))


def parse_gauge(text: str) -> tuple[int, int, int, int]:
    """'layer,direction,row,col', e.g. 'upper,row,2,3' or '0,0,2,3'."""
    parts = [p.strip().lower() for p in text.split(",")]
    if len(parts) != 4:
        raise argparse.ArgumentTypeError(
            f"gauge must be layer,direction,row,col (e.g. upper,row,2,3), got {text!r}"
        )
    if parts[0] not in _LAYERS:
        raise argparse.ArgumentTypeError(f"gauge layer must be upper or lower, got {parts[0]!r}")
    if parts[1] not in _DIRECTIONS:
        raise argparse.ArgumentTypeError(f"gauge direction must be row or col, got {parts[1]!r}")
    try:
        i, j = int(parts[2]), int(parts[3])
    except ValueError:
        raise argparse.ArgumentTypeError(f"gauge row and col must be integers, got {text!r}") from None
    return _LAYERS[parts[0]], _DIRECTIONS[parts[1]], i, j


def parse_elements(text: str) -> np.ndarray:
    """'u,v;u,v;...' material coordinates (mm) of elements to report in the truth file."""
    try:
        pts = [[float(x) for x in item.split(",")] for item in text.split(";") if item.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"elements must be 'u,v;u,v;...' in mm, got {text!r}") from None
    if not pts or any(len(p) != 2 for p in pts):
        raise argparse.ArgumentTypeError(f"elements must be 'u,v;u,v;...' in mm, got {text!r}")
    return np.array(pts)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="skinmap-emulator",
        description="Emulated skinmap scanner (firmware + sensor physics) on a pty or loopback TCP.",
    )
    g = p.add_argument_group("sensor")
    g.add_argument("--size", type=parse_size, help="array size ROWSxCOLS (default 5x5)")
    g.add_argument("--rows", type=int, help="rows N (2..32)")
    g.add_argument("--cols", type=int, help="columns M (2..32)")
    g.add_argument("--pitch", type=float, default=12.0, help="cell pitch, mm (default 12)")
    g.add_argument("--shape", default="flat",
                   help=f"shape spec kind[:key=value,...], kinds: {', '.join(SHAPE_KINDS)}; "
                        "graph shapes add with '+' (default flat); with --mechanics elastic also "
                        "poisson, friction, prestretch, prestretch_u/_v, mesh, keyframes, "
                        "finger_radius, tension, tape, indenter, relief (firmware-host/README.md)")
    g.add_argument("--mechanics", choices=("kinematic", "elastic"), default="kinematic",
                   help="kinematic: the shape's closed-form map (default); elastic: the film solved as an "
                        "elastic sheet on the mold / under the indenters (solved once, cached in "
                        f"{cache_directory()})")
    g.add_argument("--rate", type=float, default=10.0, help="scan rate at boot, scans/s (default 10)")
    g.add_argument("--max-step-rate", type=float, default=4000.0,
                   help="DAQ TDM step-rate limit, steps/s (max scan rate = this / 2·min(N,M))")
    g.add_argument("--seed", type=int, default=0, help="seed of calibration, noise and faults")
    g.add_argument("--gf-spread", type=float, default=0.0, metavar="S",
                   help="hidden truth: relative s.d. of the true gauge factors about HELLO's (e.g. 0.15)")
    g.add_argument("--offset-spread", type=float, default=0.0, metavar="S",
                   help="hidden truth: relative s.d. of each unit's true layer offsets (e.g. 0.10)")
    g.add_argument("--ideal", action="store_true", help="no hysteresis, drift, noise or ADC quantisation")
    g.add_argument("--no-noise", action="store_true")
    g.add_argument("--no-hysteresis", action="store_true")
    g.add_argument("--no-drift", action="store_true")
    g.add_argument("--response-tau", type=float, default=0.0, metavar="S",
                   help="first-order gauge response time constant, s (default 0: instantaneous)")
    g.add_argument("--relaxation", type=float, default=0.0, metavar="F",
                   help="share of a held strain's reading lost as the gauge relaxes (the paper: 0.035; default 0)")
    g.add_argument("--relaxation-tau", type=float, default=10.0, metavar="S",
                   help="the relaxation's time constant, s (default 10)")

    g = p.add_argument_group("link")
    x = g.add_mutually_exclusive_group()
    x.add_argument("--pty", action="store_true", help="serve a pseudo-terminal (default)")
    x.add_argument("--tcp", type=int, metavar="PORT", help="serve TCP on 127.0.0.1:PORT (0 = any free port)")
    g.add_argument("--link", type=Path, default=DEFAULT_LINK, help=f"stable symlink to the pty (default {DEFAULT_LINK})")

    g = p.add_argument_group("faults")
    g.add_argument("--garbage-rate", type=float, default=0.0, help="garbage bursts per second")
    g.add_argument("--bit-flip-rate", type=float, default=0.0, help="probability per byte of a bit flip")
    g.add_argument("--drop-rate", type=float, default=0.0, help="probability per byte of losing it")
    g.add_argument("--stall-every", type=float, default=0.0, metavar="S")
    g.add_argument("--stall-for", type=float, default=0.0, metavar="X", help="stall length, s")
    g.add_argument("--disconnect-every", type=float, default=0.0, metavar="S")
    g.add_argument("--disconnect-for", type=float, default=0.0, metavar="Y",
                   help="seconds until a new port appears behind the same name")
    g.add_argument("--reboot-every", type=float, default=0.0, metavar="S", help="watchdog reboot period")
    g.add_argument("--dead-gauge", type=parse_gauge, action="append", default=[],
                   metavar="L,D,I,J", help="open-circuit gauge, e.g. upper,row,2,3 (repeatable)")
    g.add_argument("--saturated-gauge", type=parse_gauge, action="append", default=[],
                   metavar="L,D,I,J", help="saturated gauge (repeatable)")

    g = p.add_argument_group("output")
    g.add_argument("--truth-file", type=Path, help="write ground truth as JSON lines, one per scan sent")
    g.add_argument("--hidden-truth-file", type=Path,
                   help="write the device's hidden truths (true gauge factors, layer offsets) as JSON")
    g.add_argument("--elements", type=parse_elements, help="element material coordinates 'u,v;u,v' for the truth file")
    g.add_argument("--duration", type=float, help="stop after this many seconds")
    g.add_argument("--status-every", type=float, default=5.0, help="status line period, s (0: none)")
    return p


def config_from_args(args: argparse.Namespace, parser: argparse.ArgumentParser) -> tuple[ScannerSpec, np.ndarray, np.ndarray]:
    n, m = args.size if args.size else (5, 5)
    if args.size and (args.rows or args.cols):
        parser.error("give either --size or --rows/--cols")
    n = args.rows or n
    m = args.cols or m
    elec = ElectricalConfig.ideal() if args.ideal else ElectricalConfig()
    off = [e for e, flag in (("noise", args.no_noise), ("hysteresis", args.no_hysteresis), ("drift", args.no_drift)) if flag]
    if off:
        elec = elec.without(*off)
    try:
        elec = replace(elec, response_tau_s=args.response_tau, relaxation=args.relaxation,
                       relaxation_tau_s=args.relaxation_tau)
    except ValueError as exc:
        parser.error(str(exc))
    try:
        cfg = ScannerSpec(n=n, m=m, pitch_mm=args.pitch, scan_rate_hz=args.rate,
                           max_step_rate_hz=args.max_step_rate, seed=args.seed, electrical=elec,
                           gf_spread=args.gf_spread, offset_spread=args.offset_spread)
    except ValueError as exc:
        parser.error(str(exc))
    masks = []
    for what, gauges in (("--dead-gauge", args.dead_gauge), ("--saturated-gauge", args.saturated_gauge)):
        mask = np.zeros((2, 2, n, m), dtype=bool)
        for l, d, i, j in gauges:
            if not (0 <= i < n and 0 <= j < m):
                parser.error(f"{what} row {i}, col {j} is outside the {n}x{m} array")
            mask[l, d, i, j] = True
        masks.append(mask)
    return cfg, masks[0], masks[1]


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    cfg, dead, saturated = config_from_args(args, parser)
    try:
        if args.mechanics == "elastic":
            print(f"skinmap-emulator: solving the elastic scene {args.shape!r} "
                  f"(cached in {cache_directory()})", flush=True)
        shape = parse_scene_spec(args.shape, args.mechanics, cfg.n, cfg.m, cfg.pitch_mm)
        if args.elements is not None:
            shape.position(args.elements)  # an element off the film is an error now, not mid-run
        faults = LinkFaults(garbage_rate_hz=args.garbage_rate, bit_flip_rate=args.bit_flip_rate,
                            drop_rate=args.drop_rate)
        schedule = FaultSchedule(stall_every_s=args.stall_every, stall_for_s=args.stall_for,
                                 disconnect_every_s=args.disconnect_every,
                                 disconnect_for_s=args.disconnect_for, reboot_every_s=args.reboot_every)
        transport = TcpTransport(args.tcp) if args.tcp is not None else PtyTransport(args.link)
    except (ValueError, MechanicsError) as exc:
        parser.error(str(exc))
    if args.duration is not None and not args.duration > 0:
        parser.error(f"--duration must be > 0 s, got {args.duration}")

    emu = Emulator(cfg, shape, transport, faults, schedule, args.truth_file, args.elements)

    def on_signal(signum, frame):  # noqa: ARG001
        emu.request_stop()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    try:
        emu.open()
    except OSError as exc:
        print(f"skinmap-emulator: cannot open the link: {exc}", file=sys.stderr)
        return 1
    device = emu.device
    assert device is not None  # open() created it
    if args.hidden_truth_file is not None:
        truth = {k: v.tolist() for k, v in emu.hidden_truth().items()}
        args.hidden_truth_file.write_text(json.dumps({"serial": device.serial_number, **truth}), encoding="utf-8")
    emu.set_open(dead)
    emu.set_saturated(saturated)
    where = transport.url if isinstance(transport, TcpTransport) else f"{transport.link} -> {transport.path}"
    print(f"skinmap-emulator: {cfg.n}x{cfg.m} pitch {cfg.pitch_mm:g} mm, shape {shape!r}, "
          f"{cfg.scan_rate_hz:g} scans/s (max {cfg.max_scan_rate_hz:g}), serial {device.serial_number}",
          flush=True)
    print(f"skinmap-emulator: serving {where}", flush=True)

    def tick(e: Emulator) -> None:
        print(e.status_line(), flush=True)

    emu.run(args.duration, tick if args.status_every > 0 else None, args.status_every or 1.0)
    print("skinmap-emulator: stopped; " + emu.status_line(), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
