"""Tactile mapping benchmark: a balloon probe pressed over a wall of raised letters, stitched.

Run: .venv/bin/python bench/tactile.py [--letters DUKE] [--wall letter|quad] [--size 5]
     [--scenes membrane,follows,bridges40] [--depth 2] [--spacing 15] [--quick] [--png FILE]
     [--weights none|sigma] [--reference bending|floor|rim] [--fit-probe-length [--plate-depths 1,2,3] | --probe-length MM]
     [--cell-quantile Q] [--rim-mm MM] [--hysteresis H] [--pairwise]

Scene (skinmap.emulator.walls), as in the paper's cavity: the sheet (N×N cells, --pitch mm,
10 mm gauges, h 0.2 mm; 5 × 5 at 12 mm as in the paper) on a balloon of radius 80 mm, pressed
--depth mm against a 120 × 120 mm wall carrying one letter (``--wall letter``, a wall a letter,
each letter its own run) or all four in its quadrants (``--wall quad``), raised 4 mm, strokes
15 mm wide (the smallest feature), flanks a 6 mm smooth step; presses on a square lattice
--spacing mm apart over the wall in a serpentine sweep, each turned by a random angle in ±30°.
Baseline: 5 noisy frames of the free balloon.  ``--hysteresis H`` (the sensor's is about 0.04):
every gauge reading goes through the emulator's play operator
(skinmap.emulator.electrical.hysteresis_step, loop H of the strain excursion) along one history
of the whole run, each press released to the free balloon before the next, the plate's included.

Scenes: *membrane* (the film solved on the pressed balloon: tension 0.1 N/mm, p = 2T/R,
bending stiffness 0.083 N·mm, the balloon wall's stretch E·t 3 N/mm; walls.Membrane),
*follows* (the sheet takes the wall's shape exactly), *bridges40* (the wall opened by a 40 mm
ball).  Surfaces: "true frame" stitches the scene's own sheet positions in the probe's true
frame (what the sheet's surface says of the wall at best); "scene" the same positions through
the mapping (registered onto the baseline by the rim, then, given poses, placed by the bending
round the contact, tactile.level_by_bending, read from the scene's noise-free gauges;
``--reference floor``: levelled on the wall's base plane where the press touched it,
tactile.level_on_floor; ``--reference rim``: the rim alone): the mapping alone; with
``--fit-probe-length`` the probe's stiffness length is fitted first on reconstructed presses of a
flat plate, as ``skinmap map --fit-probe-length`` does; "reconstructed" runs
the whole chain: gauge strains with strain noise s.d. 0.0057 % → reconstruction → mapping,
stitched unweighted as ``skinmap map`` does (``--weights sigma``: each sample weighted by 1/σ² of
the reconstruction); "rec true fit" the same reconstructed contacts, each placed by its best
rigid fit to the sheet's true surface instead of by its rim (a perfect reference for the
probe's frame: what the reconstruction's own shape allows at best, given poses only).
Poses given or estimated (then how far the placed contacts lie from their true places).

``--pairwise``: each surface's consecutive presses registered one onto the other alone, as
``tactile.estimate_pose`` registers a contact onto the map (the earlier press the map, the
later one placed), twice: searched within the registration's window about the earlier press,
and searched only within 5 mm and 6° of the true relative pose; printed per search, how many
of the pairs were placed within 1 mm and 1° of their true relative pose ("right"), placed
farther ("wrong", with their median distance), or refused.  What the overlap of two presses
says of their relative place, before any chain or map: where even the exact surfaces starting
from the truth are placed wrong, the heights in the overlap do not fix the pose.

Per row: "vs relief": mean and 90th percentile |stitched − relief| over the map cells where the
sheet touched the wall in some press (clearance < 0.05 mm; the relief is only felt there);
"vs membrane": mean and p90 |stitched − the "true frame" map| over every mapped cell (the
sheet's own surface: what it can measure at best); coverage of the wall's square; the share
of mapped cells the sheet touched; time per press.
"""
from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import re  # noqa: E402
import time  # noqa: E402
from collections import Counter  # noqa: E402
from dataclasses import replace  # noqa: E402

