"""One biased gauge: what it costs the reconstruction, whether the gauge screen names it, and
how often the screen names a good gauge.

Run: .venv/bin/python bench/biased_gauge.py [--sizes 5,8] [--draws 40] [--gauges all|K] [--seed S] [--no-elastic]
     [--only accuracy|alarms|timing|random [--random K]]

For each shape (kinematic closed-form maps, and elastic scenes of bench/elastic_dataset.py on
5×5 unless --no-elastic), every gauge in turn (or K of them, drawn, with --gauges K) reads 1.3×
its strain (a gain 30 % off: neither open nor saturated), the rest exact; the frame is
reconstructed (told strain_sigma 0.0057 %, as skinmapd tells it the sensor's) by

- "before": the default path without the screen (``gauge_screen=False``),
- "clarabel": the same with the Huber field fit by Clarabel (``convex_solver="clarabel"``),
- "after": the default path (the gauge screen on),

and the mean node error after the best rigid alignment is taken against the truth and against
the same path's reconstruction of the unbiased frame.  Per shape: mean and largest of those over
the biased gauges, how many biased frames cost more than 0.05 mm, and for "after" how many
biased gauges were named right, named wrong (another gauge), or not named.  The shapes are
split in the two sets the screen's constants were and were not looked at with ("tuning" /
"unseen").  False alarms: --draws noisy unbiased frames per shape (independent normal noise of
s.d. 0.0057 % on every gauge), the share in which the screen names any gauge.  Timing: median
and 90th percentile of the whole frame (reconstruct with previous, nodes, normals), screen on
and off, warm, one core: noisy frames of a bump circling the centre (as bench/reconstruction.py
times them), and noisy frames of a breathing sphere cap with one gauge biased (named in every
frame, so Clarabel runs in every frame); then the screen alone.  ``--only random``: K random
kinematic shapes of each of five classes (quadrics, saddles, cylinders, spheres, bumps; none
looked at while the constants were set), every gauge biased in turn through the default path:
named right / wrong / none per class, and frames costing more than 0.05 mm against the
unbiased frame; a good gauge named is printed.
"""
from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # one core, as in the gateway

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from skinmap.emulator import physics as ph  # noqa: E402
from skinmap.reconstruction import Reconstructor  # noqa: E402
from skinmap.reconstruction.robust import GaugeScreen  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from reconstruction import node_errors  # noqa: E402  (bench/reconstruction.py: aligned node errors)

PITCH, H, GAUGE = 12.0, 0.2, 10.0
NOISE = 0.0057e-2
GAIN = 1.3
LIMIT_MM = 0.05


def kinematic_shapes(n: int) -> dict[str, list[tuple[str, ph.Shape]]]:
    """Shapes per set: "tuning" were looked at while the screen's constants were set, "unseen"
    were not (radii and bump positions scale with the sheet)."""
    s = (n - 1) / 4.0
    return {
        "tuning": [
            ("cylinder R 50 at 30 deg", ph.Cylinder(50.0 * s, 30.0)),
            ("sphere cap R 60", ph.SphereCap(60.0 * s)),
            ("bump 3 mm FWHM 18", ph.GaussianBumps(height=3.0, fwhm=18.0, centre=(5.0 * s, -3.0 * s))),
            ("saddle R 80 at 20 deg", ph.Saddle(80.0 * s, 20.0)),
            ("bump 5 mm FWHM 15", ph.GaussianBumps(height=5.0, fwhm=15.0, centre=(0.0, 6.0 * s))),
        ],
        "unseen": [
            ("cylinder R -40 on a grid line", ph.Cylinder(-40.0 * s, 90.0)),
            ("sphere cap R -90", ph.SphereCap(-90.0 * s)),
            ("saddle R 60 at -35 deg", ph.Saddle(60.0 * s, -35.0)),
            ("bump -4 mm FWHM 22", ph.GaussianBumps(height=-4.0, fwhm=22.0, centre=(-7.0 * s, 9.0 * s))),
            ("twisted quadric", ph.Quadric(1 / 70 / s, -1 / 90 / s, 1 / 55 / s)),
            ("oblique cylinder R 70 at 60 deg", ph.Cylinder(70.0 * s, 60.0)),
        ],
    }


