"""Reconstruction benchmark: accuracy per shape class and time per frame.

Run: .venv/bin/python bench/reconstruction.py [--quick] [--seed S] [--shapes K] [--only accuracy|elastic|timing]
     [--sizes 5,8,12,16,32] [--elastic-sizes 5,12,16] [--elastic-shapes K] [--kernels compiled|numpy] [--general]

Accuracy (a table per size in --sizes, default 5 only): N×N cells, 12 mm pitch, h = 0.2 mm, 10 mm
gauges; strains from the physics forward model (skinmap.emulator.physics) for shapes with seeded
random parameters (on sheets larger than 5×5 the radii and bump positions grow with the sheet,
bump heights and widths stay); node error after the best rigid alignment, noise-free and with
strain noise s.d. 0.0057 % on every gauge (every reconstruction is told that s.d., as skinmapd
tells it the sensor's); the Cramér–Rao figure CR (`noise_floor`: the mean node error the noise
alone forces on the model linearised about its noise-free answer, beside which the noisy error
is read); the mean node_sigma and the count of overconfident noisy
reconstructions (some node's error above 3 node_sigma + 0.05 mm); for bumps
also the feature-size fidelity L_r/L_g (diameter of the largest circle inside the −6 dB contour
around the peak, reconstructed over true).

Elastic (a table per size in --elastic-sizes, default 5 only): the scene classes of
bench/elastic_dataset.py (bumps, convex and concave spheres, saddles at any angle, ridges, two
bumps, oblique cylinders, 5 % pre-stretched spheres and cylinders, Poisson 0.3 and friction 1e-3
variants; seeded random parameters, --elastic-shapes per class, default 2, quick 1; with the same
seed they are the first scenes of each class that elastic_dataset.py writes) solved as elastic
films on their molds (skinmap.emulator.scenes; each solve is kept in the solver's disk cache,
$SKINMAP_CACHE_DIR or ~/.cache/skinmap/mechanics: a 5×5 scene takes about 1 s to solve, a 16×16
one 5-20 s).  Per class: mean and largest node error after the best rigid alignment, noise-free
and noisy (the same noise draws as the dataset's, draw 0 being its noisy copy), the Cramér–Rao
figure CR of the elastic form (as above, from 12 draws, the first the noisy frames'), the mean node_sigma, and "over": how many reconstructions (noise-free and noisy) are overconfident, some
node's error exceeding 3 node_sigma + 0.05 mm with the surface's own node_sigma (a sensor-frame
s.d., zero at the centre node of an odd-sized sheet, while the errors are after alignment: the
0.05 mm floor covers that); then the same for the same shapes in kinematic form (the
closed-form maps, same noise).  Oblique cylinders get their (unobservable) twist_sign, except in
the row that leaves it to the default.  It measures the reconstruction as it is; nothing is
tuned to these scenes.

Timing: median and 90th percentile per frame of `reconstruct(...)` plus `locate` of 20 elements,
for N×N = 5, 8, 16, 32 on a slowly moving bump, warm (geometry cached, previous frame passed), on
one core (BLAS threads limited to 1 with threadpoolctl, as in the daemon); CPU time of the
frame's own thread; `Surface.points(per_pitch=20)`; the optional Clarabel field fit for
comparison; and the frame with node_sigma and locate_sigma (the daemon's full frame), all units
valid and when every frame brings a validity mask not seen before (3 dead units, and 10 % of
the units); a cold one-shot 5×5 `reconstruct()` (no previous frame, a new random bump each
frame); elastic films held still.
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # one core, as in the gateway

import argparse  # noqa: E402
import functools  # noqa: E402
import math  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from scipy import ndimage  # noqa: E402
from threadpoolctl import threadpool_limits  # noqa: E402

from skinmap.emulator import physics as ph  # noqa: E402
from skinmap.emulator import scenes  # noqa: E402
from skinmap.reconstruction import GRAPH_FIT_MAX_CELLS, Reconstructor, nodes_in_sensor_frame, reconstruct  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
import elastic_dataset as ed  # noqa: E402  (bench/elastic_dataset.py: the elastic scene classes)

PITCH, H, GAUGE = 12.0, 0.2, 10.0
NOISE = 0.0057e-2
# the strain s.d. the noise-free reconstructions are told: the sensor's, as skinmapd tells it
CLEAN_SIGMA = NOISE


def kabsch(p: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rotation r and centroids (pc, qc) such that (x − pc) r^T + qc best maps p onto q."""
    pc, qc = p.mean(0), q.mean(0)
    u, _, vt = np.linalg.svd((p - pc).T @ (q - qc))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    return vt.T @ np.diag([1.0, 1.0, d]) @ u.T, pc, qc


def node_errors(nodes: np.ndarray, truth: np.ndarray) -> np.ndarray:
    p, q = nodes.reshape(-1, 3), truth.reshape(-1, 3)
    r, pc, qc = kabsch(p, q)
    return np.linalg.norm((p - pc) @ r.T + qc - q, axis=1)


#: The step of the central difference that reads the answer's linear response to the noise, as
#: a share of one noise draw: small enough that no decision of the model changes (0.001 to 0.1
#: gave the same figure to four digits on the elastic classes), large enough for the model's
#: own convergence tolerances to vanish in it.
RESPONSE_STEP = 1e-2
#: Noise draws per Cramér–Rao figure (its own sampling error is about 1/√(2·draws) of it: 4 draws
#: read a 5×5 sphere's 0.0119 mm as 0.0093).
FLOOR_DRAWS = 12


def noise_floor(eu: np.ndarray, el: np.ndarray, draws: list[tuple[np.ndarray, np.ndarray]], **kw) -> float:
    """The Cramér–Rao figure of the model at these data: the mean node error (after the best
    rigid alignment) that the noise alone causes in the model linearised about its noise-free
    answer, averaged over ``draws`` (noise draws of the benchmark's s.d.).  Each is the central
    difference (x(y + tε) − x(y − tε))/2t of the answer x along the draw ε; for a model that is
    linear in the data near its answer, with Gaussian noise, the spread of these responses is the
    Cramér–Rao bound of that model's estimate, the least scatter the noise forces on it.  A noisy
    error above √(clean² + CR²) is the model's nonlinearity (a decision the noise flips), not the
    noise's due.  ``kw``: what ``reconstruct`` is told, as for the noisy frames.  NaN where the
    answer has no linear response there (the first draw's, read again at a quarter of the step,
    differs by more than 5 %: a decision of the model flips within the step)."""

    def response(du: np.ndarray, dl: np.ndarray, t: float) -> float:
        plus = reconstruct(eu + t * du, el + t * dl, PITCH, H, H, strain_sigma=NOISE, **kw).nodes
        minus = reconstruct(eu - t * du, el - t * dl, PITCH, H, H, strain_sigma=NOISE, **kw).nodes
        base = 0.5 * (plus + minus)
        return float(node_errors(base + (plus - minus) / (2.0 * t), base).mean())

    errs = [response(du, dl, RESPONSE_STEP) for du, dl in draws]
    check = response(*draws[0], 0.25 * RESPONSE_STEP)
    if not abs(check - errs[0]) <= 0.05 * errs[0]:
        return math.nan
    return float(np.mean(errs))


