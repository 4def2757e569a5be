"""Turn skinmapd element poses into a USTB/UFF probe geometry, per scan.

USTB's ``uff.probe.geometry`` holds one row per element: ``[x y z theta phi width height]``
in metres and radians, where theta (azimuth) and phi (elevation) give the element's facing
direction as ``(sin(theta)*cos(phi), sin(phi), cos(theta)*cos(phi))`` -- the same angle
convention as ``uff.point``. A flat sheet facing +z therefore has theta = phi = 0.

Run against a running daemon:

    python docs/examples/uff_probe.py --connect tcp/127.0.0.1:7447 --device demo

or self-contained, with an in-process publisher of a synthetic curved array:

    python docs/examples/uff_probe.py --demo
"""

from __future__ import annotations

import argparse
import socket
import sys
import time
from contextlib import ExitStack

import numpy as np

from skinmap.client import SkinmapClient
from skinmap.wire.messages import ElementsMessage

UFF_COLUMNS = ("x", "y", "z", "theta", "phi", "width", "height")


def normal_angles(normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Azimuth theta and elevation phi (rad) of unit normals (K, 3), USTB convention."""
    normals = np.asarray(normals, dtype=float)
    if normals.ndim != 2 or normals.shape[1] != 3:
        raise ValueError(f"normals must have shape (K, 3), got {normals.shape}")
    length = np.linalg.norm(normals, axis=1)
    if np.any(~(length > 0)):
        bad = np.flatnonzero(~(length > 0))
        raise ValueError(f"normals of elements {bad.tolist()} are zero or not finite")
    n = normals / length[:, None]
    theta = np.arctan2(n[:, 0], n[:, 2])
    phi = np.arcsin(np.clip(n[:, 1], -1.0, 1.0))
    return theta, phi


def uff_probe_geometry(positions: np.ndarray, normals: np.ndarray, width_m: float,
                       height_m: float) -> np.ndarray:
    """(K, 7) USTB ``probe.geometry``: x, y, z [m], theta, phi [rad], width, height [m]."""
    positions = np.asarray(positions, dtype=float)
    if positions.ndim != 2 or positions.shape[1] != 3:
        raise ValueError(f"positions must have shape (K, 3), got {positions.shape}")
    if np.shape(normals) != positions.shape:
        raise ValueError(f"normals shape {np.shape(normals)} differs from positions shape "
                         f"{positions.shape}")
    if not (width_m > 0 and height_m > 0):
        raise ValueError(f"element width and height must be > 0 m, got {width_m}, {height_m}")
    theta, phi = normal_angles(normals)
    k = positions.shape[0]
    return np.column_stack([positions, theta, phi, np.full(k, float(width_m)),
                            np.full(k, float(height_m))])


def probe_from_message(message: ElementsMessage, width_m: float,
                       height_m: float) -> np.ndarray:
    """Probe geometry of one decoded elements message (use ``message.valid`` to apodise)."""
    return uff_probe_geometry(message.positions, message.normals, width_m, height_m)


def format_probe(geometry: np.ndarray, valid: np.ndarray | None = None) -> str:
    """Human-readable table: positions in mm, angles in degrees."""
    lines = [f"{'elem':>4} {'x mm':>9} {'y mm':>9} {'z mm':>9} {'theta deg':>9} {'phi deg':>8} "
             f"{'w mm':>6} {'h mm':>6}"]
    for i, (x, y, z, th, ph, w, h) in enumerate(geometry):
        flag = "" if valid is None or valid[i] else "  (invalid)"
        lines.append(f"{i:>4} {x*1e3:9.3f} {y*1e3:9.3f} {z*1e3:9.3f} {np.degrees(th):9.3f} "
                     f"{np.degrees(ph):8.3f} {w*1e3:6.2f} {h*1e3:6.2f}{flag}")
    return "\n".join(lines)


def _start_demo(stack: ExitStack, endpoint: str, device: str) -> None:
    """Publish a cylindrical 4 x 8 array (radius 40 mm, pitch 6 mm) in-process."""
    from skinmap.wire import messages
    from skinmap.daemon.zenoh_io import SkinmapPublisher, make_session_config, open_session

    rows, cols, pitch, radius = 4, 8, 0.006, 0.040
    u = (np.arange(cols) - (cols - 1) / 2) * pitch
    v = (np.arange(rows) - (rows - 1) / 2) * pitch
    uu, vv = np.meshgrid(u, v)
    angle = (uu / radius).ravel()
    positions = np.column_stack([radius * np.sin(angle), vv.ravel(),
                                 radius * (np.cos(angle) - 1.0)])
    normals = np.column_stack([np.sin(angle), np.zeros_like(angle), np.cos(angle)])
    k = rows * cols
    payload = messages.encode_elements(1, 0, time.time_ns(), positions, normals,
                                       np.full(k, 5e-5),
                                       np.full(k, messages.ElementFlag.VALID, np.uint8))
    info = {"device": device, "rows": rows, "cols": cols, "pitch_m": pitch,
            "elements": {"count": k, "width_m": 0.005, "height_m": 0.005},
            "calibration": {}, "versions": {"skinmap": "demo"}}
    session = stack.enter_context(open_session(make_session_config([endpoint], [])))
    publisher = stack.enter_context(SkinmapPublisher(session, "skinmap", device))
    publisher.set_info(info)
    publisher.publish_elements(payload)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--connect", default="tcp/127.0.0.1:7447")
    parser.add_argument("--prefix", default="skinmap")
    parser.add_argument("--device", default="demo")
    parser.add_argument("--width", type=float, help="element width, m (default: from info)")
    parser.add_argument("--height", type=float, help="element height, m (default: from info)")
    parser.add_argument("--scans", type=int, default=1, help="scans to print")
    parser.add_argument("--timeout", type=float, default=3.0)
    parser.add_argument("--demo", action="store_true", help="run an in-process publisher")
    args = parser.parse_args(argv)

    with ExitStack() as stack:
        if args.demo:
            with socket.socket() as s:
                s.bind(("127.0.0.1", 0))
                args.connect = f"tcp/127.0.0.1:{s.getsockname()[1]}"
            _start_demo(stack, args.connect, args.device)
        try:
            client = stack.enter_context(
                SkinmapClient([args.connect], prefix=args.prefix, device=args.device))
            width, height = args.width, args.height
            if width is None or height is None:
                layout = client.info(timeout=args.timeout)["elements"]
                width = layout.get("width_m") if width is None else width
                height = layout.get("height_m") if height is None else height
                if width is None or height is None:
                    raise ValueError("the device info gives no element width/height_m: "
                                     "pass --width and --height")
            # The first scan comes from the latest-value cache; later ones live.
            message = client.latest("elements", timeout=args.timeout)
            for scan in range(args.scans):
                if scan:
                    message = client.elements(timeout=args.timeout)
                geometry = probe_from_message(message, width, height)
                print(f"scan {message.seq}: {message.count} elements, "
                      f"{int(message.valid.sum())} valid")
                print(format_probe(geometry, message.valid))
        except (LookupError, TimeoutError, ValueError) as exc:
            print(f"uff_probe: {exc}", file=sys.stderr)
            return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
