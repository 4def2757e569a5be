"""Calibration benchmark: the mold procedure on emulated devices with hidden gauge-factor and
layer-offset spreads, and the reconstruction error before and after.

Run: .venv/bin/python bench/calibration.py [--devices 3] [--shapes 2] [--mechanics kinematic|elastic] [--size 5]

Per device (seeded; hidden truths: gauge factors 15 % and layer offsets 10 % (s.d.) away from
what HELLO and the nominal 0.2 mm say): the whole `skinmap calibrate` procedure against the
in-process emulator over its loopback serial link (10 poses: flat, 5 % stretch, cylinders of
±40 and ±80 mm along the rows and the columns, each placed with the mold axis off by up to 3°
and off-centre by up to 5 mm), timed; the fitted gauge factors and offsets against the hidden
truth (rms of the relative errors).  Then, with the emulator's full electrical model (noise,
hysteresis, drift, ADC), the mean node error after the best rigid alignment on the shapes of
bench/reconstruction.py (--shapes per class) with (a) the factory values of HELLO and the tare,
(b) the calibration, (c) the hidden truth ("perfect").
"""
from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from threadpoolctl import threadpool_limits  # noqa: E402

from skinmap.daemon.calibrate import EmulatedPlacer, LinkFeed, run_calibration  # noqa: E402
from skinmap.strains import Calibration, resistances_to_strains, to_nominal_offsets  # noqa: E402
from skinmap.daemon.config import ScannerSpec as LinkConfig  # noqa: E402
from skinmap.daemon.moldcal import standard_poses  # noqa: E402
from skinmap.emulator import physics as ph  # noqa: E402
from skinmap.emulator.device import Device, ScannerSpec  # noqa: E402
from skinmap.emulator.emulator import Emulator  # noqa: E402
from skinmap.emulator.transport import TcpTransport  # noqa: E402
from skinmap.reconstruction import reconstruct  # noqa: E402
from skinmap.reconstruction.linalg import aligned_distances  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
import reconstruction as rb  # noqa: E402  (bench/reconstruction.py: the benchmark's shape classes)

PITCH, H = 12.0, 0.2


def calibrate_device(cfg: ScannerSpec, mechanics: str, state: Path) -> tuple[object, float, dict]:
    emu = Emulator(cfg, ph.Flat(), TcpTransport(0))
    placer = EmulatedPlacer(emu, mechanics, cfg.seed)
    poses = standard_poses()
    placer.prepare(poses)  # scenes solved before the clock starts (elastic solves are cached)
    emu.start()
    feed = LinkFeed(LinkConfig(port=emu.transport.url, scan_rate_hz=cfg.scan_rate_hz))
    try:
        hello = feed.start()
        t0 = time.perf_counter()
        run = run_calibration(feed, placer, poses, hello, state_dir=state, h_upper_mm=H, h_lower_mm=H,
                              say=lambda _s: None)
        took = time.perf_counter() - t0
    finally:
        feed.stop()
        emu.stop()
    return run, took, emu.hidden_truth()