def elastic_shapes(n: int, seed: int) -> list[tuple[str, ph.Shape]]:
    """An elastic convex sphere and saddle (bench/elastic_dataset.py's first scene of each class:
    solved once, about a second on 5×5, then read from the solver's disk cache)."""
    import elastic_dataset as ed

    out = []
    for key in ("sphere_convex", "saddle"):
        plan = ed.class_plans(key, seed, 1, n)[0]
        shape, _, _ = ed.solve_scene(plan)
        out.append((f"elastic {key} ({plan.kinematic_spec})"[:32], shape))
    return out


def gauges(n: int, how: str, rng: np.random.Generator) -> list[tuple[int, int, int, int]]:
    every = [(layer, d, i, j) for layer in (0, 1) for d in (0, 1) for i in range(n) for j in range(n)]
    if how == "all":
        return every
    pick = rng.choice(len(every), size=min(int(how), len(every)), replace=False)
    return [every[k] for k in sorted(pick)]


def biased(eu: np.ndarray, el: np.ndarray, g: tuple[int, int, int, int]) -> tuple[np.ndarray, np.ndarray]:
    bu, bl = eu.copy(), el.copy()
    (bu if g[0] == 0 else bl)[g[1:]] *= GAIN
    return bu, bl


def named_gauge(surf) -> tuple[int, int, int, int] | None:
    """(layer, direction, row, col) of the first gauge the screen named in a frame, or None."""
    named = surf.diagnostics.extra.get("suspect_gauges", [])
    if not named:
        return None
    s = named[0]
    return ("upper", "lower").index(s["layer"]), ("row", "column").index(s["direction"]), s["row"], s["col"]


def shape_rows(n: int, name: str, shape: ph.Shape, recs: dict[str, Reconstructor], which: list) -> dict:
    centres = ph.cell_centres(n, n, PITCH)
    eu, el = ph.gauge_strains(shape, n, n, PITCH, H, H, GAUGE)
    truth = shape.position(centres)
    out: dict = {}
    for key, rec in recs.items():
        base = rec(eu, el, strain_sigma=NOISE).nodes
        vs_truth, vs_base, right, wrong, none = [], [], 0, 0, 0
        for g in which:
            bu, bl = biased(eu, el, g)
            surf = rec(bu, bl, strain_sigma=NOISE)
            vs_truth.append(node_errors(surf.nodes, truth).mean())
            vs_base.append(node_errors(surf.nodes, base).mean())
            named = named_gauge(surf)
            if named is not None:
                right, wrong = right + (named == g), wrong + (named != g)
            else:
                none += 1
        out[key] = (np.array(vs_truth), np.array(vs_base), right, wrong, none,
                    node_errors(base, truth).mean())
    return out


