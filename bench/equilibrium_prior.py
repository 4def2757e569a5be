"""The full-position model with the membrane's tangential equilibrium as its prior
(`skinmap.reconstruction.positionfit`), against the default reconstruction, on the independent
elastic scenes of bench/elastic_dataset.py (docs/reconstruction.md, "Elastic films").

Run: .venv/bin/python bench/equilibrium_prior.py [--cases saddle:0,poisson_0.3:1] [--nu true,0.4]
     [--solver cholesky|clarabel] [--max-steps 40] [--bias 0.3] [--reconstructor [--noise S --draws K]]
     [--airy] [--sliding [--seed S]] [--turn [--sizes 8,16]]

Each case is ``class:index`` of bench/elastic_dataset.py (5×5 cells, 12 mm pitch, seed 2024),
noise-free unless ``--noise`` is given.  The fit starts from the default reconstruction's surface.
ν is the scene's own ("true") or a fixed value.  ``--bias`` multiplies one gauge (upper layer,
row-direction gauge of unit (1, 2)) by 1 + bias.  It prints, per case and ν: the default
reconstruction's mean node error after the best rigid alignment, the fit's, the gauges' χ² per
datum (noise s.d. 0.0057 % strain), the equilibrium prior's remaining cost, the fit's steps and
its CPU time (one BLAS thread).

``--reconstructor``: instead, ``Reconstructor(elastic_prior=PositionFitSettings(poisson=ν))`` as a
user runs it (from the answer and its mirror image; the prior's answer only where it holds),
with the default's and its errors, whether the prior was used, the mean node_sigma and whether
the error is within 3σ + 0.05 mm.

``--sliding``: what an elastic film's error is made of (noise-free; ``--seed`` picks the dataset's
scenes): the default answer; the film's true height without its in-plane sliding (a height
graph over the material coordinates); that height slid by the membrane's equilibrium with free
edges (``PositionFit.slide``, its weak form, 2 and 3 knots a pitch, with the CPU time of the
latter); the height fitted to every gauge with the film's true sliding held
(docs/reconstruction.md, "What an elastic film's error is made of").

``--turn``: what the gauges tell of a saddle's turn near the grid lines (noise-free; an N×N film
on a saddle of R 18.75·N mm, the dataset's radius scale): for each turn φ, the χ² between every
gauge of the film turned by φ and of the same saddle along the grid lines (0°: the same Gaussian
curvature, curvatures along the rows and columns 1/cos 2φ times the turned film's), and of its
twin (a saddle of R / cos 2φ along the grid lines: the same curvatures along the rows and
columns, no twist, |K| lower by cos² 2φ), against the sensor's noise; the
default answer's error, its mean node_sigma and its worst node in units of 3σ + 0.05 mm; and
its error once moved along its twist mode (z += c·u·v) by the c that fits the truth best, with
the true twist sin 2φ / R beside it (docs/reconstruction.md, "Limits").
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np
import scipy.linalg as sla
from threadpoolctl import threadpool_limits

sys.path.insert(0, str(Path(__file__).resolve().parent))
import elastic_dataset as ed  # noqa: E402
from reconstruction import GAUGE, H, PITCH, node_errors  # noqa: E402

from skinmap.emulator import physics as ph  # noqa: E402
from skinmap.reconstruction import reconstruct  # noqa: E402
from skinmap.reconstruction.engine import unit_data  # noqa: E402
from skinmap.reconstruction.positionfit import PositionFit, PositionFitSettings, start_from_surface  # noqa: E402

NOISE = 0.0057e-2
DEFAULT_CASES = ",".join(f"{k}:{i}" for k in ("bump", "sphere_convex", "sphere_concave", "saddle", "ridge", "two_bumps",
                                              "cylinder", "sphere_prestretch", "cylinder_prestretch", "poisson_0.3",
                                              "friction_1e-3") for i in (0, 1))


def _scene(key: str, index: int, noise: float, draw: int = 0, seed: int = 2024):
    """The dataset's case: its plan, gauge strains (with the dataset's noise draw), true nodes and
    the solved film."""
    plan = ed.class_plans(key, seed, index + 1, 5)[index]
    shape, _, _ = ed.solve_scene(plan)
    eu, el = ph.gauge_strains(shape, 5, 5, PITCH, H, H, GAUGE)
    if noise > 0:
        nu_, nl_ = ed.noise_draw(plan, draw, noise, eu.shape)
        eu, el = eu + nu_, el + nl_
    return plan, eu, el, ph.ground_truth(shape, 5, 5, PITCH).nodes, shape


def run_case(key: str, index: int, nu_modes: list[str], solver: str, max_steps: int, bias: float, noise: float) -> None:
    plan, eu, el, truth, _ = _scene(key, index, noise)
    if bias:
        eu = eu.copy()
        eu[0, 1, 2] *= 1.0 + bias
    kw = {} if plan.twist_sign is None else {"twist_sign": plan.twist_sign}
    surf = reconstruct(eu, el, PITCH, H, H, **kw)
    default_error = node_errors(surf.nodes, truth).mean()
    turning, stretch, valid = unit_data(eu, el, H, H, GAUGE)
    sig_t, sig_s = np.sqrt(2.0) * NOISE / (2 * H), NOISE * np.sqrt(2 * H * H) / (2 * H)
    true_nu = float(plan.elastic.get("poisson", 0.48))
    for mode in nu_modes:
        nu = true_nu if mode == "true" else float(mode)
        fit = PositionFit(5, 5, PITCH, GAUGE, PositionFitSettings(poisson=nu, step_solver=solver, max_steps=max_steps))
        c0 = start_from_surface(fit, surf)
        t0 = time.process_time()
        res = fit.fit(turning, stretch, valid, sig_t, sig_s, c0)
        seconds = time.process_time() - t0
        error = node_errors(fit.nodes(res.coeffs), truth).mean()
        print(f"| {plan.spec[:52]:52s} | {true_nu:.2f} | {nu:.2f} | {default_error:7.4f} | {error:7.4f} | {res.chi2:8.2g} "
              f"| {res.prior_cost:8.3g} | {res.steps:2d} {res.status:9s} | {1e3 * seconds:6.0f} |", flush=True)


def run_reconstructor(key: str, index: int, nu_modes: list[str], max_steps: int, noise: float,
                      draws: int) -> tuple[int, int]:
    """One case through Reconstructor(elastic_prior=...), per ν and noise draw; returns (runs, covered)."""
    from skinmap.reconstruction import Reconstructor

    covered = runs = 0
    for draw in range(draws):
        plan, eu, el, truth, _ = _scene(key, index, noise, draw)
        kw = {} if plan.twist_sign is None else {"twist_sign": plan.twist_sign}
        sigma_kw = {"strain_sigma": noise} if noise > 0 else {}
        default = reconstruct(eu, el, PITCH, H, H, **kw, **sigma_kw)
        true_nu = float(plan.elastic.get("poisson", 0.48))
        for mode in nu_modes:
            nu = true_nu if mode == "true" else float(mode)
            rec = Reconstructor(5, 5, PITCH, H, H, GAUGE,
                                elastic_prior=PositionFitSettings(poisson=nu, max_steps=max_steps))
            t0 = time.process_time()
            surf = rec(eu, el, **kw, **sigma_kw)
            seconds = time.process_time() - t0
            error = node_errors(surf.nodes, truth).mean()
            sigma = float(surf.node_sigma.mean())
            ok = error <= 3 * sigma + 0.05
            covered, runs = covered + ok, runs + 1
            used = surf.diagnostics.extra.get("elastic_prior", "")
            how = "used" if used == "used" else ("declined (Airy)" if "Airy" in used else ("not decided" if "decided" in used else "declined"))
            print(f"| {plan.spec[:52]:52s} | {draw} | {true_nu:.2f} | {nu:.2f} | {node_errors(default.nodes, truth).mean():7.4f} "
                  f"| {float(default.node_sigma.mean()):6.3f} | {error:7.4f} | {sigma:6.3f} | {'yes' if ok else 'NO'} "
                  f"| {how} | {surf.mirror is not None} | {seconds:5.1f} |", flush=True)
    return runs, covered


def _height_fit(fit: PositionFit, c: np.ndarray, turning: np.ndarray, stretch: np.ndarray, steps: int = 30) -> np.ndarray:
    """The height (c[2]) fitted to every gauge with the in-plane displacement c[:2] held (plain
    Gauss-Newton from the start given).  No frame rows: the held displacement is in the scene's
    frame, not the sensor frame, and the gauges do not see a rigid motion (node_errors aligns)."""
    nb = fit.nb
    data = np.concatenate([turning.ravel(), stretch.ravel()])
    sig_t, sig_s = np.sqrt(2.0) * NOISE / (2 * H), NOISE * np.sqrt(2 * H * H) / (2 * H)
    scale = np.concatenate([np.full(turning.size, sig_t), np.full(stretch.size, sig_s)])
    prior = fit._smooth + 1e-6 * np.eye(nb)
    c = c.copy()
    for _ in range(steps):
        t, s, jt, js = fit.gauge_model(c, jacobian=True)
        r = (np.concatenate([t.ravel(), s.ravel()]) - data) / scale
        j = np.concatenate([jt.reshape(-1, 3 * nb), js.reshape(-1, 3 * nb)])[:, 2 * nb:] / scale[:, None]
        step = sla.solve(j.T @ j + prior, j.T @ r + prior @ c[2], assume_a="pos")
        c[2] -= step
        if float(np.abs(step).max()) < 1e-6:
            break
    return c


def run_sliding(key: str, index: int, seed: int) -> None:
    """What an elastic film's error is made of (noise-free): the default answer; the film's true
    height with no in-plane sliding (a height graph over the material coordinates); that height
    slid by the membrane's equilibrium with free edges (PositionFit.slide, 2 and 3 knots a pitch);
    and the height fitted to every gauge with the film's true sliding held (3 knots a pitch)."""
    plan, eu, el, truth, shape = _scene(key, index, 0.0, seed=seed)
    kw = {} if plan.twist_sign is None else {"twist_sign": plan.twist_sign}
    default = reconstruct(eu, el, PITCH, H, H, **kw)
    nu = float(plan.elastic.get("poisson", 0.48))
    uv, pos = shape.grid.uv().reshape(-1, 2), shape.positions.reshape(-1, 3)
    graph_error = math.nan
    slid_errors, seconds = [], 0.0
    for knots in (2, 3):
        settings = PositionFitSettings(poisson=nu, knots_per_pitch=knots, film_margin=0.5)
        fit = PositionFit(5, 5, PITCH, GAUGE, settings)
        inside = np.all(np.abs(uv) <= fit.ku[-1] + 1e-9, axis=1)
        true_c = fit.coeffs_from_positions(uv[inside, 0], uv[inside, 1], pos[inside])
        graph = true_c.copy()
        graph[:2] = 0.0
        t0 = time.process_time()
        slid = fit.slide(graph)
        seconds = time.process_time() - t0
        slid_errors.append(node_errors(fit.nodes(slid), truth).mean())
        if knots == 2:
            graph_error = node_errors(fit.nodes(graph), truth).mean()
    # the height fitted to the gauges, the film's true sliding held: on the cells alone (the
    # margin's coefficients, which no gauge reaches, would be the smoothness term's to choose)
    cells = PositionFit(5, 5, PITCH, GAUGE, PositionFitSettings(poisson=nu, knots_per_pitch=3))
    inside = np.all(np.abs(uv) <= cells.ku[-1] + 1e-9, axis=1)
    held = cells.coeffs_from_positions(uv[inside, 0], uv[inside, 1], pos[inside])
    held[2] = start_from_surface(cells, default)[2]  # the height from the default answer's
    turning, stretch, _ = unit_data(eu, el, H, H, GAUGE)
    held_error = node_errors(cells.nodes(_height_fit(cells, held, turning, stretch)), truth).mean()
    print(f"| {plan.spec[:52]:52s} | {node_errors(default.nodes, truth).mean():7.4f} | {graph_error:7.4f} "
          f"| {slid_errors[0]:7.4f} | {slid_errors[1]:7.4f} | {held_error:7.4f} | {seconds:5.1f} |", flush=True)


