"""What limits tactile mapping through the gauges: the reconstruction of a sheet pressed on the
letter relief, alone.

Run: .venv/bin/python bench/tactile_reconstruction.py [--size 5] [--pitch 12] [--depth 2] [--letter E|DUKE]

For single presses of the balloon (R 80 mm) on a letter wall (skinmap.emulator.walls: one
letter spanning the 120 × 120 mm wall, or DUKE in its quadrants), with the sheet following the
wall exactly ("follows"), bridging it as a pressurised membrane of radius 40 mm ("bridges40"),
and solved as the pressed film ("membrane": walls.Membrane), and for the free balloon: the
gauges' strains (noise-free) are reconstructed (skinmap.reconstruction.reconstruct, public
options only) and the sheet's sampled surface compared with the scene's after the best rigid
alignment: mean and largest error, and the reconstruction's own mean σ (Surface.node_sigma).
Also the sheet's largest curvature (1/mm) and its gauges' largest strain, the measure of how far
the shape is beyond what 10 mm gauges at this pitch can carry; and "rim reg": how far the
scene's own surface lands from its true place when registered onto the free baseline by the
samples out of contact, as the mapping does (mean over the samples, mm).
"""
from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402

import numpy as np  # noqa: E402
from threadpoolctl import threadpool_limits  # noqa: E402

from skinmap.daemon.tactile import SampleGrid, capture_baseline, detect_contact  # noqa: E402
from skinmap.emulator import physics as ph  # noqa: E402
from skinmap.emulator.walls import BalloonOnWall, LetterRelief, Membrane  # noqa: E402
from skinmap.reconstruction import reconstruct  # noqa: E402

PRESSES = [(-30.0, 30.0, 10.0), (0.0, 0.0, 0.0), (30.0, -30.0, -20.0), (-45.0, -10.0, 25.0)]


def _rigid_error(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    a, b = p - p.mean(0), q - q.mean(0)
    u, _, vt = np.linalg.svd(a.T @ b)
    d = np.sign(np.linalg.det(u @ vt))
    rot = (u * np.array([1.0, 1.0, d])) @ vt
    return np.linalg.norm(a @ rot - b, axis=1)


def _curvature(shape: ph.Shape, uv: np.ndarray, h: float = 0.5) -> float:
    """Largest |∂²z/∂u²|, |∂²z/∂v²| of the sheet (1/mm), by central differences."""
    z = lambda d: shape.position(uv + d)[:, 2]  # noqa: E731
    z0 = z(np.zeros(2))
    kuu = (z(np.array([h, 0])) - 2 * z0 + z(np.array([-h, 0]))) / h ** 2
    kvv = (z(np.array([0, h])) - 2 * z0 + z(np.array([0, -h]))) / h ** 2
    return float(max(np.abs(kuu).max(), np.abs(kvv).max()))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=5)
    ap.add_argument("--pitch", type=float, default=12.0)
    ap.add_argument("--depth", type=float, default=2.0)
    ap.add_argument("--letter", default="E", help="one letter (a wall of its own) or four (DUKE in the quadrants)")
    args = ap.parse_args()
    n, pitch = args.size, args.pitch
    wall = LetterRelief(args.letter)
    grid = SampleGrid.for_array(n, n, pitch, 2.0)
    uv = grid.uv
    inner = SampleGrid.for_array(n, n, pitch, 1.0).uv
    free = ph.SphereCap(80.0)
    base = capture_baseline([(free.position(uv), free.normal(uv))])
    print(f"{n}x{n} sheet at {pitch:g} mm, 10 mm gauges, presses {args.depth:g} mm deep on {args.letter} "
          "(4 mm, strokes 15 mm)")
    head = (f"{'scene':10s} {'press':>18s} {'mean err mm':>12s} {'max err mm':>11s} {'mean σ mm':>10s} "
            f"{'max curv 1/mm':>14s} {'max |strain|':>13s} {'rim reg mm':>11s}")
    print(head)
    print("-" * len(head))
    with threadpool_limits(1):
        cases = [("free", None, ph.SphereCap(80.0))]
        mem = Membrane(half=max(50.0, 0.5 * n * pitch * 2 ** 0.5 + 5.0))
        for name, rho, film in (("follows", None, None), ("bridges40", 40.0, None), ("membrane", None, mem)):
            cases += [(name, p, BalloonOnWall(wall, p[:2], p[2], args.depth, membrane_radius=rho, membrane=film))
                      for p in PRESSES]
        for name, p, shape in cases:
            eu, el = ph.gauge_strains(shape, n, n, pitch, 0.2, 0.2, 10.0)
            surf = reconstruct(eu, el, pitch, 0.2, 0.2)
            err = _rigid_error(surf.locate(uv)[0], shape.position(uv))
            where = "-" if p is None else f"({p[0]:g}, {p[1]:g}) {p[2]:g}°"
            truth = shape.position(uv)
            c = detect_contact(truth, base, grid)
            reg = "-" if c is None else f"{float(np.linalg.norm(c.positions - truth, axis=1).mean()):.3f}"
            print(f"{name:10s} {where:>18s} {err.mean():12.3f} {err.max():11.3f} {float(np.mean(surf.node_sigma)):10.3f} "
                  f"{_curvature(shape, inner):14.3f} {float(max(np.abs(eu).max(), np.abs(el).max())):13.4f} {reg:>11s}")


if __name__ == "__main__":
    main()