import numpy as np  # noqa: E402
from threadpoolctl import threadpool_limits  # noqa: E402

from skinmap.daemon.tactile import (CELL_QUANTILE, CONTACT_RIM_MM, PROBE_LENGTH_MM, Contact, ProbePose,  # noqa: E402
                                    ReliefMap, SampleGrid, capture_baseline, detect_contact,
                                    _registration_map, estimate_pose, fit_probe_length, level_by_bending,
                                    level_on_floor, stitch_estimated)
from skinmap.daemon.tactilemap import write_png  # noqa: E402
from skinmap.emulator import physics as ph  # noqa: E402
from skinmap.emulator.electrical import hysteresis_step  # noqa: E402
from skinmap.emulator.walls import BalloonOnWall, FlatPlate, LetterRelief, Membrane  # noqa: E402
from skinmap.reconstruction import reconstruct  # noqa: E402
from skinmap.strains import GAUGE_LENGTH_MM, cell_bending  # noqa: E402

NOISE = 0.0057e-2
TOUCH_MM = 0.05  # clearance below which the sheet counts as touching the wall


def _scene_shape(name: str, wall: LetterRelief | FlatPlate, p: ProbePose, reach: float) -> BalloonOnWall:
    if name == "membrane":
        # the film solved out to 5 mm beyond the sheet's corners (at least 50 mm)
        return BalloonOnWall(wall, (p.x_mm, p.y_mm), p.angle_deg, p.depth_mm, membrane=Membrane(half=max(50.0, reach + 5.0)))
    if name == "follows":
        return BalloonOnWall(wall, (p.x_mm, p.y_mm), p.angle_deg, p.depth_mm)
    if name.startswith("bridges"):
        return BalloonOnWall(wall, (p.x_mm, p.y_mm), p.angle_deg, p.depth_mm, membrane_radius=float(name[7:]))
    raise SystemExit(f"unknown scene {name!r}: membrane, follows or bridgesRADIUS (e.g. bridges40)")


def _touched(relief: ReliefMap, shapes: list[BalloonOnWall], uv: np.ndarray) -> np.ndarray:
    """The map cells where the true sheet touched the wall in some press."""
    out = np.zeros(relief.shape, dtype=bool)
    for shape in shapes:
        xy = shape.position(uv)[:, :2]
        on = shape.clearance(xy) < TOUCH_MM
        ij = np.floor((shape.to_wall(xy[on]) + relief.half) / relief.step).astype(int)
        ok = np.all((ij >= 0) & (ij < relief.shape[0]), axis=1)
        out[ij[ok, 1], ij[ok, 0]] = True
    return out


def _floor_samples(shape: BalloonOnWall, uv: np.ndarray) -> int:
    """How many of the sheet's samples touch the wall's base plane (off the relief) in a press."""
    xy = shape.position(uv)[:, :2]
    return int(np.count_nonzero((shape.clearance(xy) < TOUCH_MM) & (shape.wall.height(shape.to_wall(xy)) < 0.01)))


