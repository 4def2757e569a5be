"""Accuracy of skinmapd's frame pipeline on the emulated device, against the emulator's truth.

The emulated scanner (its electrical model: gauge noise, drift, ADC, and the gauges' hysteresis
unless --hysteresis off) reads a shape that moves; every scan (or one at the output rate) goes
through ``FramePipeline`` in process as skinmapd runs it: the warm chains, the deferred cold fits
and their catch-up chains (inline, so the run is the same on every machine), the restart every
64 scans.  Each frame's cell centres are compared with the shape's truth at the scan's time (all
units read at one instant here, so that a moving shape has one truth a frame):

- mean node error after the best rigid alignment (mean over frames, and the largest frame's);
- frames with some node beyond 3 σ + 0.05 mm (σ the published node σ), and the largest ratio
  (a frame flagged ambiguous by the better of its answer and its mirror);
- frames the pipeline answered while deferring their cold graph fit (DEGRADED).

Shapes (kinematic, ``skinmap.emulator.physics``): the palm gesture (flat → cylinder → bump →
saddle, held 1 s each, 1 s transitions), its radii and bump width grown with the sheet; and the
same shapes held still after a press from flat (``--held``): the gauges' hysteresis reads them
on its loading branch, about 2 % low (docs/reconstruction.md, "A gain the gauges share"); with
``--mechanics elastic`` the held shapes are elastic films laminated on molds of those shapes
(``skinmap.emulator.scenes``, solved once and cached).

    .venv/bin/python bench/pipeline_accuracy.py [--sizes 5,8,12,16] [--outputs 0,10] [--seconds 8]
        [--hysteresis on,off] [--held [--mechanics elastic]] [--seed 0] [--lead-scans 1]
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402
from threadpoolctl import threadpool_limits  # noqa: E402

from emulated_pipeline import SCAN_RATE, emulated_device, emulated_pipeline, emulated_scans  # noqa: E402
from reconstruction import node_errors  # noqa: E402
from skinmap.emulator import physics as ph  # noqa: E402
from skinmap.emulator import scenes  # noqa: E402
from skinmap.daemon.config import OutputConfig  # noqa: E402
from skinmap.emulator.electrical import ElectricalConfig  # noqa: E402
from skinmap import strains  # noqa: E402


def palm_spec(n: int) -> str:
    """The palm gesture for an n×n sheet: 5×5 the emulator's default, larger sheets with radii
    and the bump's width grown so that they bend as far."""
    if n <= 5:
        return "palm"
    scale = n / 5.0
    return f"palm:radius={40.0 * scale:g},fwhm={min(24.0 * scale, 48.0):g}"


def held_specs(n: int) -> list[tuple[str, str]]:
    """Shapes pressed from flat and held: (label, spec with a ramp from flat over 1 s)."""
    s = n / 5.0
    return [("cylinder", f"cylinder:radius={50 * s:g}"), ("sphere", f"sphere:radius={70 * s:g}"),
            ("saddle", f"saddle:radius={80 * s:g},axis_angle=20"),
            ("bump", f"gaussian:height=4,fwhm={20 * min(s, 2):g}")]