def node_error(dev: Device, shape: ph.Shape, cal: Calibration, kw: dict, t: float) -> float:
    c = dev.config
    dev.set_shape(shape)
    strain = dev.strains(0.0)
    dev.readout.read(np.zeros_like(strain), t - 0.1)  # from rest, as a shape forms
    wire = dev.readout.read(strain, t)
    eu, el, _ = resistances_to_strains(wire.astype(float) * 1e-6, cal)
    if cal.h_upper_mm is not None:
        eu, el = to_nominal_offsets(eu, el, cal.h_upper_mm, cal.h_lower_mm, H, H)
    surf = reconstruct(eu, el, PITCH, H, H, **kw)
    truth = ph.ground_truth(shape, c.n, c.m, PITCH).nodes
    return float(np.mean(aligned_distances(surf.nodes.reshape(-1, 3), truth.reshape(-1, 3))))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--devices", type=int, default=3)
    ap.add_argument("--shapes", type=int, default=2, help="shapes per class of bench/reconstruction.py")
    ap.add_argument("--mechanics", choices=("kinematic", "elastic"), default="kinematic")
    ap.add_argument("--size", type=int, default=5)
    args = ap.parse_args()
    n = args.size
    print(f"Mold calibration, {n}x{n}, {args.mechanics} molds, hidden spreads: gauge factor 15 %, layer offsets 10 %")
    head = f"{'device':>7s} {'time s':>7s} {'GF err factory':>15s} {'GF err cal':>11s} {'h_u err':>8s} {'h_l err':>8s} {'fit s.d. GF':>12s}"
    print(head)
    print("-" * len(head))
    results = []
    with tempfile.TemporaryDirectory() as tmp, threadpool_limits(1):
        for d in range(args.devices):
            cfg = ScannerSpec(n=n, m=n, scan_rate_hz=50.0, seed=100 + d, gf_spread=0.15, offset_spread=0.10)
            run, took, truth = calibrate_device(cfg, args.mechanics, Path(tmp) / str(d))
            fit = run.fit
            dev = Device(cfg, ph.Flat())
            gf0 = dev.calibration.gauge_factor
            e_fac = np.sqrt(np.mean((gf0 / truth["gauge_factor"] - 1) ** 2))
            e_gf = np.sqrt(np.mean((fit.gauge_factor / truth["gauge_factor"] - 1) ** 2))
            e_hu = np.sqrt(np.mean((fit.h_upper_mm / truth["h_upper_mm"] - 1) ** 2))
            e_hl = np.sqrt(np.mean((fit.h_lower_mm / truth["h_lower_mm"] - 1) ** 2))
            sd = np.nanmedian(fit.gauge_factor_sd / fit.gauge_factor)
            print(f"{d:7d} {took:7.1f} {100 * e_fac:14.1f}% {100 * e_gf:10.2f}% {100 * e_hu:7.2f}% {100 * e_hl:7.2f}% "
                  f"{100 * sd:11.3f}%")
            r0 = dev.calibration.base_resistance_ohm
            cals = {
                "factory": Calibration(gf0, run.tare_ohm),
                "calibrated": Calibration(fit.gauge_factor, run.tare_ohm, "cal", fit.h_upper_mm, fit.h_lower_mm),
                "perfect": Calibration(truth["gauge_factor"], r0, "truth", truth["h_upper_mm"], truth["h_lower_mm"]),
            }
            results.append((dev, cals))
    print("(GF err cal includes the gauges' hysteresis: a pose approached from rest reads on the loading branch, "
          "(1 - H/2) = 0.98 of the strain, so the fit finds the loading-branch gauge factor, 2 % below the truth)")

    classes = rb.shape_classes(np.random.default_rng(0), args.shapes)
    print(f"\nMean node error (mm, after rigid alignment), {args.devices} devices x {args.shapes} shapes per class, "
          "full electrical model")
    head = f"{'shape class':46s} {'factory':>8s} {'calibrated':>11s} {'perfect':>8s} {'cal/perfect':>12s}"
    print(head)
    print("-" * len(head))
    ratios = []
    with threadpool_limits(1):
        for title, shapes in classes.items():
            errs = {k: [] for k in ("factory", "calibrated", "perfect")}
            t = 1.0
            for dev, cals in results:
                for shape, kw in shapes:
                    for k, cal in cals.items():
                        t += 1.0
                        errs[k].append(node_error(dev, shape, cal, kw, t))
            m = {k: float(np.mean(v)) for k, v in errs.items()}
            ratio = m["calibrated"] / m["perfect"] if m["perfect"] > 0 else float("nan")
            ratios.append(ratio)
            print(f"{title:46s} {m['factory']:8.3f} {m['calibrated']:11.3f} {m['perfect']:8.3f} {ratio:12.2f}")
    print(f"(classes with calibrated within 1.5x of perfect: {sum(r <= 1.5 for r in ratios)}/{len(ratios)})")


if __name__ == "__main__":
    main()
