"""Tactile mapping benchmark: a balloon probe pressed over a wall of raised letters, stitched.

Run: .venv/bin/python bench/tactile.py [--size 8] [--pitch 12] [--depth 2] [--spacing 25] [--png FILE]

Scene (skinmap.emulator.walls): the sheet (N×N cells, --pitch mm, 10 mm gauges, h 0.2 mm) on a
balloon of radius 80 mm, pressed --depth mm against a 120 × 120 mm wall carrying 'D', 'U', 'K',
'E' raised 4 mm, strokes 15 mm wide; presses on a square lattice --spacing mm apart over the
wall, each turned by a random angle in ±30°.  Baseline: 5 noisy frames of the free balloon.

Two rows: "scene surfaces" stitches the scene's own sheet positions (the mapping alone: baseline,
registration, contact, stitching); "reconstructed" runs the whole chain: gauge strains with
strain noise s.d. 0.0057 % → reconstruction → mapping.  Per row: the relief's mean and 90th
percentile absolute error over the touched part of the wall, and the coverage of the wall.
Also the contacts' mean area, peak depth and feature size L_r, and time per press.
"""
from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
from threadpoolctl import threadpool_limits  # noqa: E402

from skinmap.daemon.tactile import (ProbePose, ReliefMap, SampleGrid, capture_baseline, detect_contact,  # noqa: E402
                                    stitch_estimated)
from skinmap.daemon.tactilemap import write_png  # noqa: E402
from skinmap.emulator import physics as ph  # noqa: E402
from skinmap.emulator.walls import BalloonOnWall, LetterRelief  # noqa: E402
from skinmap.reconstruction import reconstruct  # noqa: E402

NOISE = 0.0057e-2


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=8)
    ap.add_argument("--pitch", type=float, default=12.0)
    ap.add_argument("--depth", type=float, default=3.0)
    ap.add_argument("--spacing", type=float, default=15.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--min-depth", type=float, default=0.5, help="contact: pressed in by more than this, mm")
    ap.add_argument("--membrane", type=float, default=40.0,
                    help="membrane radius T/p of the bridging scene, mm (half the balloon's radius)")
    ap.add_argument("--quick", action="store_true", help="given poses only (no registration)")
    ap.add_argument("--png", help="write the maps (with the truth) to PNG files named after this one")
    args = ap.parse_args()
    n, pitch = args.size, args.pitch
    rng = np.random.default_rng(args.seed)
    wall = LetterRelief()
    grid = SampleGrid.for_array(n, n, pitch, 2.0)
    uv = grid.uv
    centres = np.arange(-60.0 + args.spacing / 2, 60.0, args.spacing)
    # a serpentine sweep: each press a lattice step from the one before (the registration's prior)
    poses = [ProbePose(float(x), float(y), float(rng.uniform(-30, 30)), args.depth)
             for k, y in enumerate(centres) for x in (centres if k % 2 == 0 else centres[::-1])]

    def scene(shape: ph.Shape) -> tuple[np.ndarray, np.ndarray | None]:
        return shape.position(uv), None

    def reconstructed(shape: ph.Shape) -> tuple[np.ndarray, np.ndarray | None]:
        eu, el = ph.gauge_strains(shape, n, n, pitch, 0.2, 0.2, 10.0)
        surf = reconstruct(eu + rng.normal(0, NOISE, eu.shape), el + rng.normal(0, NOISE, el.shape), pitch, 0.2, 0.2)
        return surf.locate(uv)[0], surf.locate_sigma(uv)

    print(f"Tactile mapping: {n}x{n} sheet at {pitch:g} mm on a balloon R 80 mm, {len(poses)} presses {args.depth:g} mm "
          f"deep, {args.spacing:g} mm apart (serpentine), turned ±30°; wall 120 x 120 mm, letters DUKE 4 mm high, "
          "strokes 15 mm")
    head = (f"{'scene':9s} {'surfaces':14s} {'poses':9s} {'placed':>7s} {'vs relief':>10s} {'p90':>6s} "
            f"{'vs sheet':>9s} {'coverage':>9s} {'area mm2':>9s} {'peak mm':>8s} {'L_r mm':>7s} {'s/press':>8s}")
    print(head)
    print("-" * len(head))
    free = ph.SphereCap(80.0)
    with threadpool_limits(1):
        for scene_name, membrane in (("follows", None), (f"bridges{args.membrane:g}", args.membrane)):
            shapes = [BalloonOnWall(wall, (p.x_mm, p.y_mm), p.angle_deg, p.depth_mm, membrane_radius=membrane)
                      for p in poses]
            sheet_map = None  # the sheet's own true surface, stitched with the true poses
            for name, surface in (("scene surfaces", scene), ("reconstructed", reconstructed)):
                normals = free.normal(uv)
                base = capture_baseline([(surface(free)[0], normals) for _ in range(5)])
                t0 = time.perf_counter()
                contacts = []
                for shape in shapes:
                    pos, sig = surface(shape)
                    contacts.append(detect_contact(pos, base, grid, min_depth_mm=args.min_depth, sigma=sig))
                t_detect = (time.perf_counter() - t0) / len(poses)
                for mode in ("given",) if args.quick else ("given", "estimated"):
                    relief = ReliefMap(120.0, 1.0)
                    t0 = time.perf_counter()
                    kept = [(c, p) for c, p in zip(contacts, poses) if c is not None]
                    if mode == "given":
                        for c, p in kept:
                            relief.add(c, p, grid)
                        placed = len(kept)
                    else:
                        est = stitch_estimated([c for c, _ in kept], grid, relief, first=kept[0][1])
                        placed = sum(e.pose is not None for e in est)
                    per_press = t_detect + (time.perf_counter() - t0) / len(poses)
                    h = relief.height()
                    truth = wall.height(relief.centres)
                    touched = np.isfinite(h) & relief.wall_region()
                    err = np.abs(h - truth)[touched]
                    if sheet_map is None:
                        sheet_map = h
                    both = touched & np.isfinite(sheet_map)
                    vs_sheet = float(np.mean(np.abs(h - sheet_map)[both]))
                    cs = [c for c, _ in kept]
                    print(f"{scene_name:9s} {name:14s} {mode:9s} {placed:3d}/{len(poses):<3d} {err.mean():10.3f} "
                          f"{np.percentile(err, 90):6.2f} {vs_sheet:9.3f} {100 * relief.coverage():8.1f}% "
                          f"{np.mean([c.area_mm2 for c in cs]):9.0f} {np.mean([c.peak_depth_mm for c in cs]):8.2f} "
                          f"{np.mean([c.feature_size_mm for c in cs]):7.1f} {per_press:8.3f}", flush=True)
                    if args.png:
                        root, ext = os.path.splitext(args.png)
                        out = f"{root}-{scene_name}-{name.split()[0]}-{mode}{ext or '.png'}"
                        write_png(relief, out, truth=np.where(relief.wall_region(), truth, np.nan))
                        print(f"(map written to {out})")


if __name__ == "__main__":
    main()