def floor_text(values: list[float]) -> str:
    """A column of Cramér–Rao figures: their mean over the scenes that have one, marked with
    '+' where some scene has none (no linear response), 'n/l' where none has."""
    arr = np.array(values, dtype=float)
    if not np.isfinite(arr).any():
        return "n/l"
    return f"{np.nanmean(arr):.4f}" + ("+" if not np.isfinite(arr).all() else "")


def feature_size(height: np.ndarray, peak: tuple[int, int], step: float) -> float:
    """Diameter (mm) of the largest circle inside the −6 dB (half-height) region around the peak."""
    region = height >= 0.5 * height[peak]
    labels, _ = ndimage.label(region)
    blob = np.pad(labels == labels[peak], 1)  # the sheet's edge bounds the region too
    return 2.0 * float(ndimage.distance_transform_edt(blob).max()) * step


def bump_fidelity(shape: ph.GaussianBumps, surf, n: int, m: int) -> float:
    """L_r / L_g on a 0.25 mm material grid, the reconstruction aligned to the truth by its nodes."""
    h_sign = np.sign(shape.bumps[0][0])
    step = 0.25 * max(1.0, n / 8.0)  # 0.25 mm on small sheets; a bounded grid on large ones
    u0, u1, v0, v1 = surf.extent
    us = np.arange(u0, u1 + 1e-9, step)
    vs = np.arange(v0, v1 + 1e-9, step)
    uu, vv = np.meshgrid(us, vs)
    uv = np.stack([uu.ravel(), vv.ravel()], axis=1)
    truth = shape.position(uv)
    r, pc, qc = kabsch(surf.nodes.reshape(-1, 3), shape.position(ph.cell_centres(n, m, PITCH)).reshape(-1, 3))
    recon = (surf.locate(uv)[0] - pc) @ r.T + qc
    z_g = h_sign * truth[:, 2].reshape(uu.shape)
    z_r = h_sign * recon[:, 2].reshape(uu.shape)
    peak_g = np.unravel_index(np.argmax(z_g), z_g.shape)
    peak_r = np.unravel_index(np.argmax(z_r), z_r.shape)
    return feature_size(z_r, peak_r, step) / feature_size(z_g, peak_g, step)


def shape_classes(rng: np.random.Generator, k: int, scale: float = 1.0) -> dict[str, list[tuple[object, dict]]]:
    """Seeded random shapes per class, each with the keyword arguments its reconstruction uses.
    ``scale``: radii and bump positions for a sheet that many times the 5×5 one's size (bump
    heights and widths stay: a sharp feature stays sharp)."""

    def signed(lo, hi):
        return float(np.exp(rng.uniform(np.log(lo), np.log(hi))) * rng.choice([-1.0, 1.0])) * scale

    classes: dict[str, list] = {"flat": [(ph.Flat(), {})]}
    classes["cylinder on a grid line, |R| 25-100"] = [
        (ph.Cylinder(signed(25, 100), axis_angle=float(rng.choice([0.0, 90.0]))), {}) for _ in range(k)
    ]
    classes["bump |h| 1-5, FWHM 15-30, anywhere"] = [
        (ph.GaussianBumps(height=signed(1, 5) / scale, fwhm=float(rng.uniform(15, 30)), centre=tuple(rng.uniform(-24, 24, 2) * scale)), {})
        for _ in range(k)
    ]
    classes["bump |h| 5, FWHM 15 (spec corner)"] = [
        (ph.GaussianBumps(height=5.0 * rng.choice([-1.0, 1.0]), fwhm=15.0, centre=tuple(rng.uniform(-24, 24, 2) * scale)), {})
        for _ in range(k)
    ]
    classes["sphere cap |R| 40-120"] = [(ph.SphereCap(signed(40, 120)), {}) for _ in range(k)]
    classes["saddle |R| 40-120"] = [(ph.Saddle(signed(40, 120)), {}) for _ in range(k)]
    # An oblique cylinder's twist sign(R)·sign(axis angle) is not observable (its mirror image
    # gives the same strains): rows with the default sign (+1), the other sign told via
    # twist_sign, and the other sign left to the default (the mirror image is reconstructed).
    obl = [(signed(30, 100), float(rng.uniform(10, 80))) for _ in range(k)]
    classes["oblique cylinder, twist > 0"] = [(ph.Cylinder(r, np.sign(r) * a), {}) for r, a in obl]
    classes["oblique cylinder, twist < 0, twist_sign=-1"] = [
        (ph.Cylinder(r, -np.sign(r) * a), {"twist_sign": -1}) for r, a in obl
    ]
    classes["oblique cylinder, twist < 0, default sign"] = [(ph.Cylinder(r, -np.sign(r) * a), {}) for r, a in obl]
    # Turned saddles (drawn last, so that the classes above keep their shapes): at ±15° and ±30°
    # the stretch pattern fixes the twist's sign; at 45° the saddle and its mirror image give
    # identical strains, so the sign must be told (twist_sign, the sign of z_uv = sin 2φ / R):
    # rows with it told and left to the default (half of them then come out mirrored).
    # Their own generator (spawned: the parent's stream is untouched), so that the noise draws of
    # the classes above stay as they were.
    rng_t = rng.spawn(1)[0]

    def signed_t(lo, hi):
        return float(np.exp(rng_t.uniform(np.log(lo), np.log(hi))) * rng_t.choice([-1.0, 1.0])) * scale

    turned = [(signed_t(50, 120), float(rng_t.choice([-30.0, -15.0, 15.0, 30.0]))) for _ in range(k)]
    classes["saddle turned +-15/30 deg, |R| 50-120"] = [(ph.Saddle(r, axis_angle=a), {}) for r, a in turned]
    at45 = [(signed_t(50, 120), float(rng_t.choice([-45.0, 45.0]))) for _ in range(k)]
    classes["saddle turned +-45 deg, twist_sign told"] = [
        (ph.Saddle(r, axis_angle=a), {"twist_sign": float(np.sign(r * a))}) for r, a in at45
    ]
    classes["saddle turned +-45 deg, default sign"] = [(ph.Saddle(r, axis_angle=a), {}) for r, a in at45]
    # A film pressed out of plane (graph mappings) with twist at any angle: saddles turned
    # anywhere in 0-180 deg, general quadrics (twisted domes, bowls, saddles, troughs) and oblique
    # troughs; the stretch pattern fixes the twist.  Their own generator, as above.
    rng_g = rng.spawn(1)[0]

    def signed_g(lo, hi):
        return float(np.exp(rng_g.uniform(np.log(lo), np.log(hi))) * rng_g.choice([-1.0, 1.0])) * scale

    classes["saddle at any angle (graph), |R| 40-120"] = [
        (ph.Saddle(signed_g(40, 120), axis_angle=float(rng_g.uniform(0, 180))), {}) for _ in range(k)
    ]
    classes["twisted quadric, |k_ij| <= 1/40 mm"] = [(ph.Quadric(*(rng_g.uniform(-1 / 40, 1 / 40, 3) / scale)), {})
                                                     for _ in range(k)]

    def trough(radius: float, angle: float) -> ph.Quadric:
        d = np.array([np.cos(np.radians(angle)), np.sin(np.radians(angle))])
        return ph.Quadric(d[0] * d[0] / radius, d[0] * d[1] / radius, d[1] * d[1] / radius)

    classes["oblique trough pressed in (graph), |R| 50-120"] = [
        (trough(signed_g(50, 120), float(rng_g.uniform(10, 80))), {}) for _ in range(k)
    ]
    return classes