def accuracy(n: int, sets: dict[str, list], how: str, rng: np.random.Generator) -> None:
    recs = {"before": Reconstructor(n, n, gauge_screen=False),
            "clarabel": Reconstructor(n, n, gauge_screen=False, convex_solver="clarabel"),
            "after": Reconstructor(n, n)}
    which = gauges(n, how, rng)
    print(f"\nOne gauge reading {GAIN:g}x its strain, {n}x{n} cells, {len(which)} biased gauges per shape "
          f"(noise-free otherwise, told strain_sigma {NOISE:g}); mean node error after the best rigid alignment, mm")
    head = (f"{'set':7s} {'shape':32s} {'path':9s} {'unbiased':>9s} {'vs truth mean':>13s} {'max':>7s} "
            f"{'vs unbiased mean':>16s} {'max':>7s} {'>0.05':>6s} {'named right/wrong/none':>23s}")
    print(head)
    print("-" * len(head))
    totals: dict[str, list] = {k: [] for k in recs}
    for set_name, shapes in sets.items():
        for name, shape in shapes:
            rows = shape_rows(n, name, shape, recs, which)
            for key, (vt, vb, right, wrong, none, clean) in rows.items():
                over = int((np.maximum(vt - clean, vb) > LIMIT_MM).sum())
                totals[key].append((set_name, vt, vb, over))
                named = f"{right}/{wrong}/{none}" if key == "after" else "-"
                print(f"{set_name:7s} {name:32s} {key:9s} {clean:9.4f} {vt.mean():13.4f} {vt.max():7.4f} "
                      f"{vb.mean():16.4f} {vb.max():7.4f} {over:>6d} {named:>23s}")
    print("(unbiased: that path's error on the frame with every gauge right; >0.05: biased frames whose error "
          "exceeds 0.05 mm against the unbiased reconstruction and beyond the unbiased error against the truth)")
    for key, rows in totals.items():
        for set_name in sets:
            vb = np.concatenate([r[2] for r in rows if r[0] == set_name])
            over = sum(r[3] for r in rows if r[0] == set_name)
            print(f"  {key:9s} {set_name:7s}: vs unbiased mean {vb.mean():.4f}, max {vb.max():.4f} mm; "
                  f"{over}/{vb.size} biased frames over {LIMIT_MM:g} mm")


def random_shapes(n: int, per_class: int, rng: np.random.Generator) -> list[tuple[str, ph.Shape]]:
    """``per_class`` kinematic shapes of each of five classes with random parameters (radii and
    bump positions scaled to the sheet as kinematic_shapes scales them): none of them looked at
    while the screen's constants were set."""
    s = (n - 1) / 4.0
    out: list[tuple[str, ph.Shape]] = []

    def sign() -> float:
        return float(rng.choice([-1.0, 1.0]))

    for _ in range(per_class):
        out.append(("quadric", ph.Quadric(*(np.array([sign(), sign(), sign()]) / rng.uniform(45, 120, 3) / s))))
        out.append(("saddle", ph.Saddle(rng.uniform(50, 120) * s * sign(), rng.uniform(-90, 90))))
        out.append(("cylinder", ph.Cylinder(rng.uniform(35, 100) * s * sign(), rng.uniform(-90, 90))))
        out.append(("sphere", ph.SphereCap(rng.uniform(45, 120) * s * sign())))
        out.append(("bump", ph.GaussianBumps(height=rng.uniform(2, 5) * sign(), fwhm=rng.uniform(18, 30),
                                             centre=(rng.uniform(-18, 18) * s, rng.uniform(-18, 18) * s))))
    return out


def random_sweep(n: int, per_class: int, how: str, rng: np.random.Generator) -> None:
    """The default path on random shapes (:func:`random_shapes`), every gauge (or --gauges K of
    them) biased in turn: named right / wrong / none, and frames costing more than LIMIT_MM."""
    rec = Reconstructor(n, n)
    shapes = random_shapes(n, per_class, rng)
    which = gauges(n, how, rng)
    counts: dict[str, list[int]] = {}
    for name, shape in shapes:
        eu, el = ph.gauge_strains(shape, n, n, PITCH, H, H, GAUGE)
        base = rec(eu, el, strain_sigma=NOISE).nodes
        row = counts.setdefault(name, [0, 0, 0, 0, 0])
        for g in which:
            surf = rec(*biased(eu, el, g), strain_sigma=NOISE)
            named = named_gauge(surf)
            if named is not None:
                row[0 if named == g else 1] += 1
                if named != g:
                    print(f"  a good gauge named: {shape!r}, biased {g}, named {surf.diagnostics.suspect_gauges}")
            else:
                row[2] += 1
            row[3] += int(node_errors(surf.nodes, base).mean() > LIMIT_MM)
            row[4] += 1
    print(f"\nRandom shapes, {n}x{n}: {per_class} per class, {len(which)} biased gauges each (one at a time, "
          f"{GAIN:g}x; the default path)")
    for name, (right, wrong, none, over, total) in counts.items():
        print(f"  {name:9s} named right/wrong/none {right}/{wrong}/{none}; over {LIMIT_MM:g} mm {over}/{total}")
    tot = np.sum(list(counts.values()), axis=0)
    print(f"  all       named right/wrong/none {tot[0]}/{tot[1]}/{tot[2]}; over {LIMIT_MM:g} mm {tot[3]}/{tot[4]}")