def run_airy(key: str, index: int, noise: float) -> None:
    """The stretch pattern's Gaussian curvature against the scene's own (mean over the units' hull)."""
    from skinmap.reconstruction.airy import airy_gaussian_curvature
    from skinmap.reconstruction.engine import unit_data as units

    plan, eu, el, _, shape = _scene(key, index, noise)
    nu = float(plan.elastic.get("poisson", 0.48))
    _, stretch, valid = units(eu, el, H, H, GAUGE)
    k, sd = airy_gaussian_curvature(stretch, valid, PITCH, nu)
    # the film's own mean K over the units' hull, from its true surface
    fit = PositionFit(5, 5, PITCH, GAUGE, PositionFitSettings(poisson=nu))
    u = np.linspace(-30, 30, 61)
    uu, vv = (a.ravel() for a in np.meshgrid(u, u))
    true_k = fit.mean_gaussian_curvature(fit.coeffs_from_positions(uu, vv, shape.position(np.stack([uu, vv], axis=-1))))
    print(f"| {plan.spec[:52]:52s} | {true_k:10.3e} | {k:10.3e} | {sd:8.1e} | {k / true_k if true_k else float('nan'):6.3f} |")


def run_turn(n: int, angles: list[float]) -> None:
    """The turn table's rows for one sheet size (``--turn``)."""
    radius = 18.75 * n

    def film(r: float, angle: float):
        return ed.scenes.parse_scene_spec(f"saddle:radius={r:.6g},axis_angle={angle:g}", "elastic", n, n, PITCH)

    def chi2(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray]) -> float:
        return float(sum(np.sum((x - y) ** 2) for x, y in zip(a, b)) / NOISE ** 2)

    untwisted = ph.gauge_strains(film(radius, 0.0), n, n, PITCH, H, H, GAUGE)
    for a in angles:
        turned = film(radius, a)
        # the twin: the same curvatures along the grid lines (cos 2φ / R), no twist, so |K| lower
        twin = ph.gauge_strains(film(radius / math.cos(math.radians(2.0 * a)), 0.0), n, n, PITCH, H, H, GAUGE)
        eu, el = ph.gauge_strains(turned, n, n, PITCH, H, H, GAUGE)
        truth = ph.ground_truth(turned, n, n, PITCH).nodes.reshape(-1, 3)
        surf = reconstruct(eu, el, PITCH, H, H, strain_sigma=NOISE)
        nodes = surf.nodes.reshape(-1, 3)
        errors = node_errors(nodes, truth)
        worst = float(np.max(errors / (3.0 * surf.node_sigma.reshape(-1) + 0.05)))
        twist = math.sin(math.radians(2.0 * a)) / radius
        mode = np.outer(nodes[:, 0] * nodes[:, 1], [0.0, 0.0, 1.0])
        shifts = np.linspace(-2.0 * abs(twist) - 1e-5, 2.0 * abs(twist) + 1e-5, 201)
        moved = [node_errors(nodes + c * mode, truth).mean() for c in shifts]
        best = int(np.argmin(moved))
        print(f"| {n}×{n}, R {radius:g} mm | {a:g}° | {chi2((eu, el), untwisted):.3g} | {chi2((eu, el), twin):.3g} | "
              f"{errors.mean():.4f} | {surf.node_sigma.mean():.3f} | {worst:.2f} | {moved[best]:.4f} | "
              f"{shifts[best]:.3g} | {twist:.3g} |")