def accuracy_table(k: int, noisy_draws: int, seed: int, graph_fit: bool | None = None, n: int = 5) -> None:
    rng = np.random.default_rng(seed)
    floor_rng = np.random.default_rng(seed + 1)  # the Cramér–Rao draws, apart: the noisy frames keep theirs
    m = n
    scale = (n - 1) / 4.0  # radii and positions for this sheet's extent (the 5x5 classes as given)
    centres = ph.cell_centres(n, m, PITCH)
    model = "the general model alone (graph_fit=False)" if graph_fit is False else "the default model (graph fit first)"
    print(f"\nAccuracy of {model}, {n}x{m} cells, pitch {PITCH:g} mm, h = {H:g} mm, {GAUGE:g} mm gauges "
          f"({k} random shapes per class, seed {seed}; clean: told strain_sigma={CLEAN_SIGMA:g}; noisy: s.d. {100 * NOISE:.4f} % "
          f"strain, told so, {noisy_draws} draws each; radii and bump positions x{scale:g} of the 5x5 classes, "
          f"bump sizes as given)")
    head = (f"{'shape class':44s} {'clean mean':>10s} {'clean max':>10s} {'noisy mean':>10s} {'noisy max':>10s} "
            f"{'CR':>6s} {'sigma':>6s} {'over':>5s} {'frame':>5s} {'L_r/L_g':>16s} {'graph':>6s} {'amb':>5s} {'either':>7s}")
    print(head)
    print("-" * len(head))
    for name, shapes in shape_classes(rng, k, scale).items():
        clean_mean, clean_max, noisy_mean, noisy_max, fid, graphs = [], [], [], [], [], []
        ambiguous, either = [], []  # flagged ambiguous; of those, the answer or its mirror right (0.05 mm)
        sigmas, over, in_frame, floor = [], [], [], []
        for shape, kw in shapes:
            eu, el = ph.gauge_strains(shape, n, m, PITCH, H, H, GAUGE)
            truth = shape.position(centres)
            surf = reconstruct(eu, el, PITCH, H, H, graph_fit=graph_fit, strain_sigma=CLEAN_SIGMA, **kw)
            e = node_errors(surf.nodes, truth)
            graphs.append(surf.diagnostics.extra["model"] == "graph")
            _ambiguity(surf, e, truth, ambiguous, either)
            clean_mean.append(e.mean())
            clean_max.append(e.max())
            draws = [(rng.normal(0, NOISE, eu.shape), rng.normal(0, NOISE, el.shape)) for _ in range(noisy_draws)]
            floor.append(noise_floor(eu, el, [(floor_rng.normal(0, NOISE, eu.shape), floor_rng.normal(0, NOISE, el.shape))
                                              for _ in range(FLOOR_DRAWS)], graph_fit=graph_fit, **kw))
            for du, dl in draws:
                noisy = reconstruct(eu + du, el + dl, PITCH, H, H, graph_fit=graph_fit, **kw)
                e = node_errors(noisy.nodes, truth)
                graphs.append(noisy.diagnostics.extra["model"] == "graph")
                _ambiguity(noisy, e, truth, ambiguous, either)
                noisy_mean.append(e.mean())
                noisy_max.append(e.max())
                sigmas.append(noisy.node_sigma.mean())
                over.append(_over(e, noisy, truth))
                in_frame.append(_over_in_frame(shape, noisy, n))
            if isinstance(shape, ph.GaussianBumps):
                fid.append(bump_fidelity(shape, surf, n, m))
        f = f"{np.mean(fid):.3f} [{np.min(fid):.2f},{np.max(fid):.2f}]" if fid else "-"
        print(f"{name:44s} {np.mean(clean_mean):10.4f} {np.max(clean_max):10.4f} "
              f"{np.mean(noisy_mean):10.4f} {np.max(noisy_max):10.4f} {floor_text(floor):>6s} {np.mean(sigmas):6.3f} "
              f"{sum(over):>2d}/{len(over):<2d} {sum(in_frame):>2d}/{len(in_frame):<2d} {f:>16s} {100 * np.mean(graphs):5.0f}% "
              f"{sum(ambiguous):>2d}/{len(ambiguous):<2d} {sum(either):>3d}/{sum(ambiguous):<3d}")
    print("(mm; mean = mean over shapes of the mean node error, max = largest node error of any shape; CR: the "
          "Cramér–Rao figure, the mean node error the noise alone forces on the model linearised about its noise-free "
          "answer (noise_floor), mean over shapes: the noisy error should not exceed about √(clean² + CR²), '+': some "
          "shape has no linear response, 'n/l': none has; sigma: mean "
          "node_sigma of the noisy reconstructions; over: noisy reconstructions with some node error > 3 node_sigma + "
          "0.05 mm (for one flagged ambiguous: in both its answers), after the best rigid alignment; frame: the same "
          "with the errors in the sensor frame itself (frame_errors); node_sigma describes both (its alignment floor); "
          "graph: share of reconstructions the height-graph fit answered, the rest the general model; amb: "
          "reconstructions flagged ambiguous (Surface.mirror set), either: of those, how many have the answer or "
          "its mirror within 0.05 mm mean of the truth)")


def _ambiguity(surf, e: np.ndarray, truth: np.ndarray, ambiguous: list, either: list) -> None:
    ambiguous.append(surf.mirror is not None)
    if surf.mirror is not None:
        either.append(min(e.mean(), node_errors(surf.mirror.nodes, truth).mean()) < 0.05)


#: Moving shapes for the warm-chain table: (label, height mm, FWHM mm, ellipse half-axes mm, frames a turn)
WARM_CHAIN_SHAPES = (("bump circling", 3.0, 36.0, (12.0, 6.0), 60), ("dent circling", -3.5, 30.0, (10.0, 10.0), 70),
                     ("broad dent", -2.5, 40.0, (14.0, 9.0), 80))