def run(n: int, shape: ph.Shape, seconds: float, output_rate: float, hysteresis: bool,
        ramp_s: float = 0.0, seed: int = 0, lead_scans: int = OutputConfig().lead_scans,
        response_tau_s: float = 0.0, response_lag_s: float = strains.RESPONSE_LAG_S, relaxation: float = 0.0,
        relaxation_tau_s: float = 10.0, gf_spread: float = 0.0) -> dict:
    """One run of the pipeline over ``shape`` (scaled from flat over ``ramp_s`` seconds, then
    held, where ``ramp_s`` > 0); ``seed``: the emulated device's (noise, calibration);
    ``lead_scans``: skinmapd's `[output] lead_scans` (reconstructed, not judged);
    ``response_tau_s``: the emulated gauges' first-order response lag (0: none);
    ``response_lag_s``: the lag bound the pipeline carries into σ (0: none); ``relaxation``,
    ``relaxation_tau_s``: the emulated gauges' relaxation under a held strain (0: none);
    ``gf_spread``: the relative s.d. of the device's true gauge factors about those it reports."""
    electrical = ElectricalConfig() if hysteresis else ElectricalConfig().without("hysteresis")
    electrical = replace(electrical, response_tau_s=response_tau_s, relaxation=relaxation,
                         relaxation_tau_s=relaxation_tau_s)
    device, spec = emulated_device(n, shape, electrical, seed, scan_rate=SCAN_RATE, gf_spread=gf_spread)
    pipe = emulated_pipeline(device, spec, response_lag_s=response_lag_s)
    pipe.prepare()
    step = 1 if output_rate == 0 else max(1, round(SCAN_RATE / output_rate))
    errs, ratios, deferred, sigmas = [], [], 0, []
    with threadpool_limits(1):
        for k, t, resistances in emulated_scans(device, spec, seconds, every=step, ramp_s=ramp_s, lead=lead_scans):
            result = pipe.process(resistances, k, round(t * 1e6), 0, lead=bool(k % step))
            if k % step:
                continue  # a lead scan: not published
            if ramp_s > 0 and t < ramp_s + 0.2:
                continue  # judged held
            truth = ph.ground_truth(shape, n, n, spec.pitch_mm, t=t).nodes
            bound = 3.0 * result.node_sigma_mm.reshape(-1) + 0.05
            # a frame flagged ambiguous is judged by the better of its two answers
            mirror = getattr(result.surface, "mirror", None)
            answers = [result.nodes_mm] + ([mirror.nodes] if mirror is not None else [])
            e = min((node_errors(a, truth) for a in answers), key=lambda x: float(x.mean()))
            errs.append(float(e.mean()))
            ratios.append(float(np.max(e / bound)))
            sigmas.append(float(np.median(result.node_sigma_mm)))
            deferred += bool(result.diagnostics.get("graph_deferred"))
    r = np.array(ratios)
    return {"frames": len(errs), "mean": float(np.mean(errs)), "largest": float(np.max(errs)),
            "beyond": int(np.sum(r > 1.0)), "worst": float(r.max()), "deferred": deferred,
            "sigma": float(np.mean(sigmas))}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", default="5,8,12,16")
    ap.add_argument("--outputs", default="0,10", help="output rates, Hz (0 = every scan)")
    ap.add_argument("--seconds", type=float, default=8.0, help="seconds of the gesture (one cycle: 8)")
    ap.add_argument("--hysteresis", default="on,off", help="the gauges' hysteresis: on, off or both")
    ap.add_argument("--held", action="store_true", help="shapes pressed from flat over 1 s and held (--hold, 2 s) instead")
    ap.add_argument("--shape", default=None,
                    help="a moving shape spec instead of the palm gesture (skinmap.emulator.physics), "
                         "as given at every size")
    ap.add_argument("--mechanics", choices=("kinematic", "elastic"), default="kinematic",
                    help="the held shapes as kinematic sheets or elastic films on molds")
    ap.add_argument("--seed", type=int, default=0, help="the emulated device's seed (gauge noise, calibration)")
    ap.add_argument("--lead-scans", type=int, default=OutputConfig().lead_scans,
                    help="skinmapd's [output] lead_scans: scans reconstructed before each one due, not judged")
    ap.add_argument("--response-tau", type=float, default=0.0,
                    help="the emulated gauges' first-order response lag τ, s (0: none; the paper's 170 ms "
                         "response as 95 %% of a step: 0.057)")
    ap.add_argument("--response-time-ms", type=float, default=strains.RESPONSE_TIME_S * 1e3,
                    help="[reconstruction] response_time_ms: the lag bound the pipeline carries into σ "
                         "(a third of it; 0 leaves it out)")
    ap.add_argument("--relaxation", type=float, default=0.0,
                    help="the emulated gauges' relaxation: the share of a held strain's reading lost "
                         "(the paper: 0.035; 0: none)")
    ap.add_argument("--relaxation-tau", type=float, default=10.0, help="its time constant, s")
    ap.add_argument("--hold", type=float, default=2.0, help="with --held: seconds each shape is held")
    ap.add_argument("--gf-spread", type=float, default=0.0,
                    help="the relative s.d. of the device's true gauge factors about those it reports (an "
                         "uncalibrated or aged device; 0: they are true)")
    args = ap.parse_args(argv)
    sizes = [int(x) for x in args.sizes.split(",")]
    outputs = [float(x) for x in args.outputs.split(",")]
    modes = [x.strip() == "on" for x in args.hysteresis.split(",")]
    print(f"skinmapd's frame pipeline on the emulated device ({SCAN_RATE:g} scans/s), errors against the truth "
          f"(mean node error after the best rigid alignment; beyond: frames with some node off by more than "
          f"3 σ + 0.05 mm; σ: the frames' median node σ, mean over frames; device seed {args.seed}; "
          f"the gauges' response lag τ {1e3 * args.response_tau:g} ms, σ's lag bound "
          f"{1e3 * strains.response_lag_s(args.response_time_ms * 1e-3):.3g} ms; relaxation {args.relaxation:g}, τ {args.relaxation_tau:g} s; "
          f"gauge factors off by {100 * args.gf_spread:g} % s.d.)")
    print(f"{'sheet':>7s} {'shape':10s} {'output':>10s} {'hysteresis':>10s} {'frames':>6s} {'mean mm':>8s} "
          f"{'largest':>8s} {'beyond':>7s} {'worst':>6s} {'σ mm':>6s} {'deferred':>8s} {'s':>5s}")
    for n in sizes:
        cases = ([(label, scenes.parse_scene_spec(spec, args.mechanics, n, n, 12.0), 1.0 + args.hold, 1.0)
                  for label, spec in held_specs(n)] if args.held
                 else [(args.shape.split(":")[0], ph.parse_shape_spec(args.shape), args.seconds, 0.0)] if args.shape
                 else [("palm", ph.parse_shape_spec(palm_spec(n)), args.seconds, 0.0)])
        for label, shape, seconds, ramp in cases:
            for output in outputs:
                for hysteresis in modes:
                    t0 = time.perf_counter()
                    row = run(n, shape, seconds, output, hysteresis, ramp, args.seed, args.lead_scans,
                              args.response_tau, strains.response_lag_s(args.response_time_ms * 1e-3), args.relaxation,
                              args.relaxation_tau, args.gf_spread)
                    mode = "every scan" if output == 0 else f"{output:g} Hz"
                    print(f"{n:>3d}x{n:<3d} {label:10s} {mode:>10s} {'on' if hysteresis else 'off':>10s} "
                          f"{row['frames']:6d} {row['mean']:8.4f} {row['largest']:8.3f} "
                          f"{row['beyond']:>3d}/{row['frames']:<3d} {row['worst']:6.2f} {row['sigma']:6.3f} {row['deferred']:8d} "
                          f"{time.perf_counter() - t0:5.0f}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
