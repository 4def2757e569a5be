"""Elastic-scene dataset: seeded random elastic-sheet scenes, written for tests and benchmarks.

Run: .venv/bin/python bench/elastic_dataset.py --out DIR [--seed S] [--count K] [--sizes 5,16]
     [--noise SD] [--elements E] [--quick] [--no-cache] [--cache-dir DIR]

Every scene is a film laminated on a rigid mold (skinmap.emulator.scenes, elastic mechanics:
frictionless sliding unless ``friction`` is set), solved once and kept in the solver's disk
cache ($SKINMAP_CACHE_DIR, default ~/.cache/skinmap/mechanics; --no-cache solves afresh).
Shape parameters are drawn from the seed, per class, sheet size and index (scene i of a class is
the same whatever --count, and a class keeps its scenes when classes are added).  Classes, on
N×N cells at 12 mm pitch (radii below are for N <= 5 and grow with the sheet as N/5, so that a
larger sheet sees the same bend angle, not a wrap past the hemisphere; bumps keep their size;
every mold stays below 62° of slope under the film, margin and pre-stretch included):

- bump: one Gaussian, |h| 2-5 mm (either sign), FWHM 15-24 mm, centre anywhere over the cells;
- sphere convex / concave: R 50-100 mm;
- dome: principal radii R 50-100 mm and 1.2-2 times that (one sign), turned at any angle (a
  quadric; its twist reaches the data only through its Gaussian curvature, and its sign is not
  told);
- saddle: |R| 60-120 mm, axes at any angle (0-180 deg);
- ridge: three equal bumps in a line at any angle (|h| 2-5, FWHM 15-24, 0.4-0.6 FWHM apart),
  the middle one over the inner half of the cells;
- two bumps: |h| 2-5 each (signs independent), FWHM 15-24, centres at least a FWHM apart;
- cylinder: |R| 50-100 mm, axis at any angle (-90..90 deg from +v): the mirror-ambiguity
  cases (a constant twist whose sign the strains cannot tell; its sign is recorded);
- sphere / cylinder with a 5 % pre-stretch (the film held in a frame at 1.05x on all edges);
- poisson 0.3, and partial friction 1e-3 N/mm³: a bump, sphere, saddle or cylinder (drawn)
  with that elastic parameter.

Written per scene, DIR/<class>-<N>x<N>-<i>.npz with: eps_upper, eps_lower (2, N, N) noise-free
gauge strains (h = 0.2 mm both layers, 10 mm gauges) and a noisy copy eps_upper_noisy,
eps_lower_noisy (independent normal noise of s.d. --noise on every gauge, default 0.0057 %
strain; the same draw as noise draw 0 of bench/reconstruction.py's elastic table); nodes,
normals (N, N, 3) the true cell-centre positions and normals; element_uv (E, 2) random material
points over the cells with element_positions, element_normals (E, 3); n, m, pitch, h_upper,
h_lower, gauge_length, noise_sd; spec (the scene as a skinmap.emulator.scenes.parse_scene_spec
string, elastic form), kinematic_spec (the same shape without mechanics, for
skinmap.emulator.physics.parse_shape_spec) and meta (JSON: class, index, seeds, parameters, twist
sign); sheet_positions (nv, nu, 3) and sheet_grid (half_u, half_v, spacing) of the solved film,
so that scenes.SheetShape(mechanics.SheetGrid(*sheet_grid), sheet_positions) rebuilds the
shape without a solve.  DIR/index.json lists the scenes with their specs and solve times.  The
script prints one line per scene: the file, the spec and the time the scene took to solve (or to
load, when the solver's disk cache already held it).

bench/reconstruction.py imports the classes from here (its elastic table).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
import zlib
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from skinmap.emulator import physics as ph
from skinmap.emulator import scenes

PITCH, H, GAUGE = 12.0, 0.2, 10.0
NOISE = 0.0057e-2
ELEMENTS = 8

Terms = list[tuple[str, dict[str, float]]]


def _entropy(seed: int, key: str, n: int, m: int, index: int, stream: int) -> list[int]:
    return [seed, zlib.crc32(key.encode()), n, m, index, stream]


@dataclass(frozen=True)
class ScenePlan:
    """One scene: its class, the shape terms and elastic parameters drawn for it, and the specs
    that build it (``spec`` for :func:`scenes.parse_scene_spec` with ``"elastic"``,
    ``kinematic_spec`` for the kinematic form of the same shape)."""

    key: str
    title: str
    index: int
    n: int
    m: int
    pitch: float
    seed: int
    terms: Terms
    elastic: dict[str, float]
    spec: str
    kinematic_spec: str
    twist_sign: float | None  # sign of a constant twist the strains cannot tell (oblique cylinders), else None

    def entropy(self, stream: int) -> list[int]:
        """Seed-sequence entropy of one random stream of this scene (0: shape parameters,
        1: element points, 2 + d: noise draw d)."""
        return _entropy(self.seed, self.key, self.n, self.m, self.index, stream)

    def to_json(self) -> dict[str, Any]:
        doc = asdict(self)
        doc["terms"] = [[kind, params] for kind, params in self.terms]
        return doc


def _round(x: float, digits: int) -> float:
    return float(round(float(x), digits))


def _fmt(x: float) -> str:
    return repr(float(x))


def _spec(terms: Terms, elastic: dict[str, float] | None = None) -> str:
    """A compact spec; elastic parameters follow the first term (parse_scene_spec takes them there)."""
    parts = []
    for k, (kind, params) in enumerate(terms):
        items = dict(params)
        if k == 0 and elastic:
            items.update(elastic)
        body = ",".join(f"{name}={_fmt(v)}" for name, v in items.items())
        parts.append(f"{kind}:{body}" if body else kind)
    return " + ".join(parts)


# --------------------------------------------------------------------------- parameter draws
# Each draw takes the scene's generator and the sheet: (half extent of the cells in u and v, mm;
# the radius scale N/5) and returns (terms, twist sign or None).


@dataclass(frozen=True)
class Sheet:
    half_u: float
    half_v: float
    scale: float  # radii grow with the sheet as max(N, M)/5 (1 for N, M <= 5)


def _signed(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(rng.uniform(lo, hi) * rng.choice([-1.0, 1.0]))


def _bump(rng: np.random.Generator, sheet: Sheet, centre: tuple[float, float] | None = None,
          height: float | None = None, fwhm: float | None = None) -> dict[str, float]:
    h = _signed(rng, 2.0, 5.0) if height is None else height
    f = float(rng.uniform(15.0, 24.0)) if fwhm is None else fwhm
    if centre is None:
        centre = (float(rng.uniform(-sheet.half_u, sheet.half_u)), float(rng.uniform(-sheet.half_v, sheet.half_v)))
    return {"height": _round(h, 2), "fwhm": _round(f, 2), "u0": _round(centre[0], 2), "v0": _round(centre[1], 2)}


def draw_bump(rng, sheet):
    return [("gaussian", _bump(rng, sheet))], None


def draw_sphere(sign: float) -> Callable:
    def draw(rng, sheet):
        return [("sphere", {"radius": _round(sign * rng.uniform(50.0, 100.0) * sheet.scale, 1)})], None
    return draw


def draw_sphere_any(rng, sheet):
    return [("sphere", {"radius": _round(_signed(rng, 50.0, 100.0) * sheet.scale, 1)})], None


def draw_dome(rng, sheet):
    """A dome with unequal principal radii (|R| 50-100 mm and 1.2-2 times that, one sign) turned
    at any angle: z = ½(k_uu u² + 2 k_uv u v + k_vv v²), whose twist k_uv only its Gaussian
    curvature carries into the data (its sign is not told: a dome and its mirror image read
    alike, and the reconstruction is judged by the better of its answers where it says so)."""
    sign = float(rng.choice([-1.0, 1.0]))
    r1 = float(rng.uniform(50.0, 100.0)) * sheet.scale
    r2 = r1 * float(rng.uniform(1.2, 2.0))
    angle = math.radians(float(rng.uniform(0.0, 180.0)))
    k1, k2, c, s = sign / r1, sign / r2, math.cos(angle), math.sin(angle)
    terms = {"k_uu": _round(k1 * c * c + k2 * s * s, 7), "k_uv": _round((k1 - k2) * s * c, 7),
             "k_vv": _round(k1 * s * s + k2 * c * c, 7)}
    return [("quadric", terms)], None


def draw_saddle(rng, sheet):
    return [("saddle", {"radius": _round(_signed(rng, 60.0, 120.0) * sheet.scale, 1),
                        "axis_angle": _round(rng.uniform(0.0, 180.0), 1)})], None


def draw_cylinder(rng, sheet):
    radius = _round(_signed(rng, 50.0, 100.0) * sheet.scale, 1)
    angle = _round(rng.uniform(-90.0, 90.0), 1)
    # z_uv = sin 2θ / (2R) at the axis: the twist's sign (none on a grid line)
    twist = math.sin(math.radians(2.0 * angle)) / radius
    return [("cylinder", {"radius": radius, "axis_angle": angle})], (float(np.sign(twist)) if abs(twist) > 1e-12 else None)


def draw_ridge(rng, sheet):
    h = _signed(rng, 2.0, 5.0)
    fwhm = float(rng.uniform(15.0, 24.0))
    gap = float(rng.uniform(0.4, 0.6)) * fwhm
    angle = math.radians(rng.uniform(0.0, 180.0))
    d = np.array([math.cos(angle), math.sin(angle)])
    # the middle bump over the inner half of the cells, so that the ridge crosses the sheet
    c = 0.5 * np.array([rng.uniform(-sheet.half_u, sheet.half_u), rng.uniform(-sheet.half_v, sheet.half_v)])
    return [("gaussian", _bump(rng, sheet, tuple(c + k * gap * d), h, fwhm)) for k in (-1, 0, 1)], None


def draw_two_bumps(rng, sheet):
    first = _bump(rng, sheet)
    for _ in range(100):
        second = _bump(rng, sheet)
        apart = math.hypot(first["u0"] - second["u0"], first["v0"] - second["v0"])
        if apart >= 0.5 * (first["fwhm"] + second["fwhm"]):
            break
    return [("gaussian", first), ("gaussian", second)], None


def draw_mixed(rng, sheet):
    """A bump, sphere, saddle or cylinder, the kind drawn too."""
    kind = str(rng.choice(["bump", "sphere", "saddle", "cylinder"]))
    return {"bump": draw_bump, "sphere": draw_sphere_any, "saddle": draw_saddle, "cylinder": draw_cylinder}[kind](rng, sheet)


#: The classes: key, title, parameter draw, elastic parameters.
CLASSES: list[tuple[str, str, Callable, dict[str, float]]] = [
    ("bump", "bump |h| 2-5, FWHM 15-24, anywhere", draw_bump, {}),
    ("sphere_convex", "sphere convex, R 50-100", draw_sphere(1.0), {}),
    ("sphere_concave", "sphere concave, R 50-100", draw_sphere(-1.0), {}),
    ("dome", "dome |R| 50-100, 1.2-2 x, any angle", draw_dome, {}),
    ("saddle", "saddle |R| 60-120, any angle", draw_saddle, {}),
    ("ridge", "ridge: 3 bumps in a line, any angle", draw_ridge, {}),
    ("two_bumps", "two bumps |h| 2-5, FWHM 15-24", draw_two_bumps, {}),
    ("cylinder", "cylinder |R| 50-100, any angle", draw_cylinder, {}),
    ("sphere_prestretch", "sphere |R| 50-100, 5 % pre-stretch", draw_sphere_any, {"prestretch": 0.05}),
    ("cylinder_prestretch", "cylinder any angle, 5 % pre-stretch", draw_cylinder, {"prestretch": 0.05}),
    ("poisson_0.3", "poisson 0.3 (bump/sphere/saddle/cyl.)", draw_mixed, {"poisson": 0.3}),
    ("friction_1e-3", "friction 1e-3 (bump/sphere/saddle/cyl.)", draw_mixed, {"friction": 0.001}),
]


def class_plans(key: str, seed: int, count: int, n: int, m: int | None = None, pitch: float = PITCH) -> list[ScenePlan]:
    """The first ``count`` scenes of class ``key`` on an n×m sheet."""
    m = n if m is None else m
    entry = next((c for c in CLASSES if c[0] == key), None)
    if entry is None:
        raise ValueError(f"unknown class {key!r}; known: {', '.join(c[0] for c in CLASSES)}")
    _, title, draw, elastic = entry
    sheet = Sheet(0.5 * (m - 1) * pitch, 0.5 * (n - 1) * pitch, max(1.0, max(n, m) / 5.0))
    plans = []
    for i in range(count):
        rng = np.random.default_rng(_entropy(seed, key, n, m, i, 0))
        terms, twist = draw(rng, sheet)
        plans.append(ScenePlan(key, title, i, n, m, pitch, seed, terms, dict(elastic), _spec(terms, elastic),
                               _spec(terms), twist))
    return plans


def solve_scene(plan: ScenePlan, cache: bool = True, cache_dir: str | Path | None = None) -> tuple[ph.Shape, float, bool]:
    """The elastic scene, the seconds it took and whether it was solved (False: loaded from the
    solver's disk cache, judged by no new file appearing there)."""
    directory = Path(cache_dir) if cache_dir is not None else scenes.cache_directory()
    before = set(directory.glob("*.npz")) if cache and directory.is_dir() else set()
    t0 = time.perf_counter()
    shape = scenes.parse_scene_spec(plan.spec, "elastic", plan.n, plan.m, plan.pitch, cache=cache, cache_dir=cache_dir)
    seconds = time.perf_counter() - t0
    if not cache:
        return shape, seconds, True
    after = set(directory.glob("*.npz")) if directory.is_dir() else set()
    return shape, seconds, bool(after - before)


def kinematic_shape(plan: ScenePlan) -> ph.Shape:
    return scenes.parse_scene_spec(plan.kinematic_spec, "kinematic", plan.n, plan.m, plan.pitch)


def noise_draw(plan: ScenePlan, draw: int, sd: float, shape: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Noise arrays (upper, lower) of draw ``draw`` for this scene (draw 0: the dataset's noisy copy)."""
    rng = np.random.default_rng(plan.entropy(2 + draw))
    return rng.normal(0.0, sd, shape), rng.normal(0.0, sd, shape)


def better_answer(surf: Any, frame_error: Callable[[np.ndarray], np.ndarray]) -> Any:
    """Of a reconstruction and, where it is flagged ambiguous, its mirror, the one whose nodes
    ``frame_error`` (nodes → node errors) finds nearer the truth: a frame flagged ambiguous is
    judged by the better of its two answers (its scatter too: between draws the answer may be
    either image, and the flag says so)."""
    answers = [surf] + ([surf.mirror] if getattr(surf, "mirror", None) is not None else [])
    return min(answers, key=lambda a: float(np.mean(frame_error(a.nodes))))


def scatter_over_sigma(nodes: list[np.ndarray], sigmas: list[np.ndarray], origin: np.ndarray | None = None) -> float:
    """The σ calibration of repeated noisy frames of one sheet: the median over the nodes of
    their Monte-Carlo scatter (the rms distance of each node from its mean over the frames)
    divided by the frames' mean σ there.  ``nodes``: per frame (K, 3) positions; ``sigmas``: per
    frame (K,) σ; ``origin``: (K,) True at the nodes left out, the frame's origin (default:
    where the mean σ is zero; pass the scatter part's zeros when ``sigmas`` is a σ with a floor)."""
    runs = np.asarray(nodes, dtype=float)
    scatter = np.sqrt(((runs - runs.mean(axis=0)) ** 2).sum(axis=2).mean(axis=0))
    sig = np.mean(np.asarray(sigmas, dtype=float), axis=0)
    keep = ~np.asarray(origin, dtype=bool) if origin is not None else sig > 0
    return float(np.median(scatter[keep] / sig[keep]))


def element_points(plan: ScenePlan, count: int = ELEMENTS) -> np.ndarray:
    """Random material points (count, 2) over the cells (within half a pitch of the outer ones)."""
    rng = np.random.default_rng(plan.entropy(1))
    hu, hv = 0.5 * plan.m * plan.pitch, 0.5 * plan.n * plan.pitch
    return np.stack([rng.uniform(-hu, hu, count), rng.uniform(-hv, hv, count)], axis=1)


# --------------------------------------------------------------------------- writing


def write_scene(plan: ScenePlan, out: Path, noise: float, elements: int, cache: bool,
                cache_dir: str | None) -> dict[str, Any]:
    shape, seconds, solved = solve_scene(plan, cache, cache_dir)
    n, m = plan.n, plan.m
    eu, el = ph.gauge_strains(shape, n, m, plan.pitch, H, H, GAUGE)
    du, dl = noise_draw(plan, 0, noise, eu.shape)
    uv = element_points(plan, elements)
    truth = ph.ground_truth(shape, n, m, plan.pitch, 0.0, uv)
    meta = plan.to_json()
    name = f"{plan.key}-{n}x{m}-{plan.index:02d}.npz"
    np.savez_compressed(
        out / name,
        eps_upper=eu, eps_lower=el, eps_upper_noisy=eu + du, eps_lower_noisy=el + dl, noise_sd=np.array(noise),
        nodes=truth.nodes, normals=truth.normals,
        element_uv=truth.element_uv, element_positions=truth.element_positions, element_normals=truth.element_normals,
        n=np.array(n), m=np.array(m), pitch=np.array(plan.pitch), h_upper=np.array(H), h_lower=np.array(H),
        gauge_length=np.array(GAUGE),
        spec=np.array(plan.spec), kinematic_spec=np.array(plan.kinematic_spec), meta=np.array(json.dumps(meta)),
        sheet_positions=shape.positions, sheet_grid=np.array([shape.grid.half_u, shape.grid.half_v, shape.grid.spacing]),
    )
    return {"file": name, "class": plan.key, "title": plan.title, "index": plan.index, "n": n, "m": m,
            "spec": plan.spec, "kinematic_spec": plan.kinematic_spec, "twist_sign": plan.twist_sign,
            "solve_seconds": round(seconds, 3), "solved": solved}


def _sizes(text: str) -> list[int]:
    try:
        sizes = [int(s) for s in text.split(",") if s.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"sizes must be integers separated by commas, got {text!r}") from None
    if not sizes or any(s < 2 for s in sizes):
        raise argparse.ArgumentTypeError(f"sizes must be integers >= 2, got {text!r}")
    return sizes


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True, type=Path, help="directory to write the scenes and index.json into")
    ap.add_argument("--seed", type=int, default=2024, help="seed of the shape parameters, element points and noise")
    ap.add_argument("--count", type=int, default=None, help="scenes per class and size (default 3, quick 1)")
    ap.add_argument("--sizes", type=_sizes, default=None,
                    help="sheet sizes N (N×N cells), comma-separated (default 5,16; quick 5); a 16×16 solve takes "
                         "about 5-20 s")
    ap.add_argument("--noise", type=float, default=NOISE, help="strain noise s.d. of the noisy copy (default 5.7e-5)")
    ap.add_argument("--elements", type=int, default=ELEMENTS, help="random material points per scene (default 8)")
    ap.add_argument("--classes", default=None,
                    help="comma-separated class keys (default all: " + ", ".join(c[0] for c in CLASSES) + ")")
    ap.add_argument("--quick", action="store_true", help="one scene per class, 5×5 only (unless --count/--sizes say)")
    ap.add_argument("--no-cache", action="store_true", help="solve every scene afresh (neither read nor write the cache)")
    ap.add_argument("--cache-dir", default=None, help="the solver's disk cache (default $SKINMAP_CACHE_DIR or "
                                                      "~/.cache/skinmap/mechanics)")
    args = ap.parse_args(argv)
    count = args.count if args.count is not None else (1 if args.quick else 3)
    sizes = args.sizes if args.sizes is not None else ([5] if args.quick else [5, 16])
    if count < 1 or args.elements < 1 or not (math.isfinite(args.noise) and args.noise >= 0):
        ap.error("--count and --elements must be >= 1, --noise a finite number >= 0")
    keys = [c[0] for c in CLASSES] if args.classes is None else [k.strip() for k in args.classes.split(",") if k.strip()]
    unknown = sorted(set(keys) - {c[0] for c in CLASSES})
    if unknown:
        ap.error(f"unknown class(es) {unknown}; known: {', '.join(c[0] for c in CLASSES)}")
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    cache = not args.no_cache
    where = "no cache" if not cache else f"cache {args.cache_dir or scenes.cache_directory()}"
    print(f"elastic dataset: seed {args.seed}, {count} per class, sizes {','.join(map(str, sizes))}, "
          f"noise s.d. {args.noise:g}, {len(keys)} classes -> {out} ({where})", flush=True)
    entries = []
    t_all = time.perf_counter()
    for n in sizes:
        for key in keys:
            for plan in class_plans(key, args.seed, count, n):
                entry = write_scene(plan, out, args.noise, args.elements, cache, args.cache_dir)
                entries.append(entry)
                how = "solved" if entry["solved"] else "cached"
                print(f"  {entry['file']:34s} {entry['solve_seconds']:7.2f} s {how}  {plan.spec}", flush=True)
    total = time.perf_counter() - t_all
    index = {
        "generator": "bench/elastic_dataset.py",
        "argv": sys.argv[1:] if argv is None else list(argv),
        "seed": args.seed, "count": count, "sizes": sizes, "classes": keys, "noise_sd": args.noise,
        "elements": args.elements, "pitch": PITCH, "h_upper": H, "h_lower": H, "gauge_length": GAUGE,
        "solver_version": scenes.SOLVER_VERSION, "seconds": round(total, 2), "scenes": entries,
    }
    (out / "index.json").write_text(json.dumps(index, indent=1) + "\n")
    solved = [e for e in entries if e["solved"]]
    print(f"wrote {len(entries)} scenes and index.json to {out} in {total:.1f} s "
          f"({len(solved)} solved, {sum(e['solve_seconds'] for e in solved):.1f} s of solves; "
          f"{len(entries) - len(solved)} from the cache)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