def warm_chain_table(frames: int, seed: int, sizes: tuple[int, ...] = (5, 8)) -> None:
    """Slowly moving broad shapes reconstructed frame after frame warm from the one before, as
    skinmapd and a library caller chaining ``previous`` run them, against each frame
    reconstructed cold: mean and largest mean node error, the frames with some node beyond
    3 node_sigma + 0.05 mm, and the frames a warm fit was refused for another basin
    (reconstructor.WARM_BASIN_RATIO) and fitted cold."""
    print(f"\nWarm chains: {frames} noisy frames of a shape moving on an ellipse, each warm from the one before "
          "(cold: each frame alone)")
    print(f"{'N x N':>7s} {'shape':16s} {'warm mean':>10s} {'warm max':>9s} {'beyond':>7s} {'refits':>7s} "
          f"{'cold mean':>10s} {'cold max':>9s} {'beyond':>7s}")
    for n in sizes:
        centres = ph.cell_centres(n, n, PITCH)
        rec = Reconstructor(n, n, PITCH, H, H, GAUGE)
        for label, height, fwhm, (ax, ay), period in WARM_CHAIN_SHAPES:
            rng = np.random.default_rng(seed)
            data = []
            for k in range(frames):
                phase = 2 * np.pi * k / period
                shape = ph.GaussianBumps(height=height, fwhm=fwhm, centre=(ax * np.cos(phase), ay * np.sin(phase)))
                eu, el = ph.gauge_strains(shape, n, n, PITCH, H, H, GAUGE)
                data.append((eu + rng.normal(0, NOISE, eu.shape), el + rng.normal(0, NOISE, el.shape),
                             shape.position(centres)))
            row = []
            for warm in (True, False):
                prev, errs, beyond, refits = None, [], 0, 0
                for k, (eu, el, truth) in enumerate(data):
                    prev = rec(eu, el, previous=prev if warm else None)
                    err = node_errors(prev.nodes, truth)
                    errs.append(float(err.mean()))
                    beyond += bool(np.any(err > 3.0 * prev.node_sigma.ravel() + 0.05))
                    refits += warm and k > 0 and prev.diagnostics.extra.get("graph_fit") in ("linear", "general")
                row.append((np.mean(errs), max(errs), beyond, refits))
            (wm, wx, wb, wr), (cm, cx, cb, _) = row
            print(f"{n:>3d}x{n:<3d} {label:16s} {wm:10.4f} {wx:9.4f} {wb:>3d}/{frames:<3d} {wr:7d} {cm:10.4f} {cx:9.4f} "
                  f"{cb:>3d}/{frames:<3d}")


def bump_grid_table(positions: int, seed: int) -> None:
    """Noise-free mean node error of bumps by height and FWHM, ``positions`` random centres each."""
    rng = np.random.default_rng(seed)
    n = m = 5
    centres = ph.cell_centres(n, m, PITCH)
    fwhms = (15.0, 18.0, 20.0, 25.0)
    print(f"\nBumps by height and FWHM, {n}x{m}: noise-free mean node error (mm), {positions} random centres each "
          f"(max in brackets)")
    print(f"{'|h| mm':>10s} " + " ".join(f"{'FWHM ' + format(f, '.0f'):>15s}" for f in fwhms))
    for height in (2.0, 3.0, 4.0, 5.0):
        cells = []
        for fwhm in fwhms:
            errs = []
            for _ in range(positions):
                shape = ph.GaussianBumps(height=height * rng.choice([-1.0, 1.0]), fwhm=fwhm,
                                         centre=tuple(rng.uniform(-24, 24, 2)))
                eu, el = ph.gauge_strains(shape, n, m, PITCH, H, H, GAUGE)
                errs.append(node_errors(reconstruct(eu, el, PITCH, H, H).nodes, shape.position(centres)).mean())
            cells.append(f"{np.mean(errs):.3f} [{np.max(errs):.3f}]")
        print(f"{height:>10.0f} " + " ".join(f"{c:>15s}" for c in cells))


@functools.lru_cache(maxsize=4)
def _fine_grid(n: int):
    """The fine grid of reconstruct()'s n×n sheets (their positions' material coordinates)."""
    return Reconstructor(n, n, PITCH, H, H, GAUGE).grid


def frame_errors(shape: ph.Shape, nodes: np.ndarray, n: int) -> np.ndarray:
    """Node errors in the sensor frame itself, with no alignment: the truth put in the frame by
    its one definition (nodes_in_sensor_frame)."""
    return np.linalg.norm(nodes - nodes_in_sensor_frame(_fine_grid(n), shape.position), axis=-1).reshape(-1)


def _over_in_frame(shape: ph.Shape, surf, n: int) -> bool:
    """Overconfident in the sensor frame: some node's error there (frame_errors) above 3 of its
    node_sigma + 0.05 mm, for the answer and, where it says it is ambiguous, its mirror."""
    bound = 3.0 * surf.node_sigma.reshape(-1) + 0.05
    answers = [surf] + ([surf.mirror] if getattr(surf, "mirror", None) is not None else [])
    return all(bool(np.any(frame_errors(shape, a.nodes, n) > bound)) for a in answers)


def _over(e: np.ndarray, surf, truth: np.ndarray | None = None) -> bool:
    """Overconfident: some node's error exceeds 3 of the surface's own node_sigma + 0.05 mm.
    A surface that says it is ambiguous (``surf.mirror``) is overconfident only when neither
    of its two answers is within that bound."""
    sigma = surf.node_sigma.reshape(-1)
    if not np.any(e > 3.0 * sigma + 0.05):
        return False
    mirror = getattr(surf, "mirror", None)
    if mirror is None or truth is None:
        return True
    return bool(np.any(node_errors(mirror.nodes, truth) > 3.0 * sigma + 0.05))


def elastic_classes(only: list[str] | None) -> list[tuple]:
    """The dataset's classes (bench/elastic_dataset.py), or those of ``only`` (keys) in its order."""
    return [c for c in ed.CLASSES if only is None or c[0] in only]