def _table_head(*cells: str) -> None:
    """A markdown table's header and rule."""
    print("| " + " | ".join(cells) + " |")
    print("|" + "---|" * len(cells))


def _cases(text: str) -> list[tuple[str, int]]:
    """``class:index,...`` as (class, index) pairs."""
    return [(key, int(index)) for key, index in (case.split(":") for case in text.split(","))]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default=DEFAULT_CASES, help="class:index of bench/elastic_dataset.py, comma-separated")
    ap.add_argument("--nu", default="true", help="Poisson's ratio of the prior: true (the scene's) or numbers, comma-separated")
    ap.add_argument("--solver", choices=("cholesky", "clarabel"), default="cholesky", help="step solver")
    ap.add_argument("--max-steps", type=int, default=60)
    ap.add_argument("--bias", type=float, default=0.0, help="relative gain error of one gauge")
    ap.add_argument("--noise", type=float, default=0.0, help="strain noise s.d. (the dataset's draw 0)")
    ap.add_argument("--draws", type=int, default=1, help="noise draws per case (with --noise, --reconstructor)")
    ap.add_argument("--reconstructor", action="store_true", help="through Reconstructor(elastic_prior=...)")
    ap.add_argument("--airy", action="store_true", help="the stretch pattern's Gaussian curvature against the film's")
    ap.add_argument("--sliding", action="store_true",
                    help="what the error is made of: the film's height without its in-plane sliding, slid by the "
                         "membrane's equilibrium, and fitted to the gauges with its true sliding held (noise-free)")
    ap.add_argument("--seed", type=int, default=2024, help="seed of the dataset's scenes (--sliding)")
    ap.add_argument("--turn", action="store_true",
                    help="what the gauges tell of a saddle's turn near the grid lines (noise-free)")
    ap.add_argument("--sizes", default="8,16", help="sheet sizes N of --turn, comma-separated")
    args = ap.parse_args()
    if args.turn:
        _table_head("film", "turn", "χ² against 0°", "χ² against the twin", "default mm", "mean σ",
                    "worst / (3σ + 0.05)", "moved along the twist mode mm", "by c /mm", "true twist /mm")
        with threadpool_limits(1):
            for size in args.sizes.split(","):
                run_turn(int(size), [1.0, 2.0, 5.0])
        return
    if args.sliding:
        _table_head("scene", "default mm", "height, no sliding", "slid, 2 knots/pitch", "slid, 3",
                    "height fitted, true sliding held", "CPU s (3)")
        with threadpool_limits(1):
            for key, index in _cases(args.cases):
                run_sliding(key, index, args.seed)
        return
    if args.airy:
        _table_head("scene", "film's mean K 1/mm²", "Airy K", "s.d.", "ratio")
        for key, index in _cases(args.cases):
            run_airy(key, index, args.noise)
        return
    if args.reconstructor:
        _table_head("scene", "draw", "film ν", "prior ν", "default mm", "default σ", "elastic prior mm", "σ",
                    "≤ 3σ + 0.05", "prior", "mirror kept", "CPU s")
        total = covered = 0
        with threadpool_limits(1):
            for key, index in _cases(args.cases):
                n_cases, n_ok = run_reconstructor(key, index, args.nu.split(","), args.max_steps, args.noise,
                                                  args.draws if args.noise > 0 else 1)
                total, covered = total + n_cases, covered + n_ok
        print(f"within 3 sigma + 0.05 mm: {covered} of {total}")
        return
    _table_head("scene", "film ν", "prior ν", "default mm", "position fit mm", "χ²/datum", "prior cost", "steps",
                "CPU ms")
    with threadpool_limits(1):
        for key, index in _cases(args.cases):
            run_case(key, index, args.nu.split(","), args.solver, args.max_steps, args.bias, args.noise)


if __name__ == "__main__":
    main()