def _fitted(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """p moved by the rigid motion that best maps it onto q (Kabsch, every sample)."""
    pc, qc = p.mean(axis=0), q.mean(axis=0)
    u, _, vt = np.linalg.svd((p - pc).T @ (q - qc))
    rot = (u * np.array([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])) @ vt
    return (p - pc) @ rot + qc


def _turn(to_deg: float, from_deg: float) -> float:
    """The angle from ``from_deg`` to ``to_deg``, in (−180°, 180°]."""
    return (to_deg - from_deg + 180.0) % 360.0 - 180.0


def _relative(a: ProbePose, b: ProbePose) -> np.ndarray:
    """Pose b in the frame of pose a: (x, y) mm and the angle, degrees."""
    th = np.radians(a.angle_deg)
    c, s = np.cos(th), np.sin(th)
    dx, dy = b.x_mm - a.x_mm, b.y_mm - a.y_mm
    return np.array([c * dx + s * dy, -s * dx + c * dy, _turn(b.angle_deg, a.angle_deg)])


def _pairwise(contacts: list[Contact | None], poses: list[ProbePose], grid: SampleGrid, near_truth: bool) -> str:
    """Each press registered onto the one before it alone (``estimate_pose`` against a map of
    that contact in its own frame): searched within the registration's window about it, or
    (``near_truth``) within 5 mm and 6° of the true relative pose; how many land within 1 mm and
    1° of it, how many farther, how many are refused."""
    right, wrong, refused, off = 0, 0, 0, []
    for i in range(len(contacts) - 1):
        a, b = contacts[i], contacts[i + 1]
        if a is None or b is None:
            continue
        one = _registration_map(ReliefMap(120.0, 1.0))
        one.add(a, ProbePose(0.0, 0.0, 0.0, 0.0), grid)
        truth = _relative(poses[i], poses[i + 1])
        if near_truth:
            est = estimate_pose(one, b, grid, prior=ProbePose(*truth, 0.0), max_move_mm=5.0, angle_range_deg=6.0)
        else:
            est = estimate_pose(one, b, grid, prior=ProbePose(0.0, 0.0, 0.0, 0.0))
        if est.pose is None:
            refused += 1
            continue
        d_xy = float(np.hypot(est.pose.x_mm - truth[0], est.pose.y_mm - truth[1]))
        d_ang = abs(_turn(est.pose.angle_deg, truth[2]))
        if d_xy <= 1.0 and d_ang <= 1.0:
            right += 1
        else:
            wrong += 1
            off.append(d_xy)
    where = "from the truth ±5 mm, ±6°" if near_truth else "in the window"
    median = f" ({np.median(off):.1f} mm median off)" if off else ""
    return f"{where}: {right} right, {wrong} wrong{median}, {refused} refused"


def _fit_length(args: argparse.Namespace, grid: SampleGrid, gauges, free: ph.Shape) -> float:
    """The probe's stiffness length fitted on reconstructed presses of a flat plate (``--plate-depths``,
    12 // (their count) presses at each, turned at random), printed with its residual, the presses'
    indentation range and the time."""
    t0 = time.perf_counter()
    rng = np.random.default_rng(args.seed + 1)
    n, pitch, uv = args.size, args.pitch, grid.uv
    plate = FlatPlate()

    def rec(shape: ph.Shape) -> tuple[np.ndarray, np.ndarray]:
        eu, el = gauges(shape, rng)
        return reconstruct(eu, el, pitch, 0.2, 0.2).locate(uv)[0], cell_bending(eu, el, 0.2, 0.2)

    rest = [rec(free) for _ in range(5)]
    base = capture_baseline([(r[0], free.normal(uv)) for r in rest], bending=[r[1] for r in rest])
    depths = [float(x) for x in args.plate_depths.split(",")]
    poses = [ProbePose(float(rng.uniform(-20, 20)), float(rng.uniform(-20, 20)), float(rng.uniform(-30, 30)), d)
             for d in depths for _ in range(max(1, 12 // len(depths)))]
    contacts, kept = [], []
    for p in poses:
        shape = _scene_shape("membrane", plate, p, 0.5 * n * pitch * 2 ** 0.5)
        pos, bend = rec(shape)
        c = detect_contact(pos, base, grid, min_depth_mm=args.min_depth, bending=bend)
        if c is not None:
            contacts.append(c)
            kept.append(p)
    fit = fit_probe_length(contacts, kept, base, grid, pitch)
    print(f"(probe stiffness length fitted on {fit.contacts} reconstructed presses of a flat plate at {args.plate_depths} mm "
          f"(indenting {fit.indentation_mm[0]:.1f}-{fit.indentation_mm[1]:.1f} mm): {fit.length_mm:.2f} mm, residual "
          f"{fit.residual_mm:.3f} mm rms; {time.perf_counter() - t0:.1f} s)")
    return fit.length_mm


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--letters", default="DUKE", help="the letters to map (one wall each with --wall letter)")
    ap.add_argument("--wall", choices=("letter", "quad"), default="letter",
                    help="letter: one letter spans each 120 x 120 mm wall; quad: the four on one wall")
    ap.add_argument("--size", type=int, default=5)
    ap.add_argument("--pitch", type=float, default=12.0)
    ap.add_argument("--depth", type=float, default=2.0)
    ap.add_argument("--spacing", type=float, default=15.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--min-depth", type=float, default=0.5, help="contact: pressed in by more than this, mm")
    ap.add_argument("--scenes", default="membrane", help="comma-separated: membrane, follows, bridges40")
    ap.add_argument("--quick", action="store_true", help="given poses only (no registration)")
    ap.add_argument("--pairwise", action="store_true",
                    help="also register each surface's consecutive presses one onto the other and print how many "
                         "land on their true relative pose (module docstring)")
    ap.add_argument("--png", help="write the maps (with the truth) to PNG files named after this one")
    ap.add_argument("--reference", choices=("bending", "floor", "rim"), default="bending",
                    help="given poses: each contact placed by its free cells' bending, as skinmap map does (bending), "
                         "levelled on the wall's base plane where it touched it (floor), or left registered by its "
                         "rim (rim)")
    ap.add_argument("--probe-length", type=float, default=PROBE_LENGTH_MM,
                    help="the probe's stiffness length for --reference bending, mm (default %(default)g)")
    ap.add_argument("--fit-probe-length", action="store_true",
                    help="fit the probe's stiffness length first on reconstructed presses of a flat plate at 1, 2 "
                         "and 3 mm (as skinmap map --fit-probe-length does) and use it")
    ap.add_argument("--plate-depths", default="1,2,3",
                    help="with --fit-probe-length: the plate's press depths, mm, comma-separated, 12 // (their "
                         "count) presses at each (default %(default)s; 1,2,3,4,5,6 reaches as deep as the letters' "
                         "presses indent, docs/tactile.md)")
    ap.add_argument("--hysteresis", type=float, default=0.0,
                    help="the gauges' hysteresis, loop height as a share of the strain excursion (the sensor's: "
                         "about 0.04; default %(default)g, none)")
    ap.add_argument("--weights", choices=("none", "sigma"), default="none",
                    help="stitch the reconstructed contacts unweighted, as skinmap map does (none), or weighted by "
                         "1/sigma^2 of the reconstruction (sigma)")
    ap.add_argument("--cell-quantile", type=float, default=CELL_QUANTILE,
                    help="the quantile of a map cell's readings that is its height (ReliefMap; default %(default).3g)")
    ap.add_argument("--rim-mm", type=float, default=CONTACT_RIM_MM,
                    help="a contact's outer ring left out of the map, mm (ReliefMap; default %(default)g)")
    args = ap.parse_args()
    n, pitch = args.size, args.pitch
    grid = SampleGrid.for_array(n, n, pitch, 2.0)
    uv = grid.uv
    dense_uv = SampleGrid.for_array(n, n, pitch, 0.5).uv
    centres = np.arange(-60.0 + args.spacing / 2, 60.0, args.spacing)
    walls = [(c, LetterRelief(c)) for c in args.letters] if args.wall == "letter" else [(args.letters, LetterRelief(args.letters))]
    print(f"Tactile mapping: {n}x{n} sheet at {pitch:g} mm on a balloon R 80 mm, {len(centres) ** 2} presses "
          f"{args.depth:g} mm deep, {args.spacing:g} mm apart (serpentine), turned ±30°; "
          f"{'one letter a' if args.wall == 'letter' else 'the four letters on one'} 120 x 120 mm wall, 4 mm high, "
          "strokes 15 mm")
    head = (f"{'wall':5s} {'scene':9s} {'surfaces':13s} {'poses':9s} {'placed':>7s} {'vs relief':>9s} {'p90':>5s} "
            f"{'vs membrane':>11s} {'p90':>5s} {'coverage':>8s} {'touched':>7s} {'area mm2':>8s} {'s/press':>7s}")
    print(head)
    print("-" * len(head))
    free = ph.SphereCap(80.0)
    released = ph.gauge_strains(free, n, n, pitch, 0.2, 0.2, GAUGE_LENGTH_MM)
    memory = [np.zeros_like(released[0]), np.zeros_like(released[1])]  # the play's output, from the flat sheet

    def gauges(shape: ph.Shape, rng: np.random.Generator | None) -> tuple[np.ndarray, np.ndarray]:
        eu, el = ph.gauge_strains(shape, n, n, pitch, 0.2, 0.2, GAUGE_LENGTH_MM)
        if args.hysteresis > 0:
            eu, el = (hysteresis_step(memory[k], e, args.hysteresis) for k, e in enumerate((eu, el)))
            # the reading, then the press released to the free balloon before the next
            memory[:] = [hysteresis_step(e, r, args.hysteresis) for e, r in zip((eu, el), released)] \
                if shape is not free else [eu, el]
        if rng is not None:
            eu, el = eu + rng.normal(0, NOISE, eu.shape), el + rng.normal(0, NOISE, el.shape)
        return eu, el

    length = args.probe_length
    if args.fit_probe_length:
        with threadpool_limits(1):
            length = _fit_length(args, grid, gauges, free)
    with threadpool_limits(1):
        for wall_name, wall in walls:
            rng = np.random.default_rng(args.seed)
            poses = [ProbePose(float(x), float(y), float(rng.uniform(-30, 30)), args.depth)
                     for k, y in enumerate(centres) for x in (centres if k % 2 == 0 else centres[::-1])]
            for scene_name in args.scenes.split(","):
                t0 = time.perf_counter()
                shapes = [_scene_shape(scene_name, wall, p, 0.5 * n * pitch * 2 ** 0.5) for p in poses]
                t_scene = (time.perf_counter() - t0) / len(poses)
                touched = _touched(ReliefMap(120.0, 1.0), shapes, dense_uv)
                floor = [_floor_samples(shape, uv) for shape in shapes]
                print(f"({wall_name}, {scene_name}: {sum(f > 0 for f in floor)} of {len(shapes)} presses touch the wall's "
                      f"base plane, {sum(f >= 30 for f in floor)} with at least 30 of the sheet's {len(uv)} samples)")
                sheet_map = None  # the sheet's own true surface, stitched with the true poses

                def scene(shape: ph.Shape) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
                    return shape.position(uv), None, cell_bending(*gauges(shape, None), 0.2, 0.2)

                def positions_only(shape: ph.Shape) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
                    return shape.position(uv), None, None  # the true frame's row places by the truth: no gauges

                def true_frame(contact: Contact | None, shape: ph.Shape) -> Contact | None:
                    # the contact found as ever, its samples left in the probe's true frame
                    # (no registration onto the baseline by the rim)
                    return None if contact is None else replace(contact, positions=shape.position(uv))

                def reconstructed(shape: ph.Shape) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
                    eu, el = gauges(shape, rng)
                    surf = reconstruct(eu, el, pitch, 0.2, 0.2)
                    return surf.locate(uv)[0], surf.locate_sigma(uv), cell_bending(eu, el, 0.2, 0.2)

                rec_contacts: list[Contact | None] = []
                for name, surface in (("true frame", positions_only), ("scene", scene),
                                      ("reconstructed", reconstructed), ("rec true fit", reconstructed)):
                    t0 = time.perf_counter()
                    if name == "rec true fit":
                        # the reconstructed contacts again, each placed by its best rigid fit to the
                        # sheet's true surface (every sample): a perfect reference for the probe's
                        # frame, what the reconstruction's own shape allows at best
                        contacts = [None if c is None else replace(c, positions=_fitted(c.positions, shape.position(uv)))
                                    for c, shape in zip(rec_contacts, shapes)]
                    else:
                        rest = [surface(free) for _ in range(5)]
                        read = [r[2] for r in rest if r[2] is not None]
                        base = capture_baseline([(r[0], free.normal(uv)) for r in rest],
                                                bending=read if len(read) == len(rest) else None)
                        contacts = []
                        for shape in shapes:
                            pos, sig, bend = surface(shape)
                            c = detect_contact(pos, base, grid, min_depth_mm=args.min_depth,
                                               sigma=sig if args.weights == "sigma" else None, bending=bend)
                            contacts.append(true_frame(c, shape) if name == "true frame" else c)
                        if name == "reconstructed":
                            rec_contacts = contacts
                    t_detect = (time.perf_counter() - t0) / len(poses)
                    kept = [(c, p) for c, p in zip(contacts, poses) if c is not None]
                    if args.pairwise and name != "rec true fit":
                        print(f"{wall_name:5s} {scene_name:9s} {name:13s} consecutive presses registered pairwise: "
                              + "; ".join(_pairwise(contacts, poses, grid, near_truth)
                                          for near_truth in (False, True)), flush=True)
                    for mode in ("given",) if args.quick or name in ("true frame", "rec true fit") else ("given", "estimated"):
                        relief = ReliefMap(120.0, 1.0, rim_mm=args.rim_mm, quantile=args.cell_quantile)
                        t0 = time.perf_counter()
                        levelled, refused, placement = 0, "", ""
                        if mode == "given":
                            for c, p in kept:
                                if args.reference == "floor" and name in ("scene", "reconstructed"):
                                    lv = level_on_floor(c, p, grid)
                                    c, levelled = lv.contact, levelled + (not lv.reason)
                                elif args.reference == "bending" and name in ("scene", "reconstructed"):
                                    bl = level_by_bending(c, base, grid, pitch, length_mm=length)
                                    c, levelled = bl.contact, levelled + (not bl.reason)
                                relief.add(c, p, grid)
                            placed = len(kept)
                        else:
                            est = stitch_estimated([c for c, _ in kept], grid, relief, first=kept[0][1])
                            placed = sum(e.pose is not None for e in est)
                            # each refusal by its kind (its figures left out)
                            refusals = Counter(re.sub(r"\d+(\.\d+)?", "#", e.reason.split("(")[0]).strip()
                                               for e in est if e.pose is None)
                            refused = "; ".join(f"{k} x{v}" for k, v in refusals.most_common()) or "none"
                            # how far each placed contact lies from its true place (the anchor left out)
                            off = [(float(np.hypot(e.pose.x_mm - p.x_mm, e.pose.y_mm - p.y_mm)),
                                    abs(_turn(e.pose.angle_deg, p.angle_deg)))
                                   for e, (_, p) in list(zip(est, kept))[1:] if e.pose is not None]
                            if off:
                                xy_off, ang_off = np.array(off).T
                                placement = (f"  (placed off their true places by {np.median(xy_off):.1f} mm median, "
                                             f"{xy_off.max():.1f} mm max, {np.median(ang_off):.1f}° median)")
                        per_press = t_scene + t_detect + (time.perf_counter() - t0) / len(poses)
                        how = "placed by their bending" if args.reference == "bending" else "levelled on the floor"
                        h = relief.height()
                        truth = wall.height(relief.centres)
                        mapped = np.isfinite(h) & relief.wall_region()
                        on = mapped & touched
                        err = np.abs(h - truth)[on]
                        if sheet_map is None:
                            sheet_map = h
                        both = mapped & np.isfinite(sheet_map)
                        vs_sheet = np.abs(h - sheet_map)[both]
                        print(f"{wall_name:5s} {scene_name:9s} {name:13s} {mode:9s} {placed:3d}/{len(poses):<3d} "
                              f"{err.mean():9.3f} {np.percentile(err, 90):5.2f} {vs_sheet.mean():11.3f} "
                              f"{np.percentile(vs_sheet, 90):5.2f} {100 * relief.coverage():7.1f}% "
                              f"{100 * on.sum() / max(1, mapped.sum()):6.1f}% "
                              f"{np.mean([c.area_mm2 for c, _ in kept]):8.0f} {per_press:7.3f}"
                              + (f"  ({levelled} {how})" if levelled else "")
                              + (f"  (refused: {refused})" if refused else "") + placement, flush=True)
                        if args.png:
                            root, ext = os.path.splitext(args.png)
                            out = f"{root}-{wall_name}-{scene_name}-{name.replace(' ', '')}-{mode}{ext or '.png'}"
                            write_png(relief, out, truth=np.where(relief.wall_region(), truth, np.nan))
                            print(f"(map written to {out})")


if __name__ == "__main__":
    main()