def elastic_table(n: int, k: int, noisy_draws: int, seed: int, graph_fit: bool | None = None,
                  only: list[str] | None = None) -> None:
    """Node errors on elastic scenes (films laminated on molds, bench/elastic_dataset.py) and on
    the same shapes' kinematic form, and the count of overconfident reconstructions."""
    print(f"\nElastic scenes (film on a mold, skinmap.emulator.scenes), {n}x{n} cells, pitch {PITCH:g} mm, "
          f"h = {H:g} mm, {GAUGE:g} mm gauges ({k} random scenes per class, seed {seed}; noisy: s.d. "
          f"{100 * NOISE:.4f} % strain, {noisy_draws} draws each, the same draws on both forms)")
    head = (f"{'elastic scene class':46s} {'clean mean':>10s} {'clean max':>9s} {'noisy mean':>10s} {'noisy max':>9s} "
            f"{'CR':>6s} {'sigma':>6s} {'over':>5s} {'frame':>5s} {'amb':>3s} | {'kin clean':>9s} {'kin noisy':>9s} {'kin over':>8s} {'kamb':>4s} | {'graph':>5s}")
    print(head)
    print("-" * len(head))
    solved, cached = [], []
    for key, title, _, _ in elastic_classes(only):
        plans = ed.class_plans(key, seed, k, n)
        rows = [(title, False)]
        if key == "cylinder":  # the mirror-ambiguity cases: the sign told, and left to the default
            rows = [(title + ", sign told", False), (title + ", default sign", True)]
        cases = []
        for plan in plans:
            shape, seconds, was_solved = ed.solve_scene(plan)
            (solved if was_solved else cached).append(seconds)
            forms = []
            for form in (shape, ed.kinematic_shape(plan)):
                eu, el = ph.gauge_strains(form, n, n, PITCH, H, H, GAUGE)
                forms.append((eu, el, ph.ground_truth(form, n, n, PITCH).nodes))
            noise = [ed.noise_draw(plan, d, NOISE, forms[0][0].shape) for d in range(noisy_draws)]
            cases.append((plan, forms, noise, shape))
        for name, default_sign in rows:
            stats: dict[str, list] = {col: [] for col in ("cm", "cx", "nm", "nx", "cr", "sig", "over", "frame", "amb", "kc", "kn", "kover", "kamb", "graph")}
            for plan, forms, noise, shape in cases:
                kw = {} if default_sign or plan.twist_sign is None else {"twist_sign": plan.twist_sign}
                for f, (eu, el, truth) in enumerate(forms):
                    prefix = "" if f == 0 else "k"
                    surf = reconstruct(eu, el, PITCH, H, H, graph_fit=graph_fit, strain_sigma=CLEAN_SIGMA, **kw)
                    e = node_errors(surf.nodes, truth)
                    stats["amb" if f == 0 else "kamb"].append(surf.mirror is not None)
                    if f == 0:
                        stats["cm"].append(e.mean())
                        stats["cx"].append(e.max())
                        floor_draws = [ed.noise_draw(plan, d, NOISE, eu.shape) for d in range(FLOOR_DRAWS)]
                        stats["cr"].append(noise_floor(eu, el, floor_draws, graph_fit=graph_fit, **kw))
                        stats["graph"].append(surf.diagnostics.extra["model"] == "graph")
                    else:
                        stats["kc"].append(e.mean())
                    for du, dl in noise:
                        surf = reconstruct(eu + du, el + dl, PITCH, H, H, graph_fit=graph_fit, **kw)
                        e = node_errors(surf.nodes, truth)
                        stats[prefix + "over"].append(_over(e, surf, truth))
                        stats[prefix + "amb"].append(surf.mirror is not None)
                        if f == 0:
                            stats["frame"].append(_over_in_frame(shape, surf, n))
                            stats["nm"].append(e.mean())
                            stats["nx"].append(e.max())
                            stats["sig"].append(surf.node_sigma.mean())
                            stats["graph"].append(surf.diagnostics.extra["model"] == "graph")
                        else:
                            stats["kn"].append(e.mean())
            over = f"{sum(stats['over'])}/{len(stats['over'])}"
            frame = f"{sum(stats['frame'])}/{len(stats['frame'])}"
            kover = f"{sum(stats['kover'])}/{len(stats['kover'])}"
            amb, kamb = f"{sum(stats['amb'])}", f"{sum(stats['kamb'])}"
            print(f"{name:46s} {np.mean(stats['cm']):10.4f} {np.max(stats['cx']):9.4f} {np.mean(stats['nm']):10.4f} "
                  f"{np.max(stats['nx']):9.4f} {floor_text(stats['cr']):>6s} {np.mean(stats['sig']):6.3f} {over:>5s} {frame:>5s} {amb:>3s} | {np.mean(stats['kc']):9.4f} "
                  f"{np.mean(stats['kn']):9.4f} {kover:>8s} {kamb:>4s} | {100 * np.mean(stats['graph']):4.0f}%")
    scale = f"x{n / 5:g} on this sheet" if n > 5 else "as given"
    print(f"(mm; mean = mean over scenes of the mean node error after the best rigid alignment, max = largest "
          f"node error of any scene; clean reconstructions are told strain_sigma={CLEAN_SIGMA:g}, noisy ones the noise's s.d.; "
          f"CR: the Cramér–Rao figure, the mean node error the noise alone forces on the model linearised about its "
          f"noise-free answer (noise_floor, {FLOOR_DRAWS} draws, the first the noisy frames'), mean over scenes: the noisy error should not exceed about "
          f"√(clean² + CR²); '+': some scene has no linear response (a decision flips within the step), 'n/l': none has; "
          f"sigma: mean node_sigma of the noisy reconstructions; over: noisy reconstructions "
          f"with some node error > 3 node_sigma + 0.05 mm (for one flagged ambiguous: in both its answers); frame: the same with the errors in the sensor frame itself, no alignment (frame_errors: the truth put in the frame by its definition); node_sigma describes both (its alignment floor); amb: reconstructions flagged ambiguous (Surface.mirror set); kin: the same shapes in kinematic "
          f"form, same noise; graph: share of the elastic reconstructions the height-graph fit answered; radii "
          f"{scale}; oblique cylinders get their twist_sign except in the default-sign row)")
    print(f"(scenes: {len(solved)} solved in {sum(solved):.1f} s, {len(cached)} loaded from the solver's cache "
          f"in {sum(cached):.1f} s)")


def calibration_table(n: int, k: int, draws: int, seed: int, graph_fit: bool | None = None,
                      only: list[str] | None = None) -> None:
    """σ calibration on the elastic scenes and their kinematic form: the Monte-Carlo scatter of
    every node over ``draws`` noisy frames (sensor frame, as node_sigma is) divided by the mean
    node_scatter_sigma of those frames (the part of σ that repeated frames scatter by), its
    median over the nodes (the centre node, the frame's origin, left out); the same divided by
    the whole node_sigma (which adds the model's resolution term, a bias bound no repeat
    shows); and the largest error over the draws in units of 3σ + 0.05 mm (the whole σ), in
    the sensor frame itself (frame_errors) and after the best rigid alignment (node_errors),
    both of which node_sigma describes (the alignment moves errors onto the centre, the frame's
    origin, which its alignment floor covers); a
    reconstruction flagged ambiguous by the better of its two answers (its scatter too: between
    draws the answer may be either image, and the flag says so)."""
    print(f"\nUncertainty calibration, {n}x{n} cells ({k} scenes per class, {draws} noisy draws each, s.d. "
          f"{100 * NOISE:.4f} % strain): median over nodes of Monte-Carlo scatter / node_scatter_sigma "
          f"(in brackets: / node_sigma)")
    head = (f"{'elastic scene class':46s} {'elastic':>13s} {'kinematic':>13s}   {'worst err/(3s+0.05), elastic: frame':>35s} "
            f"{'aligned':>8s} {'kinematic: frame':>16s} {'aligned':>8s}")
    print(head)
    print("-" * len(head))
    ratios_all: dict[int, list[float]] = {0: [], 1: []}
    whole_all: dict[int, list[float]] = {0: [], 1: []}
    for key, title, _, _ in elastic_classes(only):
        cells: dict[int, list[float]] = {0: [], 1: []}
        whole: dict[int, list[float]] = {0: [], 1: []}
        worst = np.zeros((2, 2))  # [form, (frame, aligned)]
        for plan in ed.class_plans(key, seed, k, n):
            shape, _, _ = ed.solve_scene(plan)
            kw = {} if plan.twist_sign is None else {"twist_sign": plan.twist_sign}
            for f, form in enumerate((shape, ed.kinematic_shape(plan))):
                eu, el = ph.gauge_strains(form, n, n, PITCH, H, H, GAUGE)
                truth = ph.ground_truth(form, n, n, PITCH).nodes
                nodes, sigmas, scatters = [], [], []
                for d in range(draws):
                    du, dl = ed.noise_draw(plan, d, NOISE, eu.shape)
                    surf = reconstruct(eu + du, el + dl, PITCH, H, H, graph_fit=graph_fit, **kw)
                    # one flagged ambiguous is judged by the better of its two answers, as _over does
                    answers = [surf] + ([surf.mirror] if surf.mirror is not None else [])
                    better = ed.better_answer(surf, lambda p: frame_errors(form, p, n))
                    nodes.append(better.nodes.reshape(-1, 3))
                    sigmas.append(surf.node_sigma.reshape(-1))
                    scatters.append(surf.node_scatter_sigma.reshape(-1))
                    bound = 3.0 * sigmas[-1] + 0.05
                    worst[f, 0] = max(worst[f, 0], min(float(np.max(frame_errors(form, a.nodes, n) / bound)) for a in answers))
                    worst[f, 1] = max(worst[f, 1], min(float(np.max(node_errors(a.nodes, truth) / bound)) for a in answers))
                cells[f].append(ed.scatter_over_sigma(nodes, scatters))
                whole[f].append(ed.scatter_over_sigma(nodes, sigmas, origin=np.mean(scatters, axis=0) == 0))
        for f in (0, 1):
            ratios_all[f].extend(cells[f])
            whole_all[f].extend(whole[f])
        text = [f"{np.median(cells[f]):.2f} ({np.median(whole[f]):.2f})" for f in (0, 1)]
        print(f"{title:46s} {text[0]:>13s} {text[1]:>13s}   {worst[0, 0]:35.2f} {worst[0, 1]:8.2f} "
              f"{worst[1, 0]:16.2f} {worst[1, 1]:8.2f}")
    inside = [100 * np.mean([(0.7 <= r <= 1.5) for r in ratios_all[f]]) for f in (0, 1)]
    inside_whole = [100 * np.mean([(0.7 <= r <= 1.5) for r in whole_all[f]]) for f in (0, 1)]
    print(f"(scenes with the median scatter / node_scatter_sigma in [0.7, 1.5]: elastic {inside[0]:.0f} %, "
          f"kinematic {inside[1]:.0f} % (scatter / node_sigma: {inside_whole[0]:.0f} % and {inside_whole[1]:.0f} %); "
          f"worst err/(3s+0.05) > 1 means some node of some noisy frame was off by more "
          f"than 3 node_sigma + 0.05 mm, in the sensor frame or after the best rigid alignment)")


