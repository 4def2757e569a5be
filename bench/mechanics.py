"""Cost of the elastic-sheet solves: wall time, Newton steps and mesh per scene.

Every scene is solved afresh (the disk cache is bypassed), on one core (BLAS threads 1).

    .venv/bin/python bench/mechanics.py                 # 5x5 and 16x16 molds
    .venv/bin/python bench/mechanics.py --sizes 5 --moving   # also the moving 5x5 scenes (minutes)
"""
from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import re  # noqa: E402
import time  # noqa: E402

from skinmap.emulator import mechanics as mc  # noqa: E402
from skinmap.emulator.scenes import parse_scene_spec  # noqa: E402

# radii {in braces} are for 5×5 and grow as N/5: a mold is a height field, so a larger film
# needs a flatter mold (the same bend angle across it)
MOLDS = [
    "flat:prestretch=0.05",
    "cylinder:radius={40},axis_angle=30",
    "sphere:radius={60}",
    "sphere:radius={60},prestretch=0.05",
    "gaussian:height=4,fwhm=18,u0=3,v0=-2",
    "gaussian:height=4,fwhm=18,u0=30,v0=-20 + gaussian:height=-3,fwhm=20,u0=-25,v0=15",
    "saddle:radius={60},axis_angle=20",
]
MOVING = [
    "membrane:fingers=1",
    "membrane:fingers=2",
    "balloon",
    "palm",
]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="5,16", help="N of the N×N arrays (default 5,16)")
    ap.add_argument("--moving", action="store_true", help="also the moving scenes (5×5 only)")
    args = ap.parse_args()
    sizes = [int(s) for s in args.sizes.split(",")]
    print(f"{'scene':42s} {'array':>6s} {'nodes':>8s} {'frames':>6s} {'newton':>7s} {'solve s':>8s} {'s/frame':>8s}")
    calls: list[mc.Solution] = []
    original = mc.solve

    def counting(*a, **kw):
        sol = original(*a, **kw)
        calls.append(sol)
        return sol

    mc.solve = counting  # count the Newton steps of every solve the scene makes
    try:
        for n in sizes:
            scale = max(1.0, n / 5.0)
            molds = [re.sub(r"\{(\d+)\}", lambda mt: f"{float(mt.group(1)) * scale:g}", spec) for spec in MOLDS]
            for spec in molds + (MOVING if args.moving and n <= 5 else []):
                calls.clear()
                t0 = time.perf_counter()
                shape = parse_scene_spec(spec, "elastic", n, n, 12.0, cache=False)
                dt = time.perf_counter() - t0
                grid = shape.grid
                frames = getattr(shape, "times", [0.0])
                print(f"{spec:42s} {n:>3d}x{n:<2d} {grid.nv * grid.nu:>8d} {len(frames):>6d} "
                      f"{sum(s.iterations for s in calls):>7d} {dt:>8.2f} {dt / len(frames):>8.2f}", flush=True)
    finally:
        mc.solve = original


if __name__ == "__main__":
    main()