def false_alarms(n: int, sets: dict[str, list], draws: int, rng: np.random.Generator) -> None:
    rec = Reconstructor(n, n)
    print(f"\nFalse alarms, {n}x{n}: {draws} noisy unbiased frames per shape (s.d. {NOISE:g} on every gauge, told so)")
    total, flagged, ran = 0, 0, 0
    shapes = [("flat", ph.Flat())] + [s for group in sets.values() for s in group]
    for name, shape in shapes:
        eu, el = ph.gauge_strains(shape, n, n, PITCH, H, H, GAUGE)
        f = r = 0
        for _ in range(draws):
            surf = rec(eu + rng.normal(0, NOISE, eu.shape), el + rng.normal(0, NOISE, el.shape), strain_sigma=NOISE)
            f += bool(surf.diagnostics.suspect_gauges)
            r += "screen_clarabel" in surf.diagnostics.extra
        total, flagged, ran = total + draws, flagged + f, ran + r
        print(f"  {name:32s} named a gauge in {f}/{draws}; Clarabel ran in {r}/{draws}")
    # bumps sharper than the cells, moving over the sheet: where the screen's fields misfit most
    sc = (n - 1) / 4.0
    for h, fwhm in ((3.0, 18.0), (5.0, 15.0), (-4.0, 22.0)):
        f = r = 0
        frames = 5 * draws
        for k in range(frames):
            a = 2 * np.pi * k / frames
            shape = ph.GaussianBumps(height=h, fwhm=fwhm, centre=(10 * sc * np.cos(a), 10 * sc * np.sin(3 * a)))
            eu, el = ph.gauge_strains(shape, n, n, PITCH, H, H, GAUGE)
            surf = rec(eu + rng.normal(0, NOISE, eu.shape), el + rng.normal(0, NOISE, el.shape), strain_sigma=NOISE)
            f += bool(surf.diagnostics.suspect_gauges)
            r += "screen_clarabel" in surf.diagnostics.extra
        total, flagged, ran = total + frames, flagged + f, ran + r
        print(f"  {f'bump {h:g} mm FWHM {fwhm:g}, moving':32s} named a gauge in {f}/{frames}; Clarabel ran in {r}/{frames}")
    print(f"  all: a good gauge named in {flagged}/{total} frames ({100.0 * flagged / total:.2f} %); "
          f"the robust fit ran in {ran}/{total}")