def time_frames(rec: Reconstructor, frames: list, uv: np.ndarray, uncertainty: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Wall-clock and CPU seconds per frame (CPU time is what the frame costs this thread, and
    stays meaningful when other processes share the cores); ``uncertainty`` adds node_sigma and
    locate_sigma, as the daemon's full frame takes them."""
    wall, cpu = [], []
    prev = None
    for eu, el in frames:
        t0, c0 = time.perf_counter(), time.thread_time()
        surf = rec(eu, el, previous=prev)
        surf.nodes, surf.normals  # what the daemon publishes (computed with the surface)
        surf.locate(uv)
        if uncertainty:
            surf.node_sigma, surf.locate_sigma(uv)
        wall.append(time.perf_counter() - t0)
        cpu.append(time.thread_time() - c0)
        prev = surf
    return np.array(wall), np.array(cpu)


def time_unseen_masks(rec: Reconstructor, frames: list, uv: np.ndarray, rng: np.random.Generator,
                      dead: int = 3) -> np.ndarray:
    """CPU seconds per frame when every frame has a validity mask not seen before: ``dead``
    random units read NaN (a flickering or rejected gauge), and the frame also takes
    node_sigma and locate_sigma as the daemon does."""
    cpu = []
    prev = None
    n_units = frames[0][0].size
    for eu, el in frames:
        eu = eu.copy()
        eu.reshape(-1)[rng.choice(n_units, dead, replace=False)] = np.nan
        c0 = time.thread_time()
        surf = rec(eu, el, previous=prev)
        surf.nodes, surf.normals, surf.node_sigma
        surf.locate(uv), surf.locate_sigma(uv)
        cpu.append(time.thread_time() - c0)
        prev = surf
    return np.array(cpu)


def timing_table(sizes: list[int], frames_for: dict[int, int], seed: int, kernels: str = "compiled",
                 graph_fit: bool | None = None) -> None:
    rng = np.random.default_rng(seed)
    t0, c0 = time.perf_counter(), time.thread_time()
    Reconstructor(2, 2, kernels=kernels)  # loads (or compiles) the kernels once per process
    print(f"\nKernels: {kernels}; loading them took {time.perf_counter() - t0:.2f} s "
          f"({time.thread_time() - c0:.2f} s CPU), once per process, before the setups below")
    print("\nTime per frame: reconstruct + locate(20 elements), warm, one core, one BLAS thread; "
          + ("the general model alone" if graph_fit is False else
             f"graph fit first on sheets of up to {GRAPH_FIT_MAX_CELLS} cells (N <= 8)"))
    head = (f"{'N x N':>7s} {'fine grid':>10s} {'setup ms':>9s} {'median ms':>10s} {'p90 ms':>8s} "
            f"{'cpu median ms':>14s} {'cpu p90 ms':>11s} {'points(20) ms':>14s} {'clarabel fit median ms':>23s}")
    print(head)
    print("-" * len(head))
    medians = {}
    unseen: dict[int, tuple[float, float, float]] = {}
    for n in sizes:
        half = 0.5 * n * PITCH
        uv = rng.uniform(-half, half, size=(20, 2))
        count = frames_for[n]
        frames = []
        for k in range(count):
            phase = 2 * np.pi * k / max(count, 1)
            shape = ph.GaussianBumps(height=3.0, fwhm=max(18.0, 0.4 * n * PITCH),
                                     centre=(0.3 * half * np.cos(phase), 0.3 * half * np.sin(phase)))
            eu, el = ph.gauge_strains(shape, n, n, PITCH, H, H, GAUGE)
            frames.append((eu + rng.normal(0, NOISE, eu.shape), el + rng.normal(0, NOISE, el.shape)))
        t0 = time.perf_counter()
        rec = Reconstructor(n, n, PITCH, H, H, GAUGE, kernels=kernels, graph_fit=graph_fit)
        surf = rec(*frames[0])
        setup = time.perf_counter() - t0
        t, cpu = time_frames(rec, frames, uv)
        medians[n] = np.median(cpu)
        surf.node_sigma  # the all-valid uncertainty, once per geometry
        many = max(1, round(0.1 * 2 * n * n))  # a failing sensor: 10 % of the units, new every frame
        _, cpu_sigma = time_frames(rec, frames, uv, uncertainty=True)
        unseen[n] = (np.median(cpu_sigma), np.median(time_unseen_masks(rec, frames, uv, rng)),
                     np.median(time_unseen_masks(rec, frames[:10], uv, rng, dead=many)))
        surf.points(per_pitch=20)  # builds the cached sampling bases
        pts = []
        for _ in range(5):
            c0 = time.thread_time()
            surf.points(per_pitch=20)
            pts.append(time.thread_time() - c0)
        cl = "-"
        if n <= 16:
            # Clarabel solves the general model's field fit (a graph fit has no convex step)
            rec_c = Reconstructor(n, n, PITCH, H, H, GAUGE, convex_solver="clarabel", kernels=kernels, graph_fit=False)
            rec_c(*frames[0])
            tc, _ = time_frames(rec_c, frames[: max(5, count // 10)], uv)
            cl = f"{1e3 * np.median(tc):.1f}"
        print(f"{n:>3d}x{n:<3d} {rec.grid.nf:>4d}x{rec.grid.mf:<5d} {1e3 * setup:9.1f} {1e3 * np.median(t):10.2f} "
              f"{1e3 * np.percentile(t, 90):8.2f} {1e3 * medians[n]:14.2f} {1e3 * np.percentile(cpu, 90):11.2f} "
              f"{1e3 * np.median(pts):14.1f} {cl:>23s}")
    if len(medians) > 1:
        lo, hi = min(medians), max(medians)
        print(f"scaling {lo}->{hi}: cpu time x{medians[hi] / medians[lo]:.1f} for cells x{(hi / lo) ** 2:.0f} "
              f"(N^3 would be x{(hi / lo) ** 3:.0f})")
    print("\nUnseen mask each frame: random dead units, a new mask every frame; "
          "reconstruct + node_sigma + locate + locate_sigma (cpu median ms; all valid: the same frame without dead units)")
    print(f"{'N x N':>7s} {'all valid':>10s} {'3 dead':>8s} {'ratio':>6s} {'10 % dead':>10s} {'ratio':>6s}")
    for n, (base, cost, cost_many) in unseen.items():
        print(f"{n:>3d}x{n:<3d} {1e3 * base:10.2f} {1e3 * cost:8.2f} {cost / base:6.2f} "
              f"{1e3 * cost_many:10.2f} {cost_many / base:6.2f}")
    cold_timing(max(frames_for[min(frames_for)] // 2, 20), seed, kernels)
    elastic_timing(frames_for[min(frames_for)], seed, kernels)
    held_stream_table(30, seed, kernels)
    sharp_stream_table(30, seed, kernels)
    print(f"(load average during the run: {', '.join(f'{x:.1f}' for x in os.getloadavg())})")


def cold_timing(count: int, seed: int, kernels: str = "compiled") -> None:
    """CPU per cold one-shot 5×5 frame, as the module's ``reconstruct()`` runs it (the geometry's
    Reconstructor kept by the process, no previous frame): a different random noisy bump every
    frame, its nodes and normals."""
    rng = np.random.default_rng(seed)
    rec = Reconstructor(5, 5, PITCH, H, H, GAUGE, kernels=kernels)  # what reconstruct() keeps per geometry
    rec.prepare()
    cpu, models = [], []
    for _ in range(count):
        shape = ph.GaussianBumps(height=rng.uniform(-4.0, 4.0), fwhm=rng.uniform(16.0, 25.0),
                                 centre=tuple(rng.uniform(-20.0, 20.0, 2)))
        eu, el = ph.gauge_strains(shape, 5, 5, PITCH, H, H, GAUGE)
        eu, el = eu + rng.normal(0, NOISE, eu.shape), el + rng.normal(0, NOISE, el.shape)
        c0 = time.thread_time()
        surf = rec(eu, el)  # as reconstruct(eu, el, ...): no previous frame
        surf.nodes, surf.normals
        cpu.append(time.thread_time() - c0)
        models.append(surf.diagnostics.extra["model"])
    arr = np.array(cpu)
    print(f"\nCold one-shot reconstruct(), 5x5, {count} random noisy bumps (no previous frame): cpu median "
          f"{1e3 * np.median(arr):.2f} ms, p90 {1e3 * np.percentile(arr, 90):.2f} ms "
          f"(answered by the graph fit: {models.count('graph')} of {count})")


#: Elastic films held still, whose frames the general model answers (a film slides: no graph).
ELASTIC_TIMING_SPECS = ("saddle:radius=90,axis_angle=75", "sphere:radius=70", "gaussian:height=3,fwhm=18,u0=4,v0=-3")


def _held_frames(rec: Reconstructor, eu: np.ndarray, el: np.ndarray, rng: np.random.Generator, count: int):
    """(surface, CPU seconds of its frame) for ``count`` noisy frames of one still scene, each
    reconstructed warm from the one before, as skinmapd runs them."""
    prev = None
    for _ in range(count):
        du, dl = rng.normal(0, NOISE, eu.shape), rng.normal(0, NOISE, el.shape)
        c0 = time.thread_time()
        prev = rec(eu + du, el + dl, previous=prev)
        prev.nodes, prev.normals
        yield prev, time.thread_time() - c0


def elastic_timing(count: int, seed: int, kernels: str = "compiled") -> None:
    """CPU per warm frame on films laminated on molds (5×5, noisy frames of one still scene):
    the general model with the stretch pattern's twist (the membrane's reading, its refinement,
    the mirror), which the moving bump above never reaches."""
    rng = np.random.default_rng(seed)
    rec = Reconstructor(5, 5, PITCH, H, H, GAUGE, kernels=kernels)
    rec.prepare()
    print("\nElastic films held still, 5x5 (reconstruct, warm, noisy; the general model: a film slides, no graph)")
    print(f"{'scene':42s} {'cpu median ms':>14s} {'cpu p90 ms':>11s}  twist")
    for spec in ELASTIC_TIMING_SPECS:
        shape = scenes.parse_scene_spec(spec, "elastic", 5, 5, PITCH)
        eu, el = ph.gauge_strains(shape, 5, 5, PITCH, H, H, GAUGE)
        prev, cpu = None, []
        for prev, seconds in _held_frames(rec, eu, el, rng, max(count // 4, 12)):
            cpu.append(seconds)
        assert prev is not None
        cpu_arr = np.array(cpu[2:])
        how = prev.diagnostics.extra.get("stretch_reading", ("none",))[0]
        print(f"{spec:42s} {1e3 * np.median(cpu_arr):14.2f} {1e3 * np.percentile(cpu_arr, 90):11.2f}  {how}")


#: Elastic 12×12 saddles near the grid lines held still (their twist read from the stretch, its
#: interval reaching none on some frames): the twist and its sign from frame to frame.
HELD_STREAM_SPECS = ("saddle:radius=285.7,axis_angle=83.3", "saddle:radius=260,axis_angle=8")


def held_stream_table(frames: int, seed: int, kernels: str = "compiled") -> None:
    """Warm frames of elastic 12×12 saddles held still, as skinmapd streams them: the CPU per
    frame, how many frames carry the twist (not none), how often its sign changes from one frame
    to the next, how many are flagged ambiguous, and the worst mean node error of the better of
    each frame's two answers (after the best rigid alignment)."""
    n = 12
    rng = np.random.default_rng(seed)
    rec = Reconstructor(n, n, PITCH, H, H, GAUGE, kernels=kernels)
    rec.prepare()
    print(f"\nElastic films held still, {n}x{n}, {frames} noisy frames each (reconstruct with previous, as skinmapd runs it)")
    print(f"{'scene':42s} {'cpu median ms':>14s} {'twist':>7s} {'sign changes':>12s} {'flagged':>8s} {'worst mm':>9s}")
    for spec in HELD_STREAM_SPECS:
        shape = scenes.parse_scene_spec(spec, "elastic", n, n, PITCH)
        eu, el = ph.gauge_strains(shape, n, n, PITCH, H, H, GAUGE)
        truth = ph.ground_truth(shape, n, n, PITCH).nodes
        cpu, twists, flagged, worst = [], [], 0, 0.0
        for prev, seconds in _held_frames(rec, eu, el, rng, frames):
            cpu.append(seconds)
            twists.append(prev.diagnostics.twist_constant)
            flagged += prev.mirror is not None
            answers = [prev] + ([prev.mirror] if prev.mirror is not None else [])
            worst = max(worst, min(float(node_errors(a.nodes, truth).mean()) for a in answers))
        tw = np.array(twists)
        carried = np.abs(tw) > 0.5 * np.median(np.abs(tw[tw != 0])) if np.any(tw != 0) else np.zeros(len(tw), bool)
        signs = np.sign(tw[carried])
        changes = int(np.count_nonzero(signs[1:] != signs[:-1]))
        print(f"{spec:42s} {1e3 * np.median(cpu[2:]):14.2f} {int(carried.sum()):>3d}/{frames:<3d} {changes:12d} "
              f"{flagged:>3d}/{frames:<3d} {worst:9.3f}")


def sharp_stream_table(frames: int, seed: int, kernels: str = "compiled") -> None:
    """A bump sharper than the cells (5 mm, FWHM 15 mm) moving 0.5 mm a frame over 12×12 and
    16×16 sheets, each frame reconstructed warm from the one before: the general model misfits
    it, so the first frame fits the height graph cold and the rest warm from it (the rescue of
    larger sheets, docs/reconstruction.md).  CPU of the first frame and the median of the rest,
    then the median with the nodes' σ read too (skinmapd reads it every published frame), mean
    node error, beside the general model alone."""
    print(f"\nA sharp bump moving over a large sheet, {frames} noisy frames (reconstruct with previous; "
          "5 mm high, FWHM 15 mm, 0.5 mm a frame)")
    print(f"{'N x N':>7s} {'model':>22s} {'first frame ms':>15s} {'cpu median ms':>14s} {'cpu p90 ms':>11s} "
          f"{'with node σ ms':>15s} {'mean err mm':>12s} {'graph frames':>13s}")
    for n in (12, 16):
        for label, graph_fit in (("default (graph rescue)", None), ("general model alone", False)):
            rng = np.random.default_rng(seed)
            rec = Reconstructor(n, n, PITCH, H, H, GAUGE, kernels=kernels, graph_fit=graph_fit)
            rec.prepare()
            centres = ph.cell_centres(n, n, PITCH)
            prev, cpu, with_sigma, errs, graphs = None, [], [], [], 0
            for k in range(frames):
                shape = ph.GaussianBumps(height=5.0, fwhm=15.0, centre=(10.0 + 0.5 * k, -5.0))
                eu, el = ph.gauge_strains(shape, n, n, PITCH, H, H, GAUGE)
                du, dl = rng.normal(0, NOISE, eu.shape), rng.normal(0, NOISE, el.shape)
                c0 = time.thread_time()
                prev = rec(eu + du, el + dl, previous=prev)
                prev.nodes, prev.normals
                cpu.append(time.thread_time() - c0)
                prev.node_sigma
                with_sigma.append(time.thread_time() - c0)
                errs.append(float(node_errors(prev.nodes, shape.position(centres)).mean()))
                graphs += prev.diagnostics.extra["model"] == "graph"
            rest = np.array(cpu[1:])
            print(f"{n:>3d}x{n:<3d} {label:>22s} {1e3 * cpu[0]:15.1f} {1e3 * np.median(rest):14.2f} "
                  f"{1e3 * np.percentile(rest, 90):11.2f} {1e3 * np.median(with_sigma[1:]):15.2f} {np.mean(errs):12.4f} "
                  f"{graphs:>6d}/{frames:<6d}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer shapes and frames (about 30 s; the first run also solves the elastic scenes, about 15 s more)")
    ap.add_argument("--seed", type=int, default=2024, help="seed of the random shape parameters and noise")
    ap.add_argument("--shapes", type=int, default=None, help="random shapes per class (default 12, quick 4)")
    ap.add_argument("--only", choices=("accuracy", "elastic", "timing"), default=None,
                    help="print one part only (accuracy: the kinematic accuracy tables; elastic: the elastic-scene tables)")
    ap.add_argument("--sizes", default="5",
                    help="sheet sizes N of the kinematic accuracy tables, comma-separated (default 5; e.g. 5,8,12,16,32)")
    ap.add_argument("--elastic-sizes", default="5",
                    help="sheet sizes N of the elastic tables, comma-separated (default 5; a 16x16 scene takes about "
                         "5-20 s to solve once, then comes from the disk cache)")
    ap.add_argument("--elastic-shapes", type=int, default=None, help="random scenes per elastic class (default 2, quick 1)")
    ap.add_argument("--elastic-classes", default=None,
                    help="the elastic tables' classes, comma-separated keys of bench/elastic_dataset.py (default: all)")
    ap.add_argument("--calibration-draws", type=int, default=None,
                    help="noisy frames a scene of the uncertainty calibration (default 20, quick 8)")
    ap.add_argument("--general", action="store_true",
                    help="the general model alone (graph_fit=False), without the height-graph fit of step 0")
    ap.add_argument("--kernels", choices=("compiled", "numpy"), default="compiled",
                    help="per-frame kernels of the timing table (numpy: the reference implementation)")
    args = ap.parse_args()
    k = args.shapes or (4 if args.quick else 12)
    def sizes(flag: str, text: str) -> list[int]:
        try:
            out = [int(x) for x in text.split(",") if x.strip()]
        except ValueError:
            ap.error(f"{flag} takes integers separated by commas, got {text!r}")
        if not out or min(out) < 2:
            ap.error(f"{flag} takes sizes >= 2, got {text!r}")
        return out

    elastic_sizes = sizes("--elastic-sizes", args.elastic_sizes)
    known = [c[0] for c in ed.CLASSES]
    classes = None if args.elastic_classes is None else [c.strip() for c in args.elastic_classes.split(",") if c.strip()]
    if classes is not None and (not classes or any(c not in known for c in classes)):
        ap.error(f"--elastic-classes takes keys of bench/elastic_dataset.py ({', '.join(known)}), got "
                 f"{args.elastic_classes!r}")
    draws = args.calibration_draws or (8 if args.quick else 20)
    if draws < 2:
        ap.error(f"--calibration-draws takes at least 2 frames, got {args.calibration_draws}")
    kinematic_sizes = sizes("--sizes", args.sizes)
    threadpool_limits(1)
    if args.only in (None, "accuracy"):
        for n in kinematic_sizes:
            accuracy_table(k, 1 if args.quick else 3, args.seed, False if args.general else None, n)
        bump_grid_table(4 if args.quick else 10, args.seed)
        warm_chain_table(40 if args.quick else 100, args.seed)
    if args.only in (None, "elastic"):
        k_el = args.elastic_shapes or (1 if args.quick else 2)
        for n in elastic_sizes:
            elastic_table(n, k_el, 1 if args.quick else 3, args.seed, False if args.general else None, classes)
        for n in elastic_sizes:
            calibration_table(n, k_el, draws, args.seed, False if args.general else None, classes)
    if args.only in ("accuracy", "elastic"):
        return
    frames = {5: 60, 8: 40, 16: 20, 32: 10} if args.quick else {5: 300, 8: 200, 16: 100, 32: 40}
    timing_table([5, 8, 16, 32], frames, args.seed, args.kernels, False if args.general else None)


if __name__ == "__main__":
    main()