def timing(n: int, frames: int, rng: np.random.Generator) -> None:
    """Whole frames, warm (previous passed), on a slowly moving bump as bench/reconstruction.py times."""
    print(f"\nTiming, {n}x{n}, {frames} frames each, warm, one core (CPU time of the frame's thread, ms)")
    for biased_frames in (False, True):
        # screen on and off on the same frames, interleaved (both see the same machine load)
        recs = {False: Reconstructor(n, n, gauge_screen=False), True: Reconstructor(n, n)}
        prev: dict = {False: None, True: None}
        times: dict = {False: [], True: []}
        ran = named = 0
        for k in range(frames + 5):
            phase = 2 * np.pi * k / 200.0
            s = (n - 1) / 4.0
            if biased_frames:  # a breathing sphere: a shape on which the screen names the gauge
                shape: ph.Shape = ph.SphereCap(s * (65.0 + 15.0 * np.sin(phase)))
            else:
                shape = ph.GaussianBumps(height=3.0, fwhm=18.0, centre=(8 * s * np.cos(phase), 8 * s * np.sin(phase)))
            eu, el = ph.gauge_strains(shape, n, n, PITCH, H, H, GAUGE)
            eu = eu + rng.normal(0, NOISE, eu.shape)
            el = el + rng.normal(0, NOISE, el.shape)
            if biased_frames:
                eu[0, n // 2, n // 2 - 1] *= GAIN
            for screen in ((False, True) if k % 2 else (True, False)):
                t0 = time.thread_time()
                surf = recs[screen](eu, el, strain_sigma=NOISE, previous=prev[screen])
                _ = surf.nodes, surf.normals
                dt = time.thread_time() - t0
                prev[screen] = surf
                if k >= 5:
                    times[screen].append(dt)
                    if screen:
                        ran += "screen_clarabel" in surf.diagnostics.extra
                        named += bool(surf.diagnostics.suspect_gauges)
        what = "one gauge biased (breathing sphere)" if biased_frames else "every gauge right (circling bump)"
        off, on = np.array(times[False]) * 1e3, np.array(times[True]) * 1e3
        print(f"  {what:36s} screen off: median {np.median(off):6.2f} p90 {np.percentile(off, 90):6.2f};  on: median "
              f"{np.median(on):6.2f} p90 {np.percentile(on, 90):6.2f}  (Clarabel ran in {ran}/{frames} frames, "
              f"a gauge named in {named})")
    # the screen alone, and a cold biased frame (Clarabel's problem set up in that frame)
    rec = Reconstructor(n, n)
    eu, el = ph.gauge_strains(ph.SphereCap(65.0 * (n - 1) / 4.0), n, n, PITCH, H, H, GAUGE)
    eu = eu + rng.normal(0, NOISE, eu.shape)
    el = el + rng.normal(0, NOISE, el.shape)
    screen = rec._screen
    assert screen is not None
    alone = []
    for _ in range(frames):
        t0 = time.thread_time()
        screen.screen(eu, el, NOISE)
        alone.append(time.thread_time() - t0)
    bu = eu.copy()
    bu[0, n // 2, n // 2 - 1] *= GAIN
    robust = []
    hits = 0
    t0 = time.thread_time()
    GaugeScreen(n, n, H, H)
    setup = time.thread_time() - t0
    for _ in range(frames // 4):
        t0 = time.thread_time()
        found, _ = screen.screen(bu, el, NOISE)
        robust.append(time.thread_time() - t0)
        hits += bool(found)
    print(f"  the screen alone: every gauge right {1e3 * np.median(alone):.3f} ms; with the robust fit (Clarabel) "
          f"{1e3 * np.median(robust):.2f} ms median (named in {hits}/{len(robust)}); its set-up at construction "
          f"{1e3 * setup:.1f} ms")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", default="5", help="comma-separated sheet sizes N (N×N cells)")
    ap.add_argument("--gauges", default="all", help="'all' or how many biased gauges to draw per shape")
    ap.add_argument("--draws", type=int, default=40, help="noisy unbiased frames per shape (false alarms)")
    ap.add_argument("--frames", type=int, default=200, help="frames per timing row")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--no-elastic", action="store_true", help="kinematic shapes only")
    ap.add_argument("--only", choices=("accuracy", "alarms", "timing", "random"))
    ap.add_argument("--random", type=int, default=6,
                    help="with --only random: random shapes per class (quadric, saddle, cylinder, sphere, bump)")
    args = ap.parse_args()
    for n in (int(x) for x in args.sizes.split(",")):
        rng = np.random.default_rng(args.seed)
        sets = kinematic_shapes(n)
        if not args.no_elastic and n == 5:
            extra = elastic_shapes(n, args.seed)
            if extra:
                sets["unseen"] = sets["unseen"] + extra
        if args.only in (None, "accuracy"):
            accuracy(n, sets, args.gauges, rng)
        if args.only in (None, "alarms"):
            false_alarms(n, sets, args.draws, rng)
        if args.only == "random":
            random_sweep(n, args.random, args.gauges, rng)
        if args.only in (None, "timing"):
            timing(n, args.frames if n <= 8 else max(20, args.frames // 5), rng)


if __name__ == "__main__":
    main()
